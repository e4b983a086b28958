"""Fused numba kernels of mesh extraction's bookkeeping (see :mod:`h3edge.mapping.mesh`): marking
the lattice points and cubes of the allocated voxels in the bounding volume, and turning flat
lattice indices into points. Module-level so that numba's disk cache holds across processes.
"""

import numba as nb


@nb.njit(parallel=True, cache=True, nogil=True)
def mark(rel, r, shape, points, cubes):
    """For voxels at lattice offsets ``rel`` (V, 3) (= (ijk - origin) * r): set ``points`` (flat,
    C order over ``shape``) at their (r+1)^3 lattice points and ``cubes`` at the *upper* corner of
    each of their r^3 cubes (scikit-image's mask convention). Writes of True may repeat across
    voxels sharing a face; they never conflict."""
    sy, sz = shape[1], shape[2]
    for v in nb.prange(rel.shape[0]):
        x0, y0, z0 = rel[v, 0], rel[v, 1], rel[v, 2]
        for a in range(r + 1):
            for b in range(r + 1):
                base = ((x0 + a) * sy + (y0 + b)) * sz + z0
                for c in range(r + 1):
                    points[base + c] = True
                    if a > 0 and b > 0 and c > 0:
                        cubes[base + c] = True


@nb.njit(parallel=True, cache=True, nogil=True)
def to_points(flat, shape, origin_r, cell, out):
    """Points (N, 3) metres of flat lattice indices: (unravel(flat) + origin * r) * cell."""
    sy, sz = shape[1], shape[2]
    for i in nb.prange(flat.shape[0]):
        f = flat[i]
        out[i, 0] = (f // (sy * sz) + origin_r[0]) * cell
        out[i, 1] = ((f // sz) % sy + origin_r[1]) * cell
        out[i, 2] = (f % sz + origin_r[2]) * cell
