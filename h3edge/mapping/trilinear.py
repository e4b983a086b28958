"""Trilinear interpolation weights on a cell's 8 corners: the torch routine (the numba kernels'
twin is :func:`h3edge.mapping._trilinear_kernel.corner_weight`; both use this corner order).

Corner ``c`` (0..7) is offset ``CORNERS[c] = (c & 1, (c >> 1) & 1, (c >> 2) & 1)`` from the cell's
lower corner, and its weight at fractional position ``f`` in the cell is
``prod_k (f_k if CORNERS[c, k] else 1 - f_k)``; the 8 weights sum to 1.

Example::

    w = corner_weights(torch.tensor([[0.25, 0.5, 1.0]]))  # (1, 8)
    value = (w * corner_values).sum(-1)
"""

from __future__ import annotations

import functools

import numpy as np
import torch

CORNERS = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.int64)


@functools.lru_cache(maxsize=8)
def corners_on(device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """:data:`CORNERS` on ``device``, int64 (8, 3) and bool (8, 3): made once a device, as
    constants (a copy up every call would be a stall on CUDA: a copy from pageable memory waits for
    its stream's work)."""
    c = torch.from_numpy(CORNERS).to(device)
    return c, c.bool()


def corner_weights(frac: torch.Tensor) -> torch.Tensor:
    """Weights (..., 8) of the 8 corners for fractional positions ``frac`` (..., 3) in [0, 1]."""
    upper = corners_on(frac.device)[1]  # (8, 3)
    f = frac.unsqueeze(-2)  # (..., 1, 3)
    return torch.where(upper, f, 1 - f).prod(-1)
