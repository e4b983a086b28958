"""Fused numba kernels over open-addressed voxel hash tables: the renderer's prior march and the
allocated-voxel samples of its full-SDF search (see :mod:`h3edge.mapping.raymarch`), the point
location that training and the prior lookups share (:meth:`h3edge.mapping.voxels.VoxelMap.locate`),
the grouping of a frame's points by voxel that allocation starts from, and the cells free space
marks along a frame's rays.

Module-level so numba's on-disk cache is reused across processes (a closure recompiled, ~10 s,
in every process: the first render of a service would have paid it).
"""

import math

import numba as nb
import numpy as np

from h3edge.mapping._trilinear_kernel import corner_weight

_BITS = 21  # as h3edge.mapping.voxels packs keys
_OFF = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


@nb.njit(inline="always")
def slot_of(key, mask):
    """Home slot of a packed voxel key in a table of ``mask + 1`` slots (a power of two, at most
    2^32): bits 32 and up of the key times the golden ratio (Fibonacci hashing)."""
    return np.int64((np.uint64(key) * _GOLDEN) >> np.uint64(32)) & mask

@nb.njit(inline="always")
def voxel_at(cx, cy, cz, hkeys, hids):
    """Voxel id (or -1) of the voxel with integer corner (cx, cy, cz), through the open-addressed
    voxel table (``hkeys``: packed keys, -1 = empty slot; linear probing)."""
    ix, iy, iz = np.int64(cx) + _OFF, np.int64(cy) + _OFF, np.int64(cz) + _OFF
    if ix < 0 or iy < 0 or iz < 0 or ix > _MASK or iy > _MASK or iz > _MASK:
        return -1
    key = (iz << (2 * _BITS)) | (iy << _BITS) | ix
    mask = hkeys.shape[0] - 1
    s = slot_of(key, mask)
    while True:
        k = hkeys[s]
        if k == key:
            return hids[s]
        if k < 0:
            return -1
        s = (s + 1) & mask

@nb.njit(cache=True, nogil=True)
def build_table(keys, hkeys, hids):
    """Insert packed ``keys`` (unique) with ids 0..n-1 into the empty table ``hkeys`` / ``hids``
    (power-of-two length, more slots than keys)."""
    mask = hkeys.shape[0] - 1
    for i in range(keys.shape[0]):
        s = slot_of(keys[i], mask)
        while hkeys[s] >= 0:
            s = (s + 1) & mask
        hkeys[s] = keys[i]
        hids[s] = i

@nb.njit(cache=True, nogil=True)
def ray_cell_keys(rays, reach, rot, trans, voxel_size):
    """Free space's cells (:mod:`h3edge.mapping.free_space`): keys (as
    :func:`~h3edge.mapping.voxels.pack`) of the cells at the samples half a voxel apart (z-depths
    (i + 0.5) * voxel_size / 2 < ``reach[r]``) along each camera ray ``rays[r]`` (z = 1) posed by
    ``rot``, ``trans`` (camera to world); a sample in the previous sample's cell is left out, and
    so are cells outside the packable range; a ray with a non-finite reach marks none. Unsorted, with
    repeats across rays."""
    step = 0.5 * voxel_size
    out = np.empty(64, np.int64)
    n = 0
    for r in range(len(rays)):
        if not math.isfinite(reach[r]):  # no bound to march to: the ray marks nothing
            continue
        last = np.int64(-1)
        i = 0
        while True:
            t = (i + 0.5) * step
            if not t < reach[r]:
                break
            i += 1
            x, y = rays[r, 0] * t, rays[r, 1] * t
            a = math.floor((rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * t + trans[0]) / voxel_size) + _OFF
            b = math.floor((rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * t + trans[1]) / voxel_size) + _OFF
            c = math.floor((rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * t + trans[2]) / voxel_size) + _OFF
            if a < 0 or a > _MASK or b < 0 or b > _MASK or c < 0 or c > _MASK:
                continue
            key = (np.int64(c) << (2 * _BITS)) | (np.int64(b) << _BITS) | np.int64(a)
            if key == last:
                continue
            last = key
            if n == len(out):
                grown = np.empty(2 * n, np.int64)
                grown[:n] = out
                out = grown
            out[n] = key
            n += 1
    return out[:n]


