"""Cross-view free space: a frame's depth pooled into blocks, and which points another view saw through.

A band sample behind the measured depth of its own ray takes a negative SDF target ("inside").
Behind a thin object (a chair leg, a slat, a shelf edge) that is wrong: the object ends a few
centimetres behind its front face, and another view that looks past it sees the wall beyond.
:func:`seen_through` answers, for points, whether any of a set of views measured a depth more than
``margin`` beyond them along its own ray, from each view's depth pooled to its block minimum (a
block with any invalid pixel knows nothing), so that a claim of free space near a depth edge is
conservative: every pixel of the block saw past the point.

The pooling runs once per frame as a numba kernel (:mod:`h3edge.mapping._pool_kernel`); the
test runs in every training step as batched torch ops on the points' device (one projection of
every point into every view of a group: ~1.5 ms for 9,000 points against 9 views on two cores, no
faster as a serial numba loop).

Usage::

    views = [PooledDepth.of(depth, pose, intrinsics, stride=4) for depth, pose, intrinsics in frames]
    free = seen_through(points, views, margin=0.03)  # (N,) bool
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from h3edge.geometry.camera import Intrinsics


def pool_depth(depth: np.ndarray, stride: int) -> np.ndarray:
    """The minimum of each ``stride`` x ``stride`` block of ``depth`` (m, 0 = invalid), 0 where any
    pixel of the block is invalid (0, NaN, inf); (H // stride, W // stride) float32 (trailing pixels
    dropped)."""
    from h3edge.mapping import _pool_kernel as k

    out = np.empty((depth.shape[0] // stride, depth.shape[1] // stride), np.float32)
    k.pool_min(np.ascontiguousarray(depth, np.float32), int(stride), out)
    return out


@dataclass
class PooledDepth:
    """One view's pooled depth (:func:`pool_depth`) with the pose and full-resolution intrinsics it
    was measured with."""

    depth: np.ndarray  # float32 (H // stride, W // stride), 0 = unknown
    pose: np.ndarray  # camera to world (4, 4)
    intrinsics: Intrinsics
    stride: int

    @classmethod
    def of(cls, depth: np.ndarray, pose: np.ndarray, intrinsics: Intrinsics, stride: int) -> PooledDepth:
        return cls(pool_depth(depth, stride), np.asarray(pose, np.float64), intrinsics, stride)

    @property
    def nbytes(self) -> int:
        return self.depth.nbytes + 8 * 16


def seen_through(points: torch.Tensor, views: list[PooledDepth], margin: float) -> torch.Tensor:
    """(N,) bool: some view of ``views`` measured a z-depth more than ``margin`` (m) beyond each of
    ``points`` (N, 3, world) in the pooled block it projects to. Views that share intrinsics and
    block size are tested in one batch."""
    free = torch.zeros(len(points), dtype=torch.bool, device=points.device)
    if len(points) == 0:
        return free
    groups: dict[tuple, list[PooledDepth]] = {}
    for v in views:
        groups.setdefault((v.intrinsics, v.stride, v.depth.shape), []).append(v)
    for (k, s, _), vs in groups.items():
        free |= _seen_through_group(points, vs, k, s, margin)
    return free


def _seen_through_group(points: torch.Tensor, views: list[PooledDepth], k: Intrinsics, stride: int,
                        margin: float) -> torch.Tensor:
    """:func:`seen_through` for one group of views (same intrinsics and block size): every point
    projected into every view."""
    dev, dt = points.device, points.dtype
    h, w = views[0].depth.shape
    poses = torch.from_numpy(np.stack([v.pose for v in views])).to(dev, dt)  # (V, 4, 4)
    depth = torch.from_numpy(np.stack([v.depth for v in views])).to(dev)  # (V, h, w)
    cam = torch.bmm(points[None].expand(len(views), -1, -1) - poses[:, None, :3, 3], poses[:, :3, :3])
    z = cam[..., 2]
    front = z > 1e-3
    zs = torch.where(front, z, torch.ones_like(z))
    col = torch.floor((k.fx * cam[..., 0] / zs + k.cx) / stride)
    row = torch.floor((k.fy * cam[..., 1] / zs + k.cy) / stride)
    ok = front & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    flat = torch.arange(len(views), device=dev)[:, None] * (h * w) + (row.clamp(0, h - 1) * w
                                                                     + col.clamp(0, w - 1)).long()
    d = depth.reshape(-1)[flat].to(dt)
    return (ok & (d > 0) & (d > z + margin)).any(0)
