"""What a signed-distance or slice answer holds, the library's (:mod:`h3edge.mapping.distance`) and
the service's replies alike (:class:`h3edge.serving.client.Client` reads them without torch)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

UNKNOWN, FREE, NEAR, INSIDE = 0, 1, 2, 3  # DistanceSample.state


@dataclass(frozen=True)
class DistanceSample:
    """Signed distance at N world points."""

    sdf: np.ndarray  # float32 (N,) metres; NaN unknown; +truncation is a lower bound for FREE
    state: np.ndarray  # uint8 (N,): UNKNOWN, FREE, NEAR, INSIDE
    gradient: np.ndarray | None  # float32 (N, 3) or None when not asked for


@dataclass(frozen=True)
class DistanceSlice:
    """Occupancy and distance images at one height (row 0 is the lowest y)."""

    occupancy: np.ndarray  # int8 (H, W): -1 unknown, 0 free, 100 occupied
    distance: np.ndarray  # float32 (H, W) metres to the nearest occupied cell; NaN unknown
    origin: tuple[float, float, float]  # world position of cell (0, 0)'s corner (x, y) and the height z
    resolution: float  # metres per cell


def slice_cells(lo: tuple[float, float], hi: tuple[float, float], resolution: float) -> float:
    """How many cells a slice of ``lo``..``hi`` at ``resolution`` has (a float: inf for a box too large to
    count, never an overflow), to compare with a cap before any is made."""
    with np.errstate(over="ignore"):
        return float(np.ceil((hi[0] - lo[0]) / resolution)) * float(np.ceil((hi[1] - lo[1]) / resolution))


def slice_grid(z: float, lo: tuple[float, float], hi: tuple[float, float], resolution: float
               ) -> tuple[np.ndarray, tuple[int, int]]:
    """The cell centres (ny * nx, 3) float64 metres of a slice of ``lo``..``hi`` (x, y) at height ``z``,
    row by row from the lowest y, and its shape (ny, nx)."""
    nx = max(1, int(np.ceil((hi[0] - lo[0]) / resolution)))
    ny = max(1, int(np.ceil((hi[1] - lo[1]) / resolution)))
    xs = lo[0] + (np.arange(nx) + 0.5) * resolution
    ys = lo[1] + (np.arange(ny) + 0.5) * resolution
    gx, gy = np.meshgrid(xs, ys)  # (ny, nx): row = y
    return np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], -1), (ny, nx)


def slice_from_sample(sdf: np.ndarray, state: np.ndarray, shape: tuple[int, int], z: float,
                      lo: tuple[float, float], resolution: float) -> DistanceSlice:
    """The slice whose cell centres (:func:`slice_grid`) have signed distance ``sdf`` and ``state``:
    occupied where inside or within half a cell of a surface, free where otherwise known; the
    distance from each known cell to the nearest occupied cell within the plane (a Euclidean
    distance transform; inf where none is occupied, NaN where unknown)."""
    state = np.asarray(state).reshape(shape)
    sdf = np.asarray(sdf).reshape(shape)
    known = state != UNKNOWN
    occupied = known & ((state == INSIDE) | ((state == NEAR) & (sdf <= 0.5 * resolution)))
    occupancy = np.full(shape, -1, np.int8)
    occupancy[known] = 0
    occupancy[occupied] = 100
    if occupied.any():
        dist = ndimage.distance_transform_edt(~occupied).astype(np.float32) * np.float32(resolution)
    else:
        dist = np.full(shape, np.inf, np.float32)
    dist[~known] = np.nan
    return DistanceSlice(occupancy, dist, (float(lo[0]), float(lo[1]), float(z)), float(resolution))