@nb.njit(cache=True, nogil=True)
def voxel_point_stats(pts, vs, hkeys, counts, sums, every, picked):
    """Group points (metres; rows with a non-finite coordinate are skipped) by the voxel that
    contains them, through the empty table ``hkeys`` (power-of-two length): per slot, the voxel's
    packed key, its point count, the sum of its points and in ``picked`` how many of them are among
    every ``every``-th point kept (the 0th, ``every``-th, ... of the finite rows). Returns the
    slots used, -1 when the table passed half full (the caller retries with a larger one) or -2 when
    a point lies outside the +-2^20 voxel range of the packed keys."""
    mask = hkeys.shape[0] - 1
    used = 0
    tick = 0  # finite rows to skip before the next picked one
    last_key, s = np.int64(-1), 0  # the previous point's voxel and slot: neighbouring pixels share voxels
    for i in range(pts.shape[0]):
        x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            continue
        ix = np.int64(math.floor(x / vs)) + _OFF
        iy = np.int64(math.floor(y / vs)) + _OFF
        iz = np.int64(math.floor(z / vs)) + _OFF
        if ix < 0 or iy < 0 or iz < 0 or ix > _MASK or iy > _MASK or iz > _MASK:
            return -2
        key = (iz << (2 * _BITS)) | (iy << _BITS) | ix
        if key != last_key:
            s = slot_of(key, mask)
            while hkeys[s] != key and hkeys[s] >= 0:
                s = (s + 1) & mask
            if hkeys[s] < 0:
                used += 1
                if 2 * used > hkeys.shape[0]:
                    return -1
                hkeys[s] = key
            last_key = key
        counts[s] += 1
        sums[s, 0] += x
        sums[s, 1] += y
        sums[s, 2] += z
        if tick == 0:  # this row is one of every ``every``-th
            picked[s] += 1
            tick = every
        tick -= 1
    return used

@nb.njit(inline="always")
def interpolate(vid, ux, uy, uz, vv, priors):
    """Trilinear prior at fraction (ux, uy, uz) inside voxel ``vid``."""
    s = 0.0
    for c in range(8):
        s += corner_weight(ux, uy, uz, c) * priors[vv[vid, c]]
    return s

@nb.njit(inline="always")
def trilinear(px, py, pz, hkeys, hids, vv, priors):
    """(voxel id or -1, trilinear prior) at a point in voxel units, through the voxel table."""
    fx, fy, fz = math.floor(px), math.floor(py), math.floor(pz)
    vid = voxel_at(fx, fy, fz, hkeys, hids)
    if vid < 0:
        return -1, 0.0
    return vid, interpolate(vid, px - fx, py - fy, pz - fz, vv, priors)

@nb.njit(inline="always")
def face(o, dirs, r, t_in, s_in, t_out, hkeys, hids, vs, vv, priors):
    """Bisect between an allocated sample (t_in, prior s_in) and an unallocated one (t_out):
    the allocated point nearest the region's face and its prior (t_in, s_in if none is nearer)."""
    a, b = t_in, t_out
    for _ in range(8):
        mid = 0.5 * (a + b)
        v_mid, s_mid = trilinear((o[0] + dirs[r, 0] * mid) / vs, (o[1] + dirs[r, 1] * mid) / vs,
                                 (o[2] + dirs[r, 2] * mid) / vs, hkeys, hids, vv, priors)
        if v_mid < 0:
            b = mid
        else:
            a, t_in, s_in = mid, mid, s_mid
    return t_in, s_in

