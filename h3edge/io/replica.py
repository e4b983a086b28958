"""Reader for the Replica layout as NICE-SLAM ships it, and for h3edge's own format built on it.

Layout: ``results/frameNNNNNN.jpg`` (or .png), ``results/depthNNNNNN.png`` (uint16, metres =
value / depth scale, Replica 6553.5), ``traj.txt`` (one row-major camera-to-world 4x4 per line,
row i = frame i). Intrinsics come from, in order: ``intrinsics.json`` (own format), a
``cam_params.json`` (nvblox / NICE-SLAM ``{"camera": {w, h, fx, fy, cx, cy, scale}}``) or a
NICE-SLAM YAML with a ``cam:`` block, in the folder or its parent.

The own format adds ``intrinsics.json`` ``{width, height, fx, fy, cx, cy, depth_scale}``, an
optional ``timestamps.txt`` (seconds, one per frame), an optional ``gt_mesh.ply`` and an optional
``heldout/`` sub-sequence in the same layout (evaluation views between training views).
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np
import yaml

from h3edge.geometry.camera import Intrinsics
from h3edge.io.sequence import DatasetError, Frame, SequenceBase, read_color, read_depth, read_pose_rows

log = logging.getLogger(__name__)
_FRAME_RE = re.compile(r"^frame(\d+)\.(jpg|jpeg|png)$", re.IGNORECASE)
REPLICA_DEPTH_SCALE = 6553.5


def _intrinsics_from_file(path: Path) -> tuple[Intrinsics, float]:
    try:
        if path.suffix == ".json":
            d = json.loads(path.read_text())
        else:
            d = yaml.safe_load(path.read_text())
    except (json.JSONDecodeError, yaml.YAMLError) as e:
        raise DatasetError(f"{path}: cannot parse intrinsics: {e}") from None
    try:
        if "camera" in d:  # nvblox / NICE-SLAM cam_params.json
            c = d["camera"]
            return Intrinsics(int(c["w"]), int(c["h"]), float(c["fx"]), float(c["fy"]), float(c["cx"]),
                              float(c["cy"])), float(c.get("scale", REPLICA_DEPTH_SCALE))
        if "cam" in d:  # NICE-SLAM YAML config
            c = d["cam"]
            return Intrinsics(int(c["W"]), int(c["H"]), float(c["fx"]), float(c["fy"]), float(c["cx"]),
                              float(c["cy"])), float(c.get("png_depth_scale", REPLICA_DEPTH_SCALE))
        return Intrinsics(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]), float(d["cx"]),
                          float(d["cy"])), float(d["depth_scale"])
    except (KeyError, TypeError) as e:
        raise DatasetError(f"{path}: intrinsics field missing: {e}") from None
    except ValueError as e:
        raise DatasetError(f"{path}: invalid intrinsics: {e}") from None


def find_intrinsics(root: Path) -> Path:
    for folder in (root, root.parent):
        for name in ("intrinsics.json", "cam_params.json"):
            if (folder / name).is_file():
                return folder / name
        for y in sorted(folder.glob("*.yaml")) + sorted(folder.glob("*.yml")):
            try:
                if "cam" in (yaml.safe_load(y.read_text()) or {}):
                    return y
            except yaml.YAMLError:
                continue
    raise DatasetError(f"{root}: no intrinsics.json, cam_params.json or YAML with a 'cam' block here or in the parent")


class ReplicaSequence(SequenceBase):
    """Replica / own-format folder. Frames are the colour images found; row i of traj.txt is frame i."""

    def __init__(self, root: str | Path, intrinsics_file: str | Path | None = None, fps: float = 30.0):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: not a directory")
        ipath = Path(intrinsics_file) if intrinsics_file else find_intrinsics(self.root)
        self.intrinsics, self.depth_scale = _intrinsics_from_file(ipath)
        results = self.root / "results"
        if not results.is_dir():
            raise DatasetError(f"{results}: folder missing")
        self._color: dict[int, Path] = {}
        for p in results.iterdir():
            m = _FRAME_RE.match(p.name)
            if m:
                self._color[int(m.group(1))] = p
        if not self._color:
            raise DatasetError(f"{results}: no frameNNNNNN.jpg/png images")
        self._ids = sorted(self._color)
        all_poses = read_pose_rows(self.root / "traj.txt")
        if self._ids[-1] >= len(all_poses):
            raise DatasetError(f"{self.root / 'traj.txt'}: {len(all_poses)} pose rows, but frame "
                               f"{self._ids[-1]} needs row {self._ids[-1] + 1}")
        if len(all_poses) > len(self._ids):
            log.debug("%s: %d poses for %d frames", self.root, len(all_poses), len(self._ids))
        self.trajectory = all_poses  # every pose row, also those without images
        self._poses = all_poses[self._ids]
        self._timestamps = self._read_timestamps(fps)

    def _read_timestamps(self, fps: float) -> np.ndarray:
        path = self.root / "timestamps.txt"
        if not path.is_file():
            return np.asarray(self._ids, float) / fps
        vals = []
        for lineno, line in enumerate(path.read_text().splitlines(), start=1):
            if line.strip():
                try:
                    vals.append(float(line.split()[0]))
                except ValueError:
                    raise DatasetError(f"{path}:{lineno}: timestamp is not numeric") from None
        vals = np.asarray(vals)
        if len(vals) <= self._ids[-1]:
            raise DatasetError(f"{path}: {len(vals)} timestamps for frame ids up to {self._ids[-1]}")
        return vals[self._ids]

    def __len__(self) -> int:
        return len(self._ids)

    @property
    def poses(self) -> np.ndarray:
        return self._poses

    @property
    def timestamps(self) -> np.ndarray:
        return self._timestamps

    @property
    def gt_mesh_path(self) -> Path | None:
        p = self.root / "gt_mesh.ply"
        return p if p.is_file() else None

    @property
    def heldout(self) -> ReplicaSequence | None:
        """Held-out evaluation views of the own format (``heldout/``), or None."""
        h = self.root / "heldout"
        return ReplicaSequence(h) if h.is_dir() else None

    def _load(self, i: int) -> Frame:
        fid = self._ids[i]
        color = read_color(self._color[fid], self.intrinsics)
        depth = read_depth(self.root / "results" / f"depth{fid:06d}.png", self.intrinsics, self.depth_scale)
        return Frame(fid, float(self._timestamps[i]), color, depth, self._poses[i].copy(), self.intrinsics)
