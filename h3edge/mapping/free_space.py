"""Observed free space: the leaf-voxel cells that depth rays have passed through.

The H3 representation allocates voxels only around measured surfaces, so away from them it cannot
tell free space from space never seen. A planner needs the difference: this record keeps, at the
leaf voxel size, every cell a sampled depth ray crossed in front of its surface (from the camera
to ``depth - truncation``), so queries can answer *free* there and *unknown* elsewhere. Rays with
no valid depth mark nothing (a missing return is not evidence of free space).

Per frame it samples the pixels on a ``stride`` grid at half a voxel along each ray (neighbouring
rays are ``stride * z / f`` apart at depth z: 16 px on a 525 px Kinect is 9 cm at 3 m; farther
cells one frame's rays skip are filled by the next views, and a cell no sampled ray ever crossed
stays unknown); the cells are
kept in a sorted key index (:class:`~h3edge.mapping.voxels.KeyIndex`), at most ``max_cells``
(new cells past the cap are not recorded and counted in ``refused``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from h3edge.geometry.camera import Intrinsics, pixel_rays_camera
from h3edge.mapping._march_kernels import ray_cell_keys
from h3edge.mapping.voxels import KeyIndex, pack


@dataclass(frozen=True)
class FreeSpaceConfig:
    enabled: bool = True
    """record the 10 cm cells depth rays crossed (observed free space) for distance queries and slices"""
    stride: int = 16
    """px: stride of the rays that mark observed free space (16 records 97 % of stride 8's cells, ~2 ms a frame)"""
    max_cells: int = 2_000_000
    """cap (24 bytes a cell)"""


class FreeSpace:
    """Cells observed free; ``mark`` per frame, ``contains`` per query."""

    def __init__(self, cfg: FreeSpaceConfig, voxel_size: float, truncation: float):
        self.cfg, self.voxel_size, self.truncation = cfg, voxel_size, truncation
        self.cells = KeyIndex()
        self.refused = 0

    def __len__(self) -> int:
        return len(self.cells)

    @property
    def nbytes(self) -> int:
        return 3 * 8 * len(self.cells)

    def mark(self, depth: np.ndarray, intr: Intrinsics, pose: np.ndarray) -> int:
        """Record the cells the frame's sampled rays cross in front of their surface; returns how
        many were new. ``depth``: cleaned z-depth (0 = invalid), ``pose``: camera-to-world."""
        if not self.cfg.enabled:
            return 0
        s = self.cfg.stride
        z = depth[s // 2::s, s // 2::s].reshape(-1)
        rays = pixel_rays_camera(intr, s).reshape(-1, 3)  # z = 1, the same pixels as z
        ok = z > self.truncation
        z, rays = z[ok], rays[ok]
        if len(z) == 0:
            return 0
        pose = np.asarray(pose, np.float64)
        keys = np.unique(ray_cell_keys(np.ascontiguousarray(rays), z.astype(np.float64) - self.truncation,
                                        np.ascontiguousarray(pose[:3, :3]), np.ascontiguousarray(pose[:3, 3]),
                                        self.voxel_size))
        new = keys[self.cells.find(keys) < 0]
        room = self.cfg.max_cells - len(self.cells)
        if len(new) > room:
            self.refused += len(new) - max(room, 0)
            new = new[: max(room, 0)]
        if len(new):
            self.cells.add(new)
        return len(new)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Bool (N,): the cell of each point (metres) was observed free."""
        keys = pack(np.floor(np.asarray(points, np.float64) / self.voxel_size).astype(np.int64))
        return self.cells.find(keys) >= 0

    def state_dict(self) -> tuple[dict, dict[str, np.ndarray]]:
        return {"free_refused": self.refused}, {"keys": self.cells.state_dict()}

    def load_state_dict(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        self.cells.load_state_dict(np.asarray(arrays["keys"], np.int64))
        self.refused = int(meta.get("free_refused", 0))
