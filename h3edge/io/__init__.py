"""Input layer: RGB-D sequence readers behind one :class:`~h3edge.io.sequence.Sequence` interface."""

from __future__ import annotations

from pathlib import Path

from h3edge.io.sequence import DatasetError, Frame, Sequence


def open_sequence(path: str | Path) -> Sequence:
    """Open a dataset folder, detecting its layout: TUM (``rgb.txt``) or Replica / own (``traj.txt``)."""
    from h3edge.io.replica import ReplicaSequence
    from h3edge.io.tum import TUMSequence

    p = Path(path)
    if (p / "rgb.txt").is_file():
        return TUMSequence(p)
    if (p / "traj.txt").is_file():
        return ReplicaSequence(p)
    raise DatasetError(f"{p}: not a dataset (no rgb.txt for TUM, no traj.txt for Replica / h3edge format)")


__all__ = ["DatasetError", "Frame", "Sequence", "open_sequence"]
