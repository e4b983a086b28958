"""The RGB-D input interface: :class:`Frame`, the :class:`Sequence` protocol and shared helpers.

A frame is colour uint8 (H, W, 3) RGB, depth float32 metres (H, W) with 0 = invalid, a
camera-to-world 4x4 pose (OpenCV camera axes), a timestamp in seconds and pinhole intrinsics.
Readers validate as they load and raise :class:`DatasetError` naming the file (and line).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from h3edge.errors import InputError
from h3edge.geometry.camera import Intrinsics, rigid_error


class DatasetError(InputError):
    """A malformed dataset: the message names the file and, where it applies, the line."""


@dataclass
class Frame:
    index: int
    timestamp: float
    color: np.ndarray  # uint8 (H, W, 3) RGB
    depth: np.ndarray  # float32 (H, W) metres, 0 = invalid
    pose: np.ndarray  # float64 (4, 4) camera-to-world
    intrinsics: Intrinsics


@runtime_checkable
class Sequence(Protocol):
    """Random-access RGB-D sequence."""

    intrinsics: Intrinsics
    root: Path

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> Frame: ...

    def __iter__(self) -> Iterator[Frame]: ...

    @property
    def poses(self) -> np.ndarray: ...

    @property
    def gt_mesh_path(self) -> Path | None: ...


class SequenceBase:
    """Iteration and bounds checks shared by the readers."""

    intrinsics: Intrinsics
    root: Path

    def __len__(self) -> int:
        raise NotImplementedError

    def _load(self, i: int) -> Frame:
        raise NotImplementedError

    def __getitem__(self, i: int) -> Frame:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range for a sequence of {len(self)} frames")
        return self._load(i % len(self))

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self._load(i)

    @property
    def gt_mesh_path(self) -> Path | None:
        return None


def read_color(path: Path, intr: Intrinsics) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(f"{path}: colour image missing")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(f"{path}: cannot decode colour image")
    if img.shape[:2] != (intr.height, intr.width):
        raise DatasetError(f"{path}: colour is {img.shape[1]}x{img.shape[0]}, intrinsics say "
                           f"{intr.width}x{intr.height}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: Path, intr: Intrinsics, scale: float) -> np.ndarray:
    """16-bit depth PNG -> float32 metres (value / scale), 0 stays invalid."""
    if not path.is_file():
        raise DatasetError(f"{path}: depth image missing")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DatasetError(f"{path}: cannot decode depth image")
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise DatasetError(f"{path}: depth must be single-channel 16-bit, got {raw.dtype} {raw.shape}")
    if raw.shape != (intr.height, intr.width):
        raise DatasetError(f"{path}: depth is {raw.shape[1]}x{raw.shape[0]}, intrinsics say "
                           f"{intr.width}x{intr.height}")
    return raw.astype(np.float32) / np.float32(scale)


def write_depth(path: Path, depth: np.ndarray, scale: float) -> None:
    """float32 metres -> 16-bit PNG (value = round(depth * scale)); out-of-range becomes 0."""
    d = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0) * scale
    d = np.where(d > 65535, 0, np.rint(d))
    if not cv2.imwrite(str(path), d.astype(np.uint16)):
        raise OSError(f"{path}: cannot write depth PNG")


def write_color(path: Path, rgb: np.ndarray, jpeg_quality: int = 95) -> None:
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if path.suffix.lower() in (".jpg", ".jpeg") else []
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params):
        raise OSError(f"{path}: cannot write colour image")


def read_pose_rows(path: Path) -> np.ndarray:
    """``traj.txt``: one row-major camera-to-world 4x4 per line (16 numbers) -> (N, 4, 4)."""
    if not path.is_file():
        raise DatasetError(f"{path}: trajectory file missing")
    poses = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            vals = np.array([float(v) for v in line.split()])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: pose row is not numeric") from None
        if vals.size != 16:
            raise DatasetError(f"{path}:{lineno}: pose row has {vals.size} numbers, expected 16")
        T = vals.reshape(4, 4)
        why = rigid_error(T)
        if why:
            raise DatasetError(f"{path}:{lineno}: pose is not a rigid transform: {why}")
        poses.append(T)
    if not poses:
        raise DatasetError(f"{path}: no poses")
    return np.stack(poses)


def write_pose_rows(path: Path, poses: np.ndarray) -> None:
    path.write_text("".join(" ".join(f"{v:.9g}" for v in T.reshape(-1)) + "\n" for T in poses))
