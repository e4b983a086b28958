"""Input layer: RGB-D sequence readers behind one :class:`~h3edge.io.sequence.Sequence` interface
(Replica / own, TUM, ScanNet, rosbag2), the wire protocol, ROS 2 message conversion, the OAK source."""

from __future__ import annotations

from pathlib import Path

from h3edge.io.sequence import DatasetError, Frame, Sequence


def open_sequence(path: str | Path, ros=None) -> Sequence:
    """Open a dataset, detecting its layout: a rosbag2 recording (a folder with ``metadata.yaml``,
    an ``.mcap`` or ``.db3`` file; read with the topic options ``ros``, a
    :class:`~h3edge.io.ros.RosConfig`), a ScanNet export (``color/``, ``depth/``, ``pose/``,
    ``intrinsic/``), TUM (``rgb.txt``) or Replica / own (``traj.txt``)."""
    from h3edge.io.replica import ReplicaSequence
    from h3edge.io.rosbag import RosbagSequence, is_rosbag
    from h3edge.io.scannet import ScanNetSequence, is_scannet
    from h3edge.io.tum import TUMSequence

    p = Path(path)
    if is_rosbag(p):
        from h3edge.io.ros import RosConfig

        return RosbagSequence(p, ros if ros is not None else RosConfig())
    if is_scannet(p):
        return ScanNetSequence(p)
    if (p / "rgb.txt").is_file():
        return TUMSequence(p)
    if (p / "traj.txt").is_file():
        return ReplicaSequence(p)
    raise DatasetError(f"{p}: not a dataset (a rosbag2 folder / .mcap / .db3, a ScanNet export, rgb.txt for TUM, "
                       "traj.txt for Replica / h3edge format)")


__all__ = ["DatasetError", "Frame", "Sequence", "open_sequence"]
