"""Fused numba CPU kernels of the fine free-space votes (see :mod:`h3edge.mapping.cell_votes`):
every cell of the given voxels projected into one depth image, its vote moved by what the pixel
it falls on measured (``vote_cells``); random cells seen free near a prior surface drawn for the
trainer (``draw_free_cells``).

Module-level so numba's on-disk cache is reused across processes.
"""

import math

import numba as nb
import numpy as np

from h3edge.mapping._trilinear_kernel import corner_weight


@nb.njit(parallel=True, cache=True, nogil=True)
def vote_cells(corners, ids, votes, depth, rot, trans, fx, fy, cx, cy, cell, n, margin, behind, stride, phase):
    """For voxel ``ids[i]`` with its minimum corner ``corners[i]`` (world, m), each of its n^3
    cells (centre at ``corner + (a + 0.5, b + 0.5, c + 0.5) * cell``, flat index ``(a * n + b) * n
    + c``): with ``s`` = the measured z-depth at the pixel the centre projects to minus the centre's
    z, ``votes[ids[i], cell] += 1`` where ``s > margin`` (seen free) and ``-= 1`` where ``-behind <=
    s <= 0`` (just behind the measured surface), saturating at +-127. ``rot``, ``trans``: world to
    camera. Pixels with no valid depth (0, NaN, inf) leave the cell as it is. Only the cells with
    ``(a + b + c) % stride == phase`` vote (``stride`` 1, ``phase`` 0: every cell)."""
    h, w = depth.shape
    for i in nb.prange(len(ids)):
        row = ids[i]
        # the first cell's centre in camera coordinates, and one cell's step along each world axis
        p0 = corners[i] + 0.5 * cell
        c0 = rot[:, 0] * p0[0] + rot[:, 1] * p0[1] + rot[:, 2] * p0[2] + trans
        step_x, step_y, step_z = stride * cell * rot[0, 2], stride * cell * rot[1, 2], stride * cell * rot[2, 2]
        for a in range(n):
            for b in range(n):
                x = c0[0] + cell * (a * rot[0, 0] + b * rot[0, 1])
                y = c0[1] + cell * (a * rot[1, 0] + b * rot[1, 1])
                z = c0[2] + cell * (a * rot[2, 0] + b * rot[2, 1])
                base = (a * n + b) * n
                first = (phase - a - b) % stride  # the first cell of this row the frame votes on
                x += first * cell * rot[0, 2]
                y += first * cell * rot[1, 2]
                z += first * cell * rot[2, 2]
                for c in range(first, n, stride):
                    if c != first:
                        x += step_x
                        y += step_y
                        z += step_z
                    if z <= 1e-3:
                        continue
                    inv = 1.0 / z
                    u = math.floor(fx * x * inv + cx)
                    v = math.floor(fy * y * inv + cy)
                    if u < 0 or u >= w or v < 0 or v >= h:
                        continue
                    d = depth[v, u]
                    if not (d > 0.0) or not math.isfinite(d):
                        continue
                    s = d - z
                    k = base + c
                    if s > margin:
                        if votes[row, k] < 127:
                            votes[row, k] += 1
                    elif s <= 0.0 and s >= -behind:
                        if votes[row, k] > -127:
                            votes[row, k] -= 1


@nb.njit(parallel=True, cache=True, nogil=True)
def in_view(corners, rot, trans, fx, fy, cx, cy, w, h, size, out):
    """``out[i]`` = some corner of the cube at ``corners[i]`` (side ``size``) lies in front of the
    camera and its bounding box of projected corners overlaps the image, or the cube straddles the
    camera plane (a cheap, conservative cull)."""
    for i in nb.prange(len(corners)):
        umin, umax, vmin, vmax = np.inf, -np.inf, np.inf, -np.inf
        front, back = False, False
        for k in range(8):
            px = corners[i, 0] + size * (k & 1)
            py = corners[i, 1] + size * ((k >> 1) & 1)
            pz = corners[i, 2] + size * ((k >> 2) & 1)
            z = rot[2, 0] * px + rot[2, 1] * py + rot[2, 2] * pz + trans[2]
            if z <= 1e-3:
                back = True
                continue
            front = True
            x = rot[0, 0] * px + rot[0, 1] * py + rot[0, 2] * pz + trans[0]
            y = rot[1, 0] * px + rot[1, 1] * py + rot[1, 2] * pz + trans[1]
            u, v = fx * x / z + cx, fy * y / z + cy
            umin, umax, vmin, vmax = min(umin, u), max(umax, u), min(vmin, v), max(vmax, v)
        out[i] = front and (back or (umax >= 0 and umin < w and vmax >= 0 and vmin < h))


@nb.njit(cache=True, nogil=True)
def draw_free_cells(votes, vertices, priors, n, min_votes, near, count, max_tries, seed):
    """Up to ``count`` flat indices ``row * n^3 + cell`` drawn uniformly (with replacement) among
    the cells of ``votes`` (rows, n^3) with at least ``min_votes`` votes whose centre's prior
    (trilinear in ``priors[vertices[row]]``, the voxel's 8 vertex priors in the order of
    :data:`h3edge.mapping.trilinear.CORNERS`) reads below ``near``: random (row, cell) pairs,
    rejected until ``count`` pass or ``max_tries`` were drawn; priors are read only for the pairs
    whose vote passes. ``seed`` seeds numba's generator (reproducible draws)."""
    np.random.seed(seed)
    rows, cells = votes.shape
    out = np.empty(count, np.int64)
    k = 0
    for _ in range(max_tries):
        if k == count:
            break
        i = np.random.randint(0, rows)
        cell = np.random.randint(0, cells)
        if votes[i, cell] < min_votes:
            continue
        a, rest = divmod(cell, n * n)
        b, c = divmod(rest, n)
        fx, fy, fz = (a + 0.5) / n, (b + 0.5) / n, (c + 0.5) / n
        prior = 0.0
        for corner in range(8):
            prior += priors[vertices[i, corner]] * corner_weight(fx, fy, fz, corner)
        if prior < near:
            out[k] = i * cells + cell
            k += 1
    return out[:k]
