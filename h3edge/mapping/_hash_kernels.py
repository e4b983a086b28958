"""Fused numba CPU kernels of the hash encoding (forward, backward, gradient collection, lazy Adam
on the flagged rows).

Module-level functions so that numba's on-disk cache (``cache=True``) is reused across processes
(closures got a new cache entry, and a ~10 s compile, in every process). Imported lazily by
:mod:`h3edge.mapping.hashgrid` only where numba is installed.
"""

import math

import numba as nb
import numpy as np

from h3edge.mapping._trilinear_kernel import corner_weight


@nb.njit(inline="always", fastmath=True)
def cell(xn, i, scale):
    """Integer cell corner and fractional position of point i at a level of ``scale``."""
    px = xn[i, 0] * scale + 0.5
    py = xn[i, 1] * scale + 0.5
    pz = xn[i, 2] * scale + 0.5
    gx, gy, gz = math.floor(px), math.floor(py), math.floor(pz)
    return np.int64(gx), np.int64(gy), np.int64(gz), px - gx, py - gy, pz - gz

@nb.njit(inline="always", fastmath=True)
def corner(ix, iy, iz, fx, fy, fz, side, T, p0, p1, p2, d0, d1, d2, c):
    """Row offset inside the level and trilinear weight of corner c of the cell."""
    w = corner_weight(fx, fy, fz, c)
    cx = ix + (c & 1)
    cy = iy + ((c >> 1) & 1)
    cz = iz + ((c >> 2) & 1)
    if side > 0 and 0 <= cx < side and 0 <= cy < side and 0 <= cz < side:
        h = cx + side * (cy + side * cz)
    else:
        h = (cx * p0 + d0) ^ (cy * p1 + d1) ^ (cz * p2 + d2)
    return h & (T - 1), w

@nb.njit(parallel=True, fastmath=True, cache=True)
def fwd(xn, table, scales, dense, T, p0, p1, p2, d0, d1, d2, out):
    n = xn.shape[0]
    L = scales.shape[0]
    F = table.shape[1]
    for i in nb.prange(n):
        for l in range(L):
            for f in range(F):
                out[i, l * F + f] = 0.0
            ix, iy, iz, fx, fy, fz = cell(xn, i, scales[l])
            for c in range(8):
                h, w = corner(ix, iy, iz, fx, fy, fz, dense[l], T, p0, p1, p2, d0, d1, d2, c)
                row = h + l * T
                for f in range(F):
                    out[i, l * F + f] += w * table[row, f]

@nb.njit(parallel=True, fastmath=True, cache=True)
def bwd(xn, grad_out, scales, dense, T, p0, p1, p2, d0, d1, d2, grad_buf, touched):
    # Corners are recomputed rather than stored (256 B/point saved). One thread per level:
    # levels own disjoint table rows, so the scatter-add never races. ``touched`` flags the rows
    # (until the optimiser step or the collection clears them).
    n = xn.shape[0]
    L = scales.shape[0]
    F = grad_buf.shape[1]
    for l in nb.prange(L):
        for i in range(n):
            ix, iy, iz, fx, fy, fz = cell(xn, i, scales[l])
            for c in range(8):
                h, w = corner(ix, iy, iz, fx, fy, fz, dense[l], T, p0, p1, p2, d0, d1, d2, c)
                row = h + l * T
                for f in range(F):
                    grad_buf[row, f] += w * grad_out[i, l * F + f]
                touched[row] = True

@nb.njit(parallel=True, cache=True)
def collect(grad_buf, touched, rows, grads_out):
    # Gather the touched rows' gradients into a compact array, then clear buffer and flags.
    for k in nb.prange(rows.shape[0]):
        row = rows[k]
        for f in range(grad_buf.shape[1]):
            grads_out[k, f] = grad_buf[row, f]
            grad_buf[row, f] = 0.0
        touched[row] = False

# Rows per block of the flag scan: the optimiser walks the table in address order, block by block
# in parallel, so that its reads and writes stream (4x faster than visiting the touched rows in the
# order the backward found them, which is random).
SCAN_BLOCK = 4096


@nb.njit(parallel=True, fastmath=True, cache=True)
def adam_touched(table, m, v, grad_buf, touched, lr, b1, b2, eps, c1, c2, counts):
    # Lazy Adam on every flagged row, its gradient read from grad_buf; clears gradient and flag.
    # counts[block] = the rows updated in that block (len(counts) = ceil(rows / SCAN_BLOCK)).
    n = touched.shape[0]
    F = table.shape[1]
    for blk in nb.prange(counts.shape[0]):
        cnt = 0
        for r in range(blk * SCAN_BLOCK, min(n, (blk + 1) * SCAN_BLOCK)):
            if touched[r]:
                for f in range(F):
                    g = grad_buf[r, f]
                    grad_buf[r, f] = 0.0
                    mr = b1 * m[r, f] + (1 - b1) * g
                    vr = b2 * v[r, f] + (1 - b2) * g * g
                    m[r, f] = mr
                    v[r, f] = vr
                    table[r, f] -= lr * (mr / c1) / (math.sqrt(vr / c2) + eps)
                touched[r] = False
                cnt += 1
        counts[blk] = cnt
