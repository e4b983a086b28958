"""Numba CPU kernels of the fused colour base (see :mod:`h3edge.mapping.color_base`), laid out as
TSDF fusion's voxel block grids are: 4^3 blocks of fine cells, an open-addressed hash table of the
blocks (int64 block keys, linear probing, ``bslots`` holding block rows, -1 empty), and each block's
64 cells in consecutive rows of ``cells`` (block row b holds rows 64 b .. 64 b + 63, the cell at
local (x, y, z) in row 64 b + x + 4 y + 16 z; R, G, B, weight, signed distance; weight 0: no cell
there yet). A frame is fused in two passes (``reach_blocks``: the blocks its pixels reach;
``fuse_cells``: every cell of those near its depth), the colour and distance are read back with
trilinear weights between cell centres (``sample_cells``, ``sample_distance``, ``distance_volume``),
and a table is filled from listed cells (``load_cells``).

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
    """Packed key of integer coordinates (i, j, k); -1 outside the representable range."""
    a, b, c = i + _OFF, j + _OFF, k + _OFF
    if a < 0 or a > _MASK or b < 0 or b > _MASK or c < 0 or c > _MASK:
        return -1
    return (np.int64(c) << (2 * _BITS)) | (np.int64(b) << _BITS) | np.int64(a)


@nb.njit(inline="always")
def _find_block(bslots, bkeys, key, mask):
    """(block row of ``key`` or -1, the slot where it is or would go)."""
    s = np.int64((np.uint64(key) * _GOLDEN) >> np.uint64(32)) & mask
    while True:
        row = bslots[s]
        if row < 0:
            return -1, s
        if bkeys[row] == key:
            return row, s
        s = (s + 1) & mask


@nb.njit(inline="always")
def _cell_row(bslots, bkeys, mask, ix, iy, iz):
    """Row of cell (ix, iy, iz) (held or not: check its weight); -1 where its block is not held."""
    key = _key(ix >> 2, iy >> 2, iz >> 2)  # arithmetic shifts: floor division by 4
    if key < 0:
        return -1
    brow, _ = _find_block(bslots, bkeys, key, mask)
    if brow < 0:
        return -1
    return brow * 64 + (ix & 3) + ((iy & 3) << 2) + ((iz & 3) << 4)


@nb.njit(inline="always")
def _corners(p, inv):
    """The lattice of cell centres around world point ``p`` (cell = 1 / ``inv`` m): the lower corner
    cell (ix, iy, iz) and the point's fractions (fx, fy, fz) towards the upper one, for
    ``corner_weight``."""
    qx, qy, qz = p[0] * inv - 0.5, p[1] * inv - 0.5, p[2] * inv - 0.5
    ix, iy, iz = math.floor(qx), math.floor(qy), math.floor(qz)
    return ix, iy, iz, qx - ix, qy - iy, qz - iz


@nb.njit(inline="always")
def _new_block(bslots, bkeys, cells, nblocks, key, s):
    """Hold block ``key`` in row ``nblocks`` (slot ``s``, from :func:`_find_block`), its cells empty."""
    bkeys[nblocks] = key
    bslots[s] = nblocks
    cells[nblocks * 64:(nblocks + 1) * 64, :] = 0.0


@nb.njit(cache=True, nogil=True)
def load_cells(bslots, bkeys, cells, keys, rows):
    """Fill empty tables with the cells ``keys`` (packed cell coordinates) whose rows (R, G, B,
    weight, distance) are ``rows``; returns the blocks in use, -1 where more than ``len(bkeys)``
    would be."""
    mask = len(bslots) - 1
    nblocks = 0
    for i in range(len(keys)):
        key = keys[i]
        ix, iy, iz = (key & _MASK) - _OFF, ((key >> _BITS) & _MASK) - _OFF, ((key >> (2 * _BITS)) & _MASK) - _OFF
        bkey = _key(ix >> 2, iy >> 2, iz >> 2)
        brow, s = _find_block(bslots, bkeys, bkey, mask)
        if brow < 0:
            if nblocks >= len(bkeys):
                return -1
            _new_block(bslots, bkeys, cells, nblocks, bkey, s)
            brow = nblocks
            nblocks += 1
        cells[brow * 64 + (ix & 3) + ((iy & 3) << 2) + ((iz & 3) << 4), :] = rows[i]
    return nblocks


@nb.njit(cache=True, nogil=True)
def reach_blocks(bslots, bkeys, cells, nblocks, depth, rot, trans, fx, fy, cx, cy, max_stride, reach, cell, band,
                 stamp, frame, touched, stop_when_full):
    """Pass one of fusing a frame: each pixel with valid depth z whose column and row are multiples
    of its stride s(z) = clip(floor(``reach`` / z), 1, ``max_stride``) (fused pixels at most reach /
    f apart on the surface, wherever it is) reaches the points at z-depths z + k * ``cell``,
    k = -band..band, along its ray (pixel centre; ``rot``, ``trans``: camera to world), and the 4^3
    blocks of cells they fall in: a block not held yet takes a row (its cells empty) from
    ``nblocks`` up to ``len(bkeys)``; past it the point is refused, but where ``stop_when_full`` a
    full table ends the pass at once (for the caller to grow it and run it again). (Reaching the
    blocks out to ``trunc`` as well, every half block, fused 0.5 % more of the cells each frame on
    the real set, for 40 % more time: D53-13.) The block rows
    the frame reached are written to ``touched``, each once (``stamp``: the frame number that last
    touched each block row, set to ``frame`` here). Returns (blocks in use, blocks touched, points
    refused, whether it stopped at a full table)."""
    h, w = depth.shape
    mask = len(bslots) - 1
    bcap = len(bkeys)
    inv = 0.25 / cell  # blocks a metre
    refused = 0
    ntouched = 0
    last = np.int64(-1)  # the block the previous point fell in: the next one's is often the same
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
            for k in range(-band, band + 1):
                zz = z + k * cell
                if zz <= 0.0:
                    continue
                x, y = xc * zz, yc * zz
                px = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * zz + trans[0]
                py = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * zz + trans[1]
                pz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * zz + trans[2]
                key = _key(math.floor(px * inv), math.floor(py * inv), math.floor(pz * inv))
                if key < 0 or key == last:
                    continue
                brow, s = _find_block(bslots, bkeys, key, mask)
                if brow < 0:
                    if nblocks >= bcap:
                        if stop_when_full:
                            return nblocks, ntouched, refused, True
                        refused += 1
                        continue
                    _new_block(bslots, bkeys, cells, nblocks, key, s)
                    brow = nblocks
                    nblocks += 1
                last = key
                if stamp[brow] != frame:  # the block's first point this frame
                    stamp[brow] = frame
                    touched[ntouched] = brow
                    ntouched += 1
    return nblocks, ntouched, refused, False


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


# fast maths without assuming finite values: the NaN and infinity checks on depth stay
@nb.njit(parallel=True, cache=True, nogil=True, fastmath={"contract", "arcp", "afn", "reassoc"})
def fuse_cells(touched, bkeys, cells, depth, color, rot, trans, fx, fy, cx, cy, cell, band, trunc, max_weight,
               normal_px, stride, phase):
    """Pass two of fusing a frame, as TSDF fusion does: every cell of the blocks ``touched`` whose
    centre projects into a pixel of depth d (``rot``, ``trans``: camera to world) fuses that pixel,
    once a frame: a cell held already where its own z-depth lies within ``trunc`` (m) of d, in front
    or behind (each frame that sees it near its surface, not only those whose pixel samples fell
    into it, D53-13), a new one where it lies within the ``band`` + 1/2 cells of d that pixels'
    samples reach (the volume the render weights live in). It fuses the colour (uint8 RGB -> [0, 1])
    where the surface point nearest its centre projects: its foot on the plane through the pixel's
    point with the normal its neighbours ``normal_px`` pixels away span (:func:`_pixel_normal`; the
    centre itself where they do not: 0, an image border, a missing neighbour, or the three pixels of
    a row or column more than a cell off one plane; the plane at the pixel the block's centre
    projects into serves every cell whose pixel lies within half a cell of it: 19.8 -> 10.8 ms a
    loft frame on one thread, 0.07 dB), and its signed distance in front of that
    pixel's depth; where that pixel has no depth or lies across a depth edge (> 2 (band + 1) cells
    from d), the centre's own pixel. (A cell off the surface read at its own centre takes each
    view's colour from a different surface point, up to its distance from the surface times the
    tangent of the view's incidence: a blur, D53-12.) Both as running averages (a row: R, G, B,
    weight, signed distance) whose weight grows by one a fusion up to ``max_weight``. Only the cells
    (i, j, k) with ``(i + j + k) % stride == phase`` fuse (``stride`` 1, ``phase`` 0: every cell).
    Returns the cells it made."""
    h, w = depth.shape
    same_surface = 2.0 * (band + 1) * cell  # m: a projected pixel's depth this near d is its surface
    reach_new = (band + 0.5) * cell  # m: how near d a new cell's centre lies
    made = 0
    for t in nb.prange(len(touched)):
        brow = touched[t]
        bkey = bkeys[brow]
        bx = ((bkey & _MASK) - _OFF) * 4
        by = (((bkey >> _BITS) & _MASK) - _OFF) * 4
        bz = (((bkey >> (2 * _BITS)) & _MASK) - _OFF) * 4
        # the plane at the pixel the block's centre projects into: its cells' pixels on it share its normal
        ox = (bx + 2.0) * cell - trans[0]
        oy = (by + 2.0) * cell - trans[1]
        oz = (bz + 2.0) * cell - trans[2]
        zb = ox * rot[0, 2] + oy * rot[1, 2] + oz * rot[2, 2]
        bnx = bny = bnz = 0.0
        bpx = bpy = bpz = 0.0
        if zb > 0.0:
            ub = math.floor(fx * (ox * rot[0, 0] + oy * rot[1, 0] + oz * rot[2, 0]) / zb + cx)
            vb = math.floor(fy * (ox * rot[0, 1] + oy * rot[1, 1] + oz * rot[2, 1]) / zb + cy)
            if 0 <= ub < w and 0 <= vb < h:
                db = depth[vb, ub]
                if db > 0.0 and math.isfinite(db):
                    xcb, ycb = (ub + 0.5 - cx) / fx, (vb + 0.5 - cy) / fy
                    bnx, bny, bnz = _pixel_normal(depth, ub, vb, db, xcb, ycb, fx, fy, cx, cy, normal_px, cell)
                    bpx, bpy, bpz = xcb * db, ycb * db, db
        # the first cell's centre in this camera, and one cell's step along each world axis
        ox = (bx + 0.5) * cell - trans[0]
        oy = (by + 0.5) * cell - trans[1]
        oz = (bz + 0.5) * cell - trans[2]
        x0 = ox * rot[0, 0] + oy * rot[1, 0] + oz * rot[2, 0]
        y0 = ox * rot[0, 1] + oy * rot[1, 1] + oz * rot[2, 1]
        z0 = ox * rot[0, 2] + oy * rot[1, 2] + oz * rot[2, 2]
        sxx, sxy, sxz = cell * rot[0, 0], cell * rot[0, 1], cell * rot[0, 2]
        syx, syy, syz = cell * rot[1, 0], cell * rot[1, 1], cell * rot[1, 2]
        szx, szy, szz = cell * rot[2, 0], cell * rot[2, 1], cell * rot[2, 2]
        for c in range(64):
            row = brow * 64 + c
            # the cell centre in this camera
            a, b, g = c & 3, (c >> 2) & 3, c >> 4
            if stride > 1 and (bx + by + bz + a + b + g) % stride != phase:  # (Python's %: never negative)
                continue
            zc = z0 + a * sxz + b * syz + g * szz
            if not zc > 0.0:
                continue
            xf = x0 + a * sxx + b * syx + g * szx
            yf = y0 + a * sxy + b * syy + g * szy
            iz = 1.0 / zc
            u = math.floor(fx * xf * iz + cx)
            v = math.floor(fy * yf * iz + cy)
            if u < 0 or v < 0 or u >= w or v >= h:
                continue
            d = depth[v, u]
            if not (d > 0.0) or not math.isfinite(d):
                continue
            held = cells[row, 3] > 0.0
            if abs(d - zc) > (trunc if held else reach_new):
                continue
            pu, pv, cz = u, v, d
            xc, yc = (u + 0.5 - cx) / fx, (v + 0.5 - cy) / fy
            if (bnx != 0.0 or bny != 0.0 or bnz != 0.0) and abs((xc * d - bpx) * bnx + (yc * d - bpy) * bny
                                                                + (d - bpz) * bnz) <= 0.5 * cell:
                nx, ny, nz = bnx, bny, bnz  # the pixel lies on the block's plane
            else:
                nx, ny, nz = _pixel_normal(depth, u, v, d, xc, yc, fx, fy, cx, cy, normal_px, cell)
            if nx != 0.0 or ny != 0.0 or nz != 0.0:
                # the centre's foot on the pixel's plane, and the pixel it projects into
                off = (xf - xc * d) * nx + (yf - yc * d) * ny + (zc - d) * nz
                xq, yq, zq = xf - off * nx, yf - off * ny, zc - off * nz
                if zq > 0.0:
                    qu = math.floor(fx * xq / zq + cx)
                    qv = math.floor(fy * yq / zq + cy)
                    if 0 <= qu < w and 0 <= qv < h:
                        zp = depth[qv, qu]
                        if zp > 0.0 and abs(zp - d) <= same_surface:  # not across a depth edge
                            pu, pv, cz = qu, qv, zp
            if not held:
                made += 1
            wt = min(cells[row, 3] + 1.0, max_weight)
            cells[row, 0] += (color[pv, pu, 0] / 255.0 - cells[row, 0]) / wt
            cells[row, 1] += (color[pv, pu, 1] / 255.0 - cells[row, 1]) / wt
            cells[row, 2] += (color[pv, pu, 2] / 255.0 - cells[row, 2]) / wt
            cells[row, 4] += (cz - zc - cells[row, 4]) / wt
            cells[row, 3] = wt
    return made


@nb.njit(parallel=True, cache=True, nogil=True)
def sample_cells(bslots, bkeys, cells, pts, cell, out, known):
    """``out[i]`` = the colour at ``pts[i]`` (world, m), trilinear between the centres of the 8
    cells around it, renormalised over those that hold a colour; where none does, the mean of the
    known cells among the 27 around the cell it lies in (a gap between fused pixels); ``known[i]``
    False (``out`` untouched) where none of those does either."""
    mask = len(bslots) - 1
    inv = 1.0 / cell
    for i in nb.prange(len(pts)):
        ix, iy, iz, fx, fy, fz = _corners(pts[i], inv)
        r = g = b = ws = 0.0
        for c in range(8):
            row = _cell_row(bslots, bkeys, mask, ix + (c & 1), iy + ((c >> 1) & 1), iz + ((c >> 2) & 1))
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
                row = _cell_row(bslots, bkeys, mask, jx + c % 3 - 1, jy + (c // 3) % 3 - 1, jz + c // 9 - 1)
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
def sample_distance(bslots, bkeys, cells, pts, cell, out, known):
    """``out[i]`` = the fused signed distance (m, positive in front of the surface) at ``pts[i]``
    (world, m), trilinear between the centres of the 8 cells around it, renormalised over those that
    hold one; ``known[i]`` where those carry at least half the trilinear weight (``out`` untouched
    elsewhere). A cell holds one where its weight is > 0 and its distance finite."""
    mask = len(bslots) - 1
    inv = 1.0 / cell
    for i in nb.prange(len(pts)):
        ix, iy, iz, fx, fy, fz = _corners(pts[i], inv)
        d = ws = 0.0
        for c in range(8):
            row = _cell_row(bslots, bkeys, mask, ix + (c & 1), iy + ((c >> 1) & 1), iz + ((c >> 2) & 1))
            if row < 0 or cells[row, 3] <= 0.0 or not math.isfinite(cells[row, 4]):
                continue
            wc = corner_weight(fx, fy, fz, c)
            d += wc * cells[row, 4]
            ws += wc
        known[i] = ws >= 0.5
        if known[i]:
            out[i] = d / ws


@nb.njit(cache=True, nogil=True)
def distance_volume(bslots, bkeys, cells, i0, j0, k0, out):
    """``out[a, b, c]`` = the fused signed distance (m) of cell (i0 + a, j0 + b, k0 + c), NaN where no
    cell holds one (not in the table, weight <= 0 or not finite)."""
    mask = len(bslots) - 1
    na, nb_, nc = out.shape
    for a in range(na):
        for b in range(nb_):
            for c in range(nc):
                out[a, b, c] = np.nan
                row = _cell_row(bslots, bkeys, mask, i0 + a, j0 + b, k0 + c)
                if row >= 0 and cells[row, 3] > 0.0 and math.isfinite(cells[row, 4]):
                    out[a, b, c] = cells[row, 4]


@nb.njit(cache=True, nogil=True)
def rebuild_block_slots(bkeys, nblocks, capacity):
    """A block slot table of ``capacity`` (a power of two) holding block rows 0..nblocks-1."""
    bslots = np.full(capacity, -1, np.int32)
    mask = capacity - 1
    for row in range(nblocks):
        _, s = _find_block(bslots, bkeys, bkeys[row], mask)
        bslots[s] = row
    return bslots


@nb.njit(cache=True, nogil=True)
def held_cells(bkeys, cells, nblocks):
    """The cells held (weight > 0) in blocks 0..nblocks-1: their packed cell keys (N,) int64 and rows
    (N, 5) float32 (R, G, B, weight, distance), block by block."""
    n = 0
    for row in range(64 * nblocks):
        if cells[row, 3] > 0.0:
            n += 1
    keys = np.empty(n, np.int64)
    rows = np.empty((n, 5), np.float32)
    i = 0
    for b in range(nblocks):
        bkey = bkeys[b]
        bx = ((bkey & _MASK) - _OFF) * 4
        by = (((bkey >> _BITS) & _MASK) - _OFF) * 4
        bz = (((bkey >> (2 * _BITS)) & _MASK) - _OFF) * 4
        for c in range(64):
            row = b * 64 + c
            if cells[row, 3] > 0.0:
                keys[i] = _key(bx + (c & 3), by + ((c >> 2) & 3), bz + (c >> 4))
                rows[i, :] = cells[row, :]
                i += 1
    return keys, rows
