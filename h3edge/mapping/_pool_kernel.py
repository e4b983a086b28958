"""Fused numba CPU kernel of the cross-view free-space test (see :mod:`h3edge.mapping.visibility`):
a depth image pooled to its block minima, once per frame (numpy's strided block reduction took
3-6 ms a 640x480 frame on two cores, this 0.2 ms).

Module-level so numba's on-disk cache is reused across processes.
"""

import math

import numba as nb
import numpy as np


@nb.njit(parallel=True, cache=True, nogil=True)
def pool_min(depth, stride, out):
    """``out`` (H // stride, W // stride) = the minimum of each ``stride`` x ``stride`` block of
    ``depth`` (0 = invalid), 0 where any pixel of the block is invalid or not finite."""
    h, w = out.shape
    for r in nb.prange(h):
        for c in range(w):
            low = np.inf
            for i in range(r * stride, (r + 1) * stride):
                for j in range(c * stride, (c + 1) * stride):
                    d = depth[i, j]
                    if not (d > 0.0) or not math.isfinite(d):  # NaN compares false
                        low = 0.0
                        break
                    if d < low:
                        low = d
                if low == 0.0:
                    break
            out[r, c] = low
