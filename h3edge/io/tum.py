"""Reader for TUM RGB-D sequences (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``).

Each colour image is paired with the depth image nearest in time (within ``max_dt``, as TUM's
associate.py does) and with a ground-truth pose interpolated at the colour timestamp (SLERP +
linear between the bracketing GT rows, at most ``max_pose_gap`` seconds apart). Colour frames with
no depth or pose in reach are skipped and counted in ``skipped``. Depth PNGs are metres x 5000.
Intrinsics: ``intrinsics.json`` beside the files, else the published values of the
freiburg1/2/3 camera named in the folder name. Lens distortion is not modelled.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from h3edge.geometry.camera import Intrinsics, rigid_error
from h3edge.geometry.poses import interpolate_pose, pose_from_tq
from h3edge.io.sequence import DatasetError, Frame, SequenceBase, read_color, read_depth

log = logging.getLogger(__name__)
TUM_DEPTH_SCALE = 5000.0
# Published ROS-default calibrations of the TUM RGB-D cameras (640x480).
TUM_CAMERAS = {
    "freiburg1": Intrinsics(640, 480, 517.3, 516.5, 318.6, 255.3),
    "freiburg2": Intrinsics(640, 480, 520.9, 521.0, 325.1, 249.7),
    "freiburg3": Intrinsics(640, 480, 535.4, 539.2, 320.1, 247.6),
}


def _read_list(path: Path, min_cols: int) -> list[tuple[int, list[str]]]:
    if not path.is_file():
        raise DatasetError(f"{path}: file missing")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        cols = line.split()
        if len(cols) < min_cols:
            raise DatasetError(f"{path}:{lineno}: expected {min_cols} columns, got {len(cols)}")
        try:
            float(cols[0])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: timestamp {cols[0]!r} is not numeric") from None
        rows.append((lineno, cols))
    if not rows:
        raise DatasetError(f"{path}: no entries")
    return rows


class TUMSequence(SequenceBase):
    def __init__(self, root: str | Path, max_dt: float = 0.02, max_pose_gap: float = 0.1):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: not a directory")
        self.intrinsics = self._intrinsics()
        self.depth_scale = TUM_DEPTH_SCALE
        rgb = _read_list(self.root / "rgb.txt", 2)
        depth = _read_list(self.root / "depth.txt", 2)
        gt_path = self.root / "groundtruth.txt"
        gt = _read_list(gt_path, 8)
        gt_t = np.array([float(c[0]) for _, c in gt])
        gt_T = []
        for lineno, c in gt:
            try:
                vals = [float(v) for v in c[1:8]]
                T = pose_from_tq(np.array(vals[:3]), np.array(vals[3:7]))
            except ValueError as e:
                raise DatasetError(f"{gt_path}:{lineno}: bad pose row: {e}") from None
            why = rigid_error(T)
            if why:
                raise DatasetError(f"{gt_path}:{lineno}: pose is not rigid: {why}")
            gt_T.append(T)
        if np.any(np.diff(gt_t) <= 0):
            bad = int(np.argmax(np.diff(gt_t) <= 0)) + 1
            raise DatasetError(f"{gt_path}:{gt[bad][0]}: timestamps not strictly increasing")
        gt_T = np.stack(gt_T)
        d_t = np.array([float(c[0]) for _, c in depth])
        order = np.argsort(d_t)
        d_t, d_files = d_t[order], [depth[i][1][1] for i in order]

        self._items: list[tuple[float, Path, Path, np.ndarray]] = []
        self.skipped = {"no_depth": 0, "no_pose": 0}
        for _, c in rgb:
            t = float(c[0])
            j = int(np.clip(np.searchsorted(d_t, t), 1, len(d_t) - 1)) if len(d_t) > 1 else 0
            cand = [k for k in (j - 1, j) if 0 <= k < len(d_t)]
            k = min(cand, key=lambda k: abs(d_t[k] - t))
            if abs(d_t[k] - t) > max_dt:
                self.skipped["no_depth"] += 1
                continue
            pose = self._pose_at(t, gt_t, gt_T, max_pose_gap)
            if pose is None:
                self.skipped["no_pose"] += 1
                continue
            self._items.append((t, self.root / c[1], self.root / d_files[k], pose))
        if not self._items:
            raise DatasetError(f"{self.root}: no colour frame has both depth and a pose in reach")
        if any(self.skipped.values()):
            log.info("%s: skipped colour frames %s", self.root, self.skipped)

    def _intrinsics(self) -> Intrinsics:
        p = self.root / "intrinsics.json"
        if p.is_file():
            try:
                d = json.loads(p.read_text())
                return Intrinsics(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]),
                                  float(d["cx"]), float(d["cy"]))
            except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
                raise DatasetError(f"{p}: invalid intrinsics: {e}") from None
        for key, intr in TUM_CAMERAS.items():
            if key in self.root.name:
                return intr
        raise DatasetError(f"{self.root}: no intrinsics.json and no freiburg1/2/3 in the folder name")

    @staticmethod
    def _pose_at(t: float, gt_t: np.ndarray, gt_T: np.ndarray, max_gap: float) -> np.ndarray | None:
        j = int(np.searchsorted(gt_t, t))
        if j < len(gt_t) and gt_t[j] == t:
            return gt_T[j].copy()
        if j == 0 or j == len(gt_t) or gt_t[j] - gt_t[j - 1] > max_gap:
            return None
        alpha = (t - gt_t[j - 1]) / (gt_t[j] - gt_t[j - 1])
        return interpolate_pose(gt_T[j - 1], gt_T[j], alpha)

    def __len__(self) -> int:
        return len(self._items)

    @property
    def poses(self) -> np.ndarray:
        return np.stack([it[3] for it in self._items])

    @property
    def timestamps(self) -> np.ndarray:
        return np.array([it[0] for it in self._items])

    def _load(self, i: int) -> Frame:
        t, cpath, dpath, pose = self._items[i]
        return Frame(i, t, read_color(cpath, self.intrinsics), read_depth(dpath, self.intrinsics, self.depth_scale),
                     pose.copy(), self.intrinsics)