@nb.njit(inline="always")
def _box_clip(o, dirs, r, t0, t1, lo, hi):
    """[t0, t1] of ray ``r`` clipped to the box [lo, hi] (metres); t0 > t1 when it misses."""
    for a in range(3):
        d = dirs[r, a]
        if abs(d) < 1e-12:
            if o[a] < lo[a] or o[a] > hi[a]:
                return 1.0, 0.0
            continue
        ta, tb = (lo[a] - o[a]) / d, (hi[a] - o[a]) / d
        if ta > tb:
            ta, tb = tb, ta
        t0, t1 = max(t0, ta), min(t1, tb)
    return t0, t1

@nb.njit(parallel=True, fastmath=False, cache=True, nogil=True)
def march(o, dirs, nears, far, step, hkeys, hids, box_lo, box_hi, vs, vv, priors, exit_tol, out):
    # box_lo / box_hi: integer corners of the allocated voxels' bounding box (hi exclusive)
    lo = (box_lo[0] * vs, box_lo[1] * vs, box_lo[2] * vs)
    hi = (box_hi[0] * vs, box_hi[1] * vs, box_hi[2] * vs)
    for r in nb.prange(dirs.shape[0]):
        out[r] = -1.0
        t0, t1 = _box_clip(o, dirs, r, nears[r], far, lo, hi)
        if t0 >= t1:
            continue
        prev = math.nan
        prev_t = 0.0
        t = t0
        while t <= t1:
            vid, s = trilinear((o[0] + dirs[r, 0] * t) / vs, (o[1] + dirs[r, 1] * t) / vs,
                               (o[2] + dirs[r, 2] * t) / vs, hkeys, hids, vv, priors)
            if vid < 0:
                if prev > 0.0:
                    # leaving the allocated region while the prior is still positive: find the
                    # exit point (bisection); the surface may lie in the last sliver before it
                    a_, s_in = face(o, dirs, r, prev_t, prev, t, hkeys, hids, vs, vv, priors)
                    if s_in <= 0.0:
                        out[r] = prev_t + (a_ - prev_t) * prev / (prev - s_in)
                        break
                    if s_in < exit_tol and s_in < prev and a_ > prev_t:
                        # just short of zero at the region's back face: extrapolate a little
                        out[r] = min(a_ + (a_ - prev_t) * s_in / (prev - s_in), a_ + step)
                        break
                prev = math.nan
                t += step
                continue
            if prev != prev and t > t0:
                # just entered the allocated region: find the entry point (bisection) and use
                # the prior there, so a surface just inside the region's face is not stepped over
                prev_t, prev = face(o, dirs, r, t, s, t - step, hkeys, hids, vs, vv, priors)
                if prev_t < t and -exit_tol < prev <= 0.0:
                    # entering just behind the surface: it lies at the region's front face
                    out[r] = prev_t
                    break
            if prev > 0.0 and s <= 0.0:
                out[r] = prev_t + (t - prev_t) * prev / (prev - s)
                break
            prev, prev_t = s, t
            t += step
    return out

@nb.njit(inline="always")
def cell_of(px, py, pz, hkeys, hids, eps):
    """(voxel id or -1, its integer corner) of a point in voxel units, as ``VoxelMap.locate``
    defines it: the voxel ``floor`` picks, else the first allocated voxel across the faces the point
    lies on (within ``eps`` voxels), the lower side first along each such axis (corners 0..7).
    Priors are shared at vertices, so the value is the same from either side of a face."""
    gx, gy, gz = math.floor(px), math.floor(py), math.floor(pz)
    v = voxel_at(gx, gy, gz, hkeys, hids)
    if v >= 0:
        return v, gx, gy, gz
    ax, ay, az = round(px), round(py), round(pz)
    on_x, on_y, on_z = abs(px - ax) < eps, abs(py - ay) < eps, abs(pz - az) < eps
    for c in range(8):
        bx, by, bz = c & 1, (c >> 1) & 1, (c >> 2) & 1
        if (bx and not on_x) or (by and not on_y) or (bz and not on_z):
            continue  # the same candidate as a lower corner number
        cx = (ax if bx else ax - 1) if on_x else gx
        cy = (ay if by else ay - 1) if on_y else gy
        cz = (az if bz else az - 1) if on_z else gz
        v = voxel_at(cx, cy, cz, hkeys, hids)
        if v >= 0:
            return v, cx, cy, cz
    return -1, gx, gy, gz

