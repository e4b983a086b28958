"""Numba CPU kernels of the fused colour base (see :mod:`h3edge.mapping.color_base`): an
open-addressed hash table of fine cells (int64 cell keys, linear probing, ``slots`` holding row
indices, -1 empty), a frame's colours fused into it (``fuse_frame``), the colour read back with
trilinear weights between cell centres (``sample_cells``), and the table rebuilt at a new size
(``rebuild_slots``).

Module-level so numba's on-disk cache is reused across processes.
"""

import math

import numba as nb
import numpy as np

from h3edge.mapping._trilinear_kernel import corner_weight

_BITS = 21  # as h3edge.mapping.voxels.pack: +-2^20 cells a side
_OFF = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


@nb.njit(inline="always")
def _key(i, j, k):
    """Packed key of cell (i, j, k); -1 outside the representable range."""
    a, b, c = i + _OFF, j + _OFF, k + _OFF
    if a < 0 or a > _MASK or b < 0 or b > _MASK or c < 0 or c > _MASK:
        return -1
    return (np.int64(c) << (2 * _BITS)) | (np.int64(b) << _BITS) | np.int64(a)


_BLOCK = (3 << (2 * _BITS)) | (3 << _BITS) | 3  # the low 2 bits of each axis: a cell's place in its 4^3 block


@nb.njit(inline="always")
def _home(key, mask):
    """The slot a key's probe starts at: its 4^3 block's hash, times 64, plus the cell's place in
    the block, so that the cells of a block (a surface patch) probe neighbouring slots, a few cache
    lines, not one random line each."""
    block = np.uint64(key & ~np.int64(_BLOCK))
    local = (key & 3) | (((key >> _BITS) & 3) << 2) | (((key >> (2 * _BITS)) & 3) << 4)
    return ((np.int64((block * _GOLDEN) >> np.uint64(32)) << 6) | local) & mask


@nb.njit(inline="always")
def _find(slots, keys, key, mask):
    """(row of ``key`` or -1, the slot where it is or would go)."""
    s = _home(key, mask)
    while True:
        row = slots[s]
        if row < 0:
            return -1, s
        if keys[row] == key:
            return row, s
        s = (s + 1) & mask


@nb.njit(inline="always")
def _corners(p, inv):
    """The lattice of cell centres around world point ``p`` (cell = 1 / ``inv`` m): the lower corner
    cell (ix, iy, iz) and the point's fractions (fx, fy, fz) towards the upper one, for
    :func:`_corner_row` and ``corner_weight``."""
    qx, qy, qz = p[0] * inv - 0.5, p[1] * inv - 0.5, p[2] * inv - 0.5
    ix, iy, iz = math.floor(qx), math.floor(qy), math.floor(qz)
    return ix, iy, iz, qx - ix, qy - iy, qz - iz


@nb.njit(inline="always")
def _corner_row(slots, keys, mask, ix, iy, iz, c):
    """Row of corner ``c`` (0..7, bits x, y, z) of the cell lattice at (ix, iy, iz); -1 if not held."""
    key = _key(ix + (c & 1), iy + ((c >> 1) & 1), iz + ((c >> 2) & 1))
    if key < 0:
        return -1
    row, _ = _find(slots, keys, key, mask)
    return row


@nb.njit(cache=True, nogil=True)
def rebuild_slots(keys, n, capacity):
    """A slot table of ``capacity`` (a power of two) holding rows 0..n-1 of ``keys``."""
    slots = np.full(capacity, -1, np.int32)
    mask = capacity - 1
    for row in range(n):
        _, s = _find(slots, keys, keys[row], mask)
        slots[s] = row
    return slots


@nb.njit(inline="always")
def _pixel_normal(depth, u, v, z, xc, yc, fx, fy, cx, cy, reach, flat):
    """Unit normal (camera frame) of the surface at pixel (u, v) of depth ``z`` (its ray (xc, yc, 1)),
    spanned by the points of the pixels ``reach`` to its left and right, above and below; (0, 0, 0)
    where ``reach`` is 0, one of them lies outside the image or has no depth, or the three pixels
    along a row or a column do not lie on one plane: their depths' second difference above ``flat``
    (m; a depth edge or a crease between them, where the normal would not be the surface's)."""
    h, w = depth.shape
    if reach <= 0 or u < reach or v < reach or u + reach >= w or v + reach >= h:
        return 0.0, 0.0, 0.0
    zl, zr, zu, zd = depth[v, u - reach], depth[v, u + reach], depth[v - reach, u], depth[v + reach, u]
    if not (zl > 0.0 and zr > 0.0 and zu > 0.0 and zd > 0.0) or max(abs(zl + zr - 2.0 * z),
                                                                  abs(zu + zd - 2.0 * z)) > flat:
        return 0.0, 0.0, 0.0
    # tangents: right minus left, below minus above (each point on its own pixel's ray)
    ax = (u + reach + 0.5 - cx) / fx * zr - (u - reach + 0.5 - cx) / fx * zl
    ay, az = yc * (zr - zl), zr - zl
    bx, bz = xc * (zd - zu), zd - zu
    by = (v + reach + 0.5 - cy) / fy * zd - (v - reach + 0.5 - cy) / fy * zu
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    if not norm > 0.0:
        return 0.0, 0.0, 0.0
    return nx / norm, ny / norm, nz / norm


