"""Cross-view free space: a frame's depth pooled into blocks, and which points another view saw through.

A band sample behind the measured depth of its own ray takes a negative SDF target ("inside").
Behind a thin object (a chair leg, a slat, a shelf edge) that is wrong: the object ends a few
centimetres behind its front face, and another view that looks past it sees the wall beyond.
:func:`seen_through` answers, for points, whether any of a set of views measured a depth more than
``margin`` beyond them along its own ray, from each view's depth pooled to its block minimum (a
block with any invalid pixel knows nothing), so that a claim of free space near a depth edge is
conservative: every pixel of the block saw past the point.

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
    pixel of the block is invalid; (H // stride, W // stride) float32 (trailing pixels dropped)."""
    h, w = depth.shape[0] // stride, depth.shape[1] // stride
    blocks = np.asarray(depth, np.float32)[:h * stride, :w * stride].reshape(h, stride, w, stride)
    low = blocks.min(axis=(1, 3))
    return np.where(low > 0, low, np.float32(0)).astype(np.float32)


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
    dev, dt = points.device, points.dtype
    for (k, s, (h, w)), vs in groups.items():
        poses = torch.from_numpy(np.stack([v.pose for v in vs])).to(dev, dt)  # (V, 4, 4)
        depth = torch.from_numpy(np.stack([v.depth for v in vs])).to(dev)  # (V, h, w)
        cam = torch.bmm(points[None].expand(len(vs), -1, -1) - poses[:, None, :3, 3], poses[:, :3, :3])
        z = cam[..., 2]
        front = z > 1e-3
        zs = torch.where(front, z, torch.ones_like(z))
        col = torch.floor((k.fx * cam[..., 0] / zs + k.cx) / s)
        row = torch.floor((k.fy * cam[..., 1] / zs + k.cy) / s)
        ok = front & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        flat = torch.arange(len(vs), device=dev)[:, None] * (h * w) + (row.clamp(0, h - 1) * w
                                                                         + col.clamp(0, w - 1)).long()
        d = depth.reshape(-1)[flat].to(dt)
        free |= (ok & (d > 0) & (d > z + margin)).any(0)
    return free