@nb.njit(parallel=True, cache=True, nogil=True)
def locate_cells(pts, hkeys, hids, vs, eps, vox, frac):
    """Voxel id (-1 outside) of points (metres) and their position inside it, clipped to [0, 1]^3
    (:func:`cell_of`)."""
    for i in nb.prange(pts.shape[0]):
        px, py, pz = pts[i, 0] / vs, pts[i, 1] / vs, pts[i, 2] / vs
        v, gx, gy, gz = cell_of(px, py, pz, hkeys, hids, eps)
        vox[i] = v
        frac[i, 0] = min(max(px - gx, 0.0), 1.0)
        frac[i, 1] = min(max(py - gy, 0.0), 1.0)
        frac[i, 2] = min(max(pz - gz, 0.0), 1.0)

@nb.njit(parallel=True, cache=True, nogil=True)
def locate_prior(pts, hkeys, hids, vs, vv, priors, eps, sdf, vox):
    """Voxel id (-1 outside) and trilinear prior (0 outside) of points (metres) (:func:`cell_of`)."""
    for i in nb.prange(pts.shape[0]):
        px, py, pz = pts[i, 0] / vs, pts[i, 1] / vs, pts[i, 2] / vs
        v, gx, gy, gz = cell_of(px, py, pz, hkeys, hids, eps)
        s = 0.0
        if v >= 0:
            s = interpolate(v, min(max(px - gx, 0.0), 1.0), min(max(py - gy, 0.0), 1.0),
                            min(max(pz - gz, 0.0), 1.0), vv, priors)
        vox[i], sdf[i] = v, s

@nb.njit(parallel=True, cache=True, nogil=True)
def allocated_samples(o, dirs, t_lo, t_hi, step, hkeys, hids, box_lo, box_hi, vs, vv, priors, offsets,
                      ts, prior, fill):
    """Samples every ``step`` along each ray from ``t_lo`` to ``t_hi`` that lie in allocated voxels.
    With ``fill`` False: their count per ray into ``offsets[r + 1]``; with ``fill`` True (``offsets``
    now the cumulative counts): their ray parameters and trilinear priors into ``ts`` / ``prior``
    from ``offsets[r]`` on. The samples sit on one grid per ray, so two of them are neighbours when
    their parameters differ by one step."""
    lo = (box_lo[0] * vs, box_lo[1] * vs, box_lo[2] * vs)
    hi = (box_hi[0] * vs, box_hi[1] * vs, box_hi[2] * vs)
    for r in nb.prange(dirs.shape[0]):
        t0, t1 = _box_clip(o, dirs, r, t_lo[r], t_hi[r], lo, hi)
        # start on the ray's grid t_lo + k step, so clipping does not shift the samples
        k = math.ceil((t0 - t_lo[r]) / step) if t0 > t_lo[r] else 0
        c = offsets[r] if fill else 0
        t = t_lo[r] + k * step
        while t <= t1:
            vid, s = trilinear((o[0] + dirs[r, 0] * t) / vs, (o[1] + dirs[r, 1] * t) / vs,
                               (o[2] + dirs[r, 2] * t) / vs, hkeys, hids, vv, priors)
            if vid >= 0:
                if fill:
                    ts[c] = t
                    prior[c] = s
                c += 1
            k += 1
            t = t_lo[r] + k * step
        if not fill:
            offsets[r + 1] = c
