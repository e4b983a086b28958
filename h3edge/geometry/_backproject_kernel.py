"""The numba kernel of :func:`h3edge.geometry.camera.backproject`: one parallel pass over the
pixels instead of NumPy's pixel grid, product and 3x3 matrix product (at 640x480 on two cores,
12 -> ~3 ms, most of it the output's allocation; the pass itself ~0.7 ms). Module-level so numba's
on-disk cache is reused across processes."""

import math

import numba as nb


@nb.njit(parallel=True, fastmath=False, cache=True, nogil=True)
def backproject_into(depth, fx, fy, cx, cy, offset, rot, trans, out):
    """Points (H, W, 3) of a z-depth image: ``rot @ p_cam + trans``; NaN where the depth is not a
    finite positive number."""
    h, w = depth.shape
    for v in nb.prange(h):
        y = (v + offset - cy) / fy
        for u in range(w):
            z = float(depth[v, u])
            if not (z > 0.0 and math.isfinite(z)):
                out[v, u, 0] = math.nan
                out[v, u, 1] = math.nan
                out[v, u, 2] = math.nan
                continue
            px, py = (u + offset - cx) / fx * z, y * z
            for a in range(3):
                out[v, u, a] = rot[a, 0] * px + rot[a, 1] * py + rot[a, 2] * z + trans[a]
