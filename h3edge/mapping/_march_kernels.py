"""Fused numba kernels of the renderer's prior march (see :mod:`h3edge.mapping.render`).

Module-level so numba's on-disk cache is reused across processes (a closure recompiled, ~10 s,
in every process: the first render of a service would have paid it).
"""

import math

import numba as nb


@nb.njit(inline="always")
def voxel_at(cx, cy, cz, grid, g0):
    """Voxel id (or -1) of the voxel with integer corner (cx, cy, cz), through the dense id grid."""
    ix, iy, iz = int(cx) - g0[0], int(cy) - g0[1], int(cz) - g0[2]
    if not (0 <= ix < grid.shape[0] and 0 <= iy < grid.shape[1] and 0 <= iz < grid.shape[2]):
        return -1
    return grid[ix, iy, iz]

@nb.njit(inline="always")
def interpolate(vid, ux, uy, uz, vv, priors):
    """Trilinear prior at fraction (ux, uy, uz) inside voxel ``vid``."""
    s = 0.0
    for c in range(8):
        w = (ux if c & 1 else 1.0 - ux) * (uy if (c >> 1) & 1 else 1.0 - uy) * (uz if (c >> 2) & 1 else 1.0 - uz)
        s += w * priors[vv[vid, c]]
    return s

@nb.njit(inline="always")
def trilinear(px, py, pz, grid, g0, vv, priors):
    """(voxel id or -1, trilinear prior) at a point in voxel units, through the dense id grid."""
    fx, fy, fz = math.floor(px), math.floor(py), math.floor(pz)
    vid = voxel_at(fx, fy, fz, grid, g0)
    if vid < 0:
        return -1, 0.0
    return vid, interpolate(vid, px - fx, py - fy, pz - fz, vv, priors)

@nb.njit(inline="always")
def face(o, dirs, r, t_in, s_in, t_out, grid, g0, vs, vv, priors):
    """Bisect between an allocated sample (t_in, prior s_in) and an unallocated one (t_out):
    the allocated point nearest the region's face and its prior (t_in, s_in if none is nearer)."""
    a, b = t_in, t_out
    for _ in range(8):
        mid = 0.5 * (a + b)
        v_mid, s_mid = trilinear((o[0] + dirs[r, 0] * mid) / vs, (o[1] + dirs[r, 1] * mid) / vs,
                                 (o[2] + dirs[r, 2] * mid) / vs, grid, g0, vv, priors)
        if v_mid < 0:
            b = mid
        else:
            a, t_in, s_in = mid, mid, s_mid
    return t_in, s_in

@nb.njit(parallel=True, fastmath=False, cache=True)
def march(o, dirs, nears, far, step, grid, g0, vs, vv, priors, exit_tol, out):
    nx, ny, nz = grid.shape
    lo = (g0[0] * vs, g0[1] * vs, g0[2] * vs)
    hi = ((g0[0] + nx) * vs, (g0[1] + ny) * vs, (g0[2] + nz) * vs)
    for r in nb.prange(dirs.shape[0]):
        out[r] = -1.0
        t0, t1 = nears[r], far
        for a in range(3):
            d = dirs[r, a]
            if abs(d) < 1e-12:
                if o[a] < lo[a] or o[a] > hi[a]:
                    t0, t1 = 1.0, 0.0
                continue
            ta, tb = (lo[a] - o[a]) / d, (hi[a] - o[a]) / d
            if ta > tb:
                ta, tb = tb, ta
            t0, t1 = max(t0, ta), min(t1, tb)
        if t0 >= t1:
            continue
        prev = math.nan
        prev_t = 0.0
        t = t0
        while t <= t1:
            vid, s = trilinear((o[0] + dirs[r, 0] * t) / vs, (o[1] + dirs[r, 1] * t) / vs,
                               (o[2] + dirs[r, 2] * t) / vs, grid, g0, vv, priors)
            if vid < 0:
                if prev > 0.0:
                    # leaving the allocated region while the prior is still positive: find the
                    # exit point (bisection); the surface may lie in the last sliver before it
                    a_, s_in = face(o, dirs, r, prev_t, prev, t, grid, g0, vs, vv, priors)
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
                prev_t, prev = face(o, dirs, r, t, s, t - step, grid, g0, vs, vv, priors)
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

@nb.njit(parallel=True, cache=True)
def locate_prior(pts, grid, g0, vs, vv, priors, eps, sdf, vox):
    """Voxel id (-1 outside) and trilinear prior of points (metres) like ``VoxelMap.locate``: a point
    within ``eps`` voxels of a face of an unallocated voxel belongs to the allocated one across it
    (priors are shared at vertices, so the value is the same from either side)."""
    for i in nb.prange(pts.shape[0]):
        px, py, pz = pts[i, 0] / vs, pts[i, 1] / vs, pts[i, 2] / vs
        v, s = trilinear(px, py, pz, grid, g0, vv, priors)
        if v < 0:
            fx, fy, fz = math.floor(px), math.floor(py), math.floor(pz)
            ax, ay, az = round(px), round(py), round(pz)
            on_x, on_y, on_z = abs(px - ax) < eps, abs(py - ay) < eps, abs(pz - az) < eps
            for c in range(1, 8):
                bx, by, bz = c & 1, (c >> 1) & 1, (c >> 2) & 1
                if (bx and not on_x) or (by and not on_y) or (bz and not on_z):
                    continue
                # along each chosen axis, the voxel on the other side of the face from floor's
                cx = (ax - 1 if fx >= ax else ax) if bx else fx
                cy = (ay - 1 if fy >= ay else ay) if by else fy
                cz = (az - 1 if fz >= az else az) if bz else fz
                v = voxel_at(cx, cy, cz, grid, g0)
                if v >= 0:
                    s = interpolate(v, min(max(px - cx, 0.0), 1.0), min(max(py - cy, 0.0), 1.0),
                                    min(max(pz - cz, 0.0), 1.0), vv, priors)
                    break
        vox[i], sdf[i] = v, s
