"""Planner outputs from a map view: signed distance (and its gradient) at points, and an occupancy /
distance slice at a height.

What the map knows at a point, in this order:

- inside an allocated voxel whose priors were observed (trilinear support at least the mesh's
  ``mesh_min_support``; :meth:`~h3edge.mapping.raymarch.PriorLookup.support`): the field's SDF,
  ``sdf_m = field_sdf * truncation``. Within the band (``|sdf_m| < truncation``) it is the distance
  to the surface (state ``NEAR``); beyond it only its sign is trusted: ``FREE`` in front (distance
  at least ``truncation``), ``INSIDE`` behind. Support ends ``voxels.observed_behind`` behind the
  surfaces the frames saw: deeper, no training reached the field (where it drifts, it would read
  free inside a wall), so such points are ``UNKNOWN``, and ``INSIDE`` spans the band behind a surface;
- else, outside every allocated voxel, in a cell depth rays crossed
  (:mod:`h3edge.mapping.free_space`): ``FREE``, distance at least ``truncation`` (reported as
  ``truncation``, a lower bound); an allocated voxel without observed priors may hold a surface,
  so it is never free;
- else ``UNKNOWN``: distance NaN. Never free.

The gradient (metres per metre, pointing away from the surface) is the central difference of the
field's SDF over ``GRADIENT_STEP`` voxels, where the field is known (NaN elsewhere); it runs on the
view's decoders as they are (eager or ONNX), so it needs no autograd.

The slice samples cell centres of a regular grid at height ``z``: occupancy as ``nav_msgs/
OccupancyGrid`` values (-1 unknown, 0 free, 100 occupied: behind or within half a cell of a
surface), and the distance (metres) from each known cell to the nearest occupied cell of the slice
(a Euclidean distance transform within the plane; NaN for unknown cells). Row 0 is the lowest y.
"""

from __future__ import annotations

import numpy as np

from h3edge.io.distance_types import (
    FREE,
    INSIDE,
    NEAR,
    UNKNOWN,
    DistanceSample,
    DistanceSlice,
    slice_from_sample,
    slice_grid,
)
from h3edge.mapping.raymarch import PriorLookup

__all__ = ["FREE", "INSIDE", "NEAR", "UNKNOWN", "DistanceSample", "DistanceSlice", "distance_slice", "signed_distance"]

GRADIENT_STEP = 0.05  # voxel sizes, central differences


def _field_sdf(view, pts: np.ndarray, lookup: PriorLookup) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(SDF metres, supported-in-voxel mask, in-any-voxel mask) at points."""
    tr = view.voxels.cfg.truncation
    _, vox = lookup(pts)
    support = np.where(vox >= 0, lookup.support(pts), 0.0)
    inside = support >= max(view.mesh_min_support, 1e-6)
    sdf = np.full(len(pts), np.nan, np.float32)
    if inside.any():
        sdf[inside] = view.banded_sdf_np(pts[inside], np.inf, lookup) * tr
    return sdf, inside, vox >= 0


def signed_distance(view, points: np.ndarray, gradient: bool = False, chunk: int = 262_144) -> DistanceSample:
    """Signed distance, state and (optionally) gradient at world points (N, 3) (module docstring)."""
    pts = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
    tr = view.voxels.cfg.truncation
    lookup = PriorLookup(view.voxels)
    sdf = np.full(len(pts), np.nan, np.float32)
    state = np.zeros(len(pts), np.uint8)
    grad = np.full((len(pts), 3), np.nan, np.float32) if gradient else None
    # beyond max_position the map knows nothing (and voxel keys cannot hold such coordinates): unknown
    with np.errstate(invalid="ignore"):
        within = np.abs(pts).max(1, initial=0.0) <= min(view.max_position, view.voxel_size * (2 ** 20 - 2))
    for a in range(0, len(pts), chunk):
        p = pts[a:a + chunk]
        ok = within[a:a + chunk]
        if not ok.all():  # evaluated as the origin, then forgotten
            p = np.where(ok[:, None], p, 0.0)
        s, known, allocated = _field_sdf(view, p, lookup)
        known &= ok
        allocated &= ok
        s[~ok] = np.nan
        st = np.zeros(len(p), np.uint8)
        st[known] = np.where(s[known] >= tr, FREE, np.where(s[known] <= -tr, INSIDE, NEAR))
        if view.free_space is not None:  # a voxel without observed priors may hold a surface: unknown
            free = ~allocated & view.free_space.contains(p) & ok
            s[free], st[free] = tr, FREE
        sdf[a:a + chunk], state[a:a + chunk] = s, st
        if gradient and known.any():
            h = GRADIENT_STEP * view.voxel_size
            k = np.flatnonzero(known)
            g = np.empty((len(k), 3), np.float32)
            for axis in range(3):
                off = np.zeros(3)
                off[axis] = h
                hi = _field_sdf(view, p[k] + off, lookup)[0]
                lo = _field_sdf(view, p[k] - off, lookup)[0]
                g[:, axis] = (hi - lo) / (2 * h)  # NaN where a side leaves the known field
            grad[a + k] = g
    return DistanceSample(sdf, state, grad)


def distance_slice(view, z: float, lo: tuple[float, float], hi: tuple[float, float], resolution: float
                   ) -> DistanceSlice:
    """Occupancy and distance images of the rectangle ``lo``..``hi`` (x, y metres) at height ``z``."""
    pts, shape = slice_grid(z, lo, hi, resolution)
    sample = signed_distance(view, pts)
    return slice_from_sample(sample.sdf, sample.state, shape, z, lo, resolution)
