"""Reader for ScanNet exports (the layout ScanNet's SensReader writes, used by NICE-SLAM and the
H3-Mapping authors): ``color/<i>.jpg``, ``depth/<i>.png`` (uint16 millimetres), ``pose/<i>.txt``
(camera-to-world 4x4, OpenCV axes), ``intrinsic/intrinsic_depth.txt`` (4x4, K in its top-left) and
``intrinsic/intrinsic_color.txt``.

Colour (1296x968 in ScanNet) and depth (640x480) differ in size: as the authors do, colour is
resized to the depth image and the depth intrinsics are used. Frames whose pose is not finite
(ScanNet marks lost tracking with ``-inf``) or not rigid are left out, counted in
:attr:`ScanNetSequence.skipped`. There are no timestamps: frame ``i`` is stamped ``i / fps``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from h3edge.geometry.camera import Intrinsics, rigid_error
from h3edge.io.sequence import DatasetError, Frame, SequenceBase, read_depth, write_color, write_depth

log = logging.getLogger(__name__)
SCANNET_DEPTH_SCALE = 1000.0
SCANNET_FPS = 30.0


def is_scannet(path: Path) -> bool:
    p = Path(path)
    return all((p / d).is_dir() for d in ("color", "depth", "pose")) and (p / "intrinsic").is_dir()


def _matrix(path: Path) -> np.ndarray:
    try:
        m = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError) as e:
        raise DatasetError(f"{path}: cannot read a 4x4 matrix ({e})") from None
    if m.shape != (4, 4):
        raise DatasetError(f"{path}: expected a 4x4 matrix, got shape {m.shape}")
    return m


class ScanNetSequence(SequenceBase):
    def __init__(self, root: str | Path, fps: float = SCANNET_FPS):
        self.root = Path(root)
        if not is_scannet(self.root):
            raise DatasetError(f"{self.root}: not a ScanNet export (color/, depth/, pose/, intrinsic/)")
        ids = sorted(int(p.stem) for p in (self.root / "depth").glob("*.png") if p.stem.isdigit())
        if not ids:
            raise DatasetError(f"{self.root}/depth: no <i>.png depth images")
        K = _matrix(self.root / "intrinsic" / "intrinsic_depth.txt")
        first = cv2.imread(str(self.root / "depth" / f"{ids[0]}.png"), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise DatasetError(f"{self.root}/depth/{ids[0]}.png: cannot decode")
        h, w = first.shape[:2]
        self.intrinsics = Intrinsics(w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        self.fps = fps
        self.skipped: dict[str, int] = {}
        self._ids, poses = [], []
        for i in ids:
            pose_path = self.root / "pose" / f"{i}.txt"
            if not pose_path.is_file():
                self.skipped["no_pose"] = self.skipped.get("no_pose", 0) + 1
                continue
            T = _matrix(pose_path)
            if not np.isfinite(T).all() or rigid_error(T):
                self.skipped["invalid_pose"] = self.skipped.get("invalid_pose", 0) + 1
                continue
            self._ids.append(i)
            poses.append(T)
        if not self._ids:
            raise DatasetError(f"{self.root}: no frame with a valid pose")
        self._poses = np.stack(poses)
        if self.skipped:
            log.info("%s: %d frames; left out %s", self.root, len(self._ids), self.skipped)

    def __len__(self) -> int:
        return len(self._ids)

    @property
    def poses(self) -> np.ndarray:
        return self._poses.copy()

    def _load(self, i: int) -> Frame:
        n = self._ids[i]
        path = self.root / "color" / f"{n}.jpg"
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise DatasetError(f"{path}: colour image missing or not decodable")
        intr = self.intrinsics
        if img.shape[:2] != (intr.height, intr.width):
            img = cv2.resize(img, (intr.width, intr.height), interpolation=cv2.INTER_AREA)
        depth = read_depth(self.root / "depth" / f"{n}.png", intr, SCANNET_DEPTH_SCALE)
        return Frame(i, n / self.fps, cv2.cvtColor(img, cv2.COLOR_BGR2RGB), depth, self._poses[i].copy(), intr)


def write_scannet(seq, out: str | Path, color_scale: float = 2.025) -> Path:
    """Write ``seq`` in the ScanNet export layout (colour upscaled by ``color_scale``, as ScanNet's
    1296x968 colour is to its 640x480 depth); for tests and for trying the reader."""
    out = Path(out)
    for d in ("color", "depth", "pose", "intrinsic"):
        (out / d).mkdir(parents=True, exist_ok=True)
    intr = seq.intrinsics
    K = np.eye(4)
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = intr.fx, intr.fy, intr.cx, intr.cy
    np.savetxt(out / "intrinsic" / "intrinsic_depth.txt", K)
    Kc = K.copy()
    Kc[:2] *= color_scale
    np.savetxt(out / "intrinsic" / "intrinsic_color.txt", Kc)
    for i in range(len(seq)):
        f = seq[i]
        big = cv2.resize(f.color, (round(intr.width * color_scale), round(intr.height * color_scale)),
                         interpolation=cv2.INTER_CUBIC)
        write_color(out / "color" / f"{i}.jpg", big, 95)
        write_depth(out / "depth" / f"{i}.png", f.depth, SCANNET_DEPTH_SCALE)
        np.savetxt(out / "pose" / f"{i}.txt", f.pose)
    return out
