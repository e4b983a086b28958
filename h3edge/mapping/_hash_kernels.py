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
def cell(xn, i, scale, p0, p1, p2, d0, d1, d2):
    """Integer cell corner of point i at a level of ``scale``, its fractional position, and the
    per-axis hash terms ``v * pi + delta`` of the cell's low (v) and high (v + 1) corners."""
    px = xn[i, 0] * scale + 0.5
    py = xn[i, 1] * scale + 0.5
    pz = xn[i, 2] * scale + 0.5
    gx, gy, gz = math.floor(px), math.floor(py), math.floor(pz)
    ix, iy, iz = np.int64(gx), np.int64(gy), np.int64(gz)
    return (ix, iy, iz, px - gx, py - gy, pz - gz,
            ix * p0 + d0, (ix + 1) * p0 + d0, iy * p1 + d1, (iy + 1) * p1 + d1, iz * p2 + d2, (iz + 1) * p2 + d2)


@nb.njit(inline="always", fastmath=True)
def corner(c, ix, iy, iz, fx, fy, fz, hx0, hx1, hy0, hy1, hz0, hz1, side, mask):
    """Row offset inside the level and trilinear weight of corner c of the cell: dense inside a
    dense level's grid (``side`` > 0), else ``(v_x pi_1 + d_1) ^ (v_y pi_2 + d_2) ^ (v_z pi_3 + d_3)``."""
    bx, by, bz = c & 1, (c >> 1) & 1, (c >> 2) & 1
    w = corner_weight(fx, fy, fz, c)
    if side > 0:
        cx, cy, cz = ix + bx, iy + by, iz + bz
        if 0 <= cx < side and 0 <= cy < side and 0 <= cz < side:
            return (cx + side * (cy + side * cz)) & mask, w
    return ((hx1 if bx else hx0) ^ (hy1 if by else hy0) ^ (hz1 if bz else hz0)) & mask, w


# Forward and backward: F = 2 features per row (every profile's width) keeps a row's two values in
# registers (fwd2, bwd2: 2.4x and 1.3x the per-feature loops they replaced, on a sim step's points); other widths take
# the generic loops (fwd_any, bwd_any).
def fwd(xn, table, scales, dense, T, p0, p1, p2, d0, d1, d2, out):
    """Features (N, L*F) of normalised points ``xn`` into ``out``: the F = 2 kernel or the generic one."""
    if table.shape[1] == 2:
        fwd2(xn, table, scales, dense, T, p0, p1, p2, d0, d1, d2, out)
    else:
        fwd_any(xn, table, scales, dense, T, p0, p1, p2, d0, d1, d2, out)

@nb.njit(parallel=True, fastmath=True, cache=True, nogil=True)
def fwd2(xn, table, scales, dense, T, p0, p1, p2, d0, d1, d2, out):
    n = xn.shape[0]
    L = scales.shape[0]
    mask = T - 1
    for i in nb.prange(n):
        for l in range(L):
            ix, iy, iz, fx, fy, fz, hx0, hx1, hy0, hy1, hz0, hz1 = cell(xn, i, scales[l], p0, p1, p2, d0, d1, d2)
            a0 = np.float32(0.0)
            a1 = np.float32(0.0)
            for c in range(8):
                h, w = corner(c, ix, iy, iz, fx, fy, fz, hx0, hx1, hy0, hy1, hz0, hz1, dense[l], mask)
                row = h + l * T
                a0 += w * table[row, 0]
                a1 += w * table[row, 1]
            out[i, 2 * l] = a0
            out[i, 2 * l + 1] = a1

@nb.njit(parallel=True, fastmath=True, cache=True, nogil=True)
def fwd_any(xn, table, scales, dense, T, p0, p1, p2, d0, d1, d2, out):
    n = xn.shape[0]
    L = scales.shape[0]
    F = table.shape[1]
    mask = T - 1
    for i in nb.prange(n):
        for l in range(L):
            ix, iy, iz, fx, fy, fz, hx0, hx1, hy0, hy1, hz0, hz1 = cell(xn, i, scales[l], p0, p1, p2, d0, d1, d2)
            for f in range(F):
                out[i, l * F + f] = 0.0
            for c in range(8):
                h, w = corner(c, ix, iy, iz, fx, fy, fz, hx0, hx1, hy0, hy1, hz0, hz1, dense[l], mask)
                row = h + l * T
                for f in range(F):
                    out[i, l * F + f] += w * table[row, f]

def bwd(xn, grad_out, scales, dense, T, p0, p1, p2, d0, d1, d2, grad_buf, touched):
    """Scatter-add the features' gradient ``grad_out`` into ``grad_buf`` and flag the rows in ``touched``."""
    # Corners are recomputed rather than stored (256 B/point saved). One thread per level:
    # levels own disjoint table rows, so the scatter-add never races. ``touched`` flags the rows
    # (until the optimiser step or the collection clears them).
    if grad_buf.shape[1] == 2:
        bwd2(xn, grad_out, scales, dense, T, p0, p1, p2, d0, d1, d2, grad_buf, touched)
    else:
        bwd_any(xn, grad_out, scales, dense, T, p0, p1, p2, d0, d1, d2, grad_buf, touched)

@nb.njit(parallel=True, fastmath=True, cache=True, nogil=True)
def bwd2(xn, grad_out, scales, dense, T, p0, p1, p2, d0, d1, d2, grad_buf, touched):
    n = xn.shape[0]
    L = scales.shape[0]
    mask = T - 1
    for l in nb.prange(L):
        for i in range(n):
            g0 = grad_out[i, 2 * l]
            g1 = grad_out[i, 2 * l + 1]
            ix, iy, iz, fx, fy, fz, hx0, hx1, hy0, hy1, hz0, hz1 = cell(xn, i, scales[l], p0, p1, p2, d0, d1, d2)
            for c in range(8):
                h, w = corner(c, ix, iy, iz, fx, fy, fz, hx0, hx1, hy0, hy1, hz0, hz1, dense[l], mask)
                row = h + l * T
                grad_buf[row, 0] += w * g0
                grad_buf[row, 1] += w * g1
                touched[row] = True

@nb.njit(parallel=True, fastmath=True, cache=True, nogil=True)
def bwd_any(xn, grad_out, scales, dense, T, p0, p1, p2, d0, d1, d2, grad_buf, touched):
    n = xn.shape[0]
    L = scales.shape[0]
    F = grad_buf.shape[1]
    mask = T - 1
    for l in nb.prange(L):
        for i in range(n):
            ix, iy, iz, fx, fy, fz, hx0, hx1, hy0, hy1, hz0, hz1 = cell(xn, i, scales[l], p0, p1, p2, d0, d1, d2)
            for c in range(8):
                h, w = corner(c, ix, iy, iz, fx, fy, fz, hx0, hx1, hy0, hy1, hz0, hz1, dense[l], mask)
                row = h + l * T
                for f in range(F):
                    grad_buf[row, f] += w * grad_out[i, l * F + f]
                touched[row] = True

@nb.njit(parallel=True, cache=True, nogil=True)
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


@nb.njit(parallel=True, fastmath=True, cache=True, nogil=True)
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
