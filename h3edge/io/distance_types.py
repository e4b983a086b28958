"""What a signed-distance or slice answer holds, the library's (:mod:`h3edge.mapping.distance`) and
the service's replies alike (:class:`h3edge.serving.client.Client` reads them without torch)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