@nb.njit(cache=True, nogil=True)
def fuse_frame(slots, keys, cells, n, depth, color, rot, trans, fx, fy, cx, cy, max_stride, reach, cell, band,
               max_weight, normal_px):
    """Fuse one frame: each pixel with valid depth z whose column and row are multiples of its
    stride s(z) = clip(floor(``reach`` / z), 1, ``max_stride``) (fused pixels at most reach / f
    apart on the surface, wherever it is) reaches the cells at z-depths z + k * ``cell``,
    k = -band..band, along its ray (pixel centre; ``rot``, ``trans``: camera to world). Each cell
    reached takes the colour (uint8 RGB -> [0, 1]) of the pixel that the surface point nearest its
    centre projects into, the foot of the centre on the plane through the reaching pixel's point
    with the normal its neighbours ``normal_px`` pixels away span (:func:`_pixel_normal`; the
    centre itself where they do not: 0, an image border, a missing neighbour, or the three pixels
    of a row or column more than a cell off one plane), and the
    signed distance of its centre in front of that pixel's depth along the camera's z axis (m,
    positive in front); where that pixel has no depth or lies across a depth edge (> 2 (band + 1)
    cells from z), the reaching pixel's colour and depth. (A cell off the surface read at its own
    centre takes each view's colour from a different surface point, up to a cell away times the
    tangent of the view's incidence: a blur a base whose cell centres lie on the surface does not
    have, D53-12.) Both as running averages (``cells`` rows:
    R, G, B, weight, signed distance) whose weight grows by one a fusion up to ``max_weight`` (a
    cell the previous pixel's sample reached already is not fused again). New cells take rows
    from ``n`` up to ``len(keys)``; past it they are refused. Returns (rows in use, cells refused)."""
    h, w = depth.shape
    mask = len(slots) - 1
    cap = len(keys)
    inv = 1.0 / cell
    same_surface = 2.0 * (band + 1) * cell  # m: a projected pixel's depth this near the ray's is its surface
    refused = 0
    # the cell the previous fused pixel's k-th sample fell in: the next pixel's often falls there too
    # (pixels finer than cells), and it has taken its projected pixel's colour already
    last_key = np.full(2 * band + 1, -1, np.int64)
    for v in range(h):
        yc = (v + 0.5 - cy) / fy
        for u in range(w):
            z = depth[v, u]
            if not (z > 0.0) or not math.isfinite(z):
                continue
            st = min(max_stride, max(1, int(reach / z)))
            if u % st or v % st:
                continue
            xc = (u + 0.5 - cx) / fx
            r = color[v, u, 0] / 255.0
            g = color[v, u, 1] / 255.0
            b = color[v, u, 2] / 255.0
            nx, ny, nz = _pixel_normal(depth, u, v, z, xc, yc, fx, fy, cx, cy, normal_px, cell)
            px0, py0 = xc * z, yc * z  # the reaching pixel's point (camera frame), z its depth
            for k in range(-band, band + 1):
                zz = z + k * cell
                if zz <= 0.0:
                    continue
                x, y = xc * zz, yc * zz
                px = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * zz + trans[0]
                py = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * zz + trans[1]
                pz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * zz + trans[2]
                ix, iy, iz = math.floor(px * inv), math.floor(py * inv), math.floor(pz * inv)
                key = _key(ix, iy, iz)
                if key < 0:
                    continue
                if key == last_key[k + band]:  # the previous pixel's cell: the same projected pixel, fused
                    continue
                row, s = _find(slots, keys, key, mask)
                if row < 0:
                    if n >= cap:
                        refused += 1
                        continue
                    row = n
                    n += 1
                    keys[row] = key
                    slots[s] = row
                    cells[row, 3] = 0.0
                last_key[k + band] = key
                # the cell centre in this camera, and the pixel its foot on the surface projects into:
                # the cell takes that pixel's colour and depth, not the colour of the ray that reached
                # it, which lies up to a cell beside the centre, more at grazing angles
                ox, oy, oz = (ix + 0.5) * cell - trans[0], (iy + 0.5) * cell - trans[1], (iz + 0.5) * cell - trans[2]
                xf = ox * rot[0, 0] + oy * rot[1, 0] + oz * rot[2, 0]
                yf = ox * rot[0, 1] + oy * rot[1, 1] + oz * rot[2, 1]
                zc = ox * rot[0, 2] + oy * rot[1, 2] + oz * rot[2, 2]
                # its foot on the reaching pixel's plane (nx = ny = nz = 0: the centre itself)
                off = (xf - px0) * nx + (yf - py0) * ny + (zc - z) * nz
                xf, yf, zf = xf - off * nx, yf - off * ny, zc - off * nz
                cr, cg, cb, cz = r, g, b, z
                if zf > 0.0:
                    pu = math.floor(fx * xf / zf + cx)
                    pv = math.floor(fy * yf / zf + cy)
                    if 0 <= pu < w and 0 <= pv < h:
                        zp = depth[pv, pu]
                        if zp > 0.0 and abs(zp - z) <= same_surface:  # not across a depth edge
                            cr, cg, cb, cz = color[pv, pu, 0] / 255.0, color[pv, pu, 1] / 255.0, \
                                color[pv, pu, 2] / 255.0, zp
                wt = min(cells[row, 3] + 1.0, max_weight)
                cells[row, 0] += (cr - cells[row, 0]) / wt
                cells[row, 1] += (cg - cells[row, 1]) / wt
                cells[row, 2] += (cb - cells[row, 2]) / wt
                cells[row, 4] += (cz - zc - cells[row, 4]) / wt
                cells[row, 3] = wt
    return n, refused


@nb.njit(parallel=True, cache=True, nogil=True)
def sample_cells(slots, keys, cells, pts, cell, out, known):
    """``out[i]`` = the colour at ``pts[i]`` (world, m), trilinear between the centres of the 8
    cells around it, renormalised over those that hold a colour; where none does, the mean of the
    known cells among the 27 around the cell it lies in (a gap between fused pixels); ``known[i]``
    False (``out`` untouched) where none of those does either."""
    mask = len(slots) - 1
    inv = 1.0 / cell
    for i in nb.prange(len(pts)):
        ix, iy, iz, fx, fy, fz = _corners(pts[i], inv)
        r = g = b = ws = 0.0
        for c in range(8):
            row = _corner_row(slots, keys, mask, ix, iy, iz, c)
            if row < 0 or cells[row, 3] <= 0.0:
                continue
            wc = corner_weight(fx, fy, fz, c)
            r += wc * cells[row, 0]
            g += wc * cells[row, 1]
            b += wc * cells[row, 2]
            ws += wc
        if ws <= 1e-6:  # none of the 8: the mean of the known cells around the one it lies in
            jx, jy, jz = ix + int(fx >= 0.5), iy + int(fy >= 0.5), iz + int(fz >= 0.5)  # the cell it lies in
            for c in range(27):
                key = _key(jx + c % 3 - 1, jy + (c // 3) % 3 - 1, jz + c // 9 - 1)
                if key < 0:
                    continue
                row, _ = _find(slots, keys, key, mask)
                if row < 0 or cells[row, 3] <= 0.0:
                    continue
                r += cells[row, 0]
                g += cells[row, 1]
                b += cells[row, 2]
                ws += 1.0
        if ws > 1e-6:
            out[i, 0], out[i, 1], out[i, 2] = r / ws, g / ws, b / ws
            known[i] = True
        else:
            known[i] = False


@nb.njit(parallel=True, cache=True, nogil=True)
def sample_distance(slots, keys, cells, pts, cell, out, known):
    """``out[i]`` = the fused signed distance (m, positive in front of the surface) at ``pts[i]``
    (world, m), trilinear between the centres of the 8 cells around it, renormalised over those that
    hold one; ``known[i]`` where those carry at least half the trilinear weight (``out`` untouched
    elsewhere). A cell holds one where its weight is > 0 and its distance finite."""
    mask = len(slots) - 1
    inv = 1.0 / cell
    for i in nb.prange(len(pts)):
        ix, iy, iz, fx, fy, fz = _corners(pts[i], inv)
        d = ws = 0.0
        for c in range(8):
            row = _corner_row(slots, keys, mask, ix, iy, iz, c)
            if row < 0 or cells[row, 3] <= 0.0 or not math.isfinite(cells[row, 4]):
                continue
            wc = corner_weight(fx, fy, fz, c)
            d += wc * cells[row, 4]
            ws += wc
        known[i] = ws >= 0.5
        if known[i]:
            out[i] = d / ws


@nb.njit(cache=True, nogil=True)
def distance_volume(slots, keys, cells, i0, j0, k0, out):
    """``out[a, b, c]`` = the fused signed distance (m) of cell (i0 + a, j0 + b, k0 + c), NaN where no
    cell holds one (not in the table, weight <= 0 or not finite)."""
    mask = len(slots) - 1
    na, nb_, nc = out.shape
    for a in range(na):
        for b in range(nb_):
            for c in range(nc):
                out[a, b, c] = np.nan
                key = _key(i0 + a, j0 + b, k0 + c)
                if key < 0:
                    continue
                row, _ = _find(slots, keys, key, mask)
                if row >= 0 and cells[row, 3] > 0.0 and math.isfinite(cells[row, 4]):
                    out[a, b, c] = cells[row, 4]
