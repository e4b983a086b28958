"""Mesh extraction: marching cubes of an SDF over the allocated leaf voxels, per-vertex colour.

The SDF is sampled on a regular lattice of ``resolution`` cells per voxel edge (8 = the authors'
1.25 cm at 10 cm voxels), only at lattice points of allocated voxels; scikit-image's marching
cubes runs on the bounding volume with a mask of evaluated cubes, so nothing is invented in
unobserved space. Vertex colours come from the colour field at the vertices.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
import trimesh
from skimage.measure import marching_cubes

from h3edge.mapping.trilinear import CORNERS
from h3edge.mapping.voxels import unpack

SdfFn = Callable[[np.ndarray], np.ndarray]  # points (N, 3) metres -> SDF (N,), any positive-outside unit
ColorFn = Callable[[np.ndarray], np.ndarray]  # points (N, 3) -> RGB (N, 3) in [0, 1]
SupportFn = Callable[[np.ndarray], np.ndarray]  # points (N, 3) -> evidence (N,) in [0, 1]


def _region(voxel_keys: np.ndarray, voxel_size: float, aabb: np.ndarray | None) -> np.ndarray:
    """Integer coordinates of the voxels to mesh: all of them, or those inside ``aabb``."""
    ijk = unpack(voxel_keys)
    if aabb is None:
        return ijk
    lo = np.floor(np.asarray(aabb[0]) / voxel_size).astype(np.int64)
    hi = np.floor(np.asarray(aabb[1]) / voxel_size).astype(np.int64)
    return ijk[np.all((ijk >= lo) & (ijk <= hi), axis=1)]


MESH_CHUNK = 32  # voxels per chunk edge: marching cubes runs chunk by chunk (bounded scratch)


def _chunks(ijk: np.ndarray) -> list[np.ndarray]:
    """The voxels ``ijk`` grouped by the ``MESH_CHUNK``-voxel cube they lie in (one group when they
    all fit one chunk-sized box), so scratch memory follows the voxels, not their bounding box."""
    if np.all(ijk.max(0) - ijk.min(0) < MESH_CHUNK):
        return [ijk]
    chunk = ijk // MESH_CHUNK
    _, inv = np.unique(chunk, axis=0, return_inverse=True)
    order = np.argsort(inv.reshape(-1), kind="stable")
    bounds = np.flatnonzero(np.diff(inv.reshape(-1)[order])) + 1
    return [ijk[g] for g in np.split(order, bounds)]


def working_bytes(voxel_keys: np.ndarray, voxel_size: float, resolution: int, aabb: np.ndarray | None = None) -> int:
    """Peak scratch memory of :func:`extract_mesh` (the SDF volume over the largest chunk's bounding
    box, its masks, the lattice index), before the mesh itself: what a caller checks against a budget."""
    ijk = _region(voxel_keys, voxel_size, aabb)
    if len(ijk) == 0:
        return 0
    cells = max(int(np.prod((g.max(0) - g.min(0) + 1) * resolution + 1)) for g in _chunks(ijk))
    return cells * (4 + 1 + 1) + len(ijk) * (resolution + 1) ** 3 * 8 // 2 + 64 * 1024 * 1024


def extract_mesh(voxel_keys: np.ndarray, voxel_size: float, sdf_fn: SdfFn, resolution: int = 8,
                 color_fn: ColorFn | None = None, batch: int = 262_144,
                 aabb: np.ndarray | None = None, support_fn: SupportFn | None = None,
                 min_support: float = 0.0) -> trimesh.Trimesh:
    """Zero level set of ``sdf_fn`` inside the voxels ``voxel_keys`` (optionally cut to ``aabb``).
    ``support_fn`` / ``min_support``: a cube is meshed only where all 8 of its lattice points have
    a support of at least ``min_support`` (evidence from observations, see
    :meth:`~h3edge.mapping.raymarch.PriorLookup.support`), as TSDF fusion meshes only cubes whose
    corners all carry weight. Runs chunk by chunk (``MESH_CHUNK``); vertices on chunk faces are
    merged."""
    ijk = _region(voxel_keys, voxel_size, aabb)
    if len(ijk) == 0:
        return trimesh.Trimesh()
    parts = [_chunk_surface(g, voxel_size, sdf_fn, resolution, batch, support_fn, min_support) for g in _chunks(ijk)]
    parts = [p for p in parts if p is not None]
    if not parts:
        return trimesh.Trimesh()
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    verts = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets)])
    if len(parts) > 1:
        verts, faces = _merge_chunk_faces(verts, faces, voxel_size * MESH_CHUNK, voxel_size / resolution * 1e-3)
    mesh = trimesh.Trimesh(verts, faces, process=False)  # normals point to positive SDF (tested)
    if color_fn is not None:
        paint(mesh, color_fn, batch)
    return mesh


def paint(mesh: trimesh.Trimesh, color_fn: ColorFn, batch: int = 262_144) -> None:
    """Vertex colours of ``mesh`` from ``color_fn`` at its vertices, ``batch`` at a time (in place)."""
    verts = np.asarray(mesh.vertices)
    if len(verts) == 0:
        return
    rgb = np.concatenate([color_fn(verts[s:s + batch]) for s in range(0, len(verts), batch)])
    mesh.visual.vertex_colors = np.concatenate([np.clip(rgb * 255 + 0.5, 0, 255).astype(np.uint8),
                                                np.full((len(verts), 1), 255, np.uint8)], 1)


def _merge_chunk_faces(verts: np.ndarray, faces: np.ndarray, chunk: float, tol: float
                       ) -> tuple[np.ndarray, np.ndarray]:
    """One vertex for each edge crossing found from both sides of a chunk face: vertices on a
    chunk face (a multiple of ``chunk`` metres along some axis) closer than ``tol`` are merged
    (marching cubes returns float32 positions, so the two copies differ in the last bits)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    rel = verts / chunk
    on_face = np.flatnonzero((np.abs(rel - np.round(rel)) * chunk < tol).any(1))
    pairs = cKDTree(verts[on_face]).query_pairs(tol, output_type="ndarray")
    if len(pairs) == 0:
        return verts, faces
    n = len(verts)
    a, b = on_face[pairs[:, 0]], on_face[pairs[:, 1]]
    _, label = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)), directed=False)
    _, first, inv = np.unique(label, return_index=True, return_inverse=True)
    return verts[first], inv.reshape(-1)[faces]


def _chunk_surface(ijk: np.ndarray, voxel_size: float, sdf_fn: SdfFn, r: int, batch: int,
                   support_fn: SupportFn | None, min_support: float) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices metres, faces) of the zero level set inside the voxels ``ijk``; None if empty."""
    from h3edge.mapping import _mesh_kernels as k

    origin = ijk.min(0)
    shape = tuple(int(v) for v in (ijk.max(0) - origin + 1) * r + 1)
    cell = voxel_size / r
    # lattice points of the allocated voxels (shared ones once; a mark per point beats np.unique's
    # sort ~50x) and the cubes inside them: scikit-image's mask[p] enables the cube whose *upper*
    # corner is p (checked empirically, see tests/test_mesh.py), so nothing is meshed in unobserved space
    points = np.zeros(int(np.prod(shape)), bool)
    mask = np.zeros(shape, bool)
    k.mark(np.ascontiguousarray((ijk - origin) * r), r, np.array(shape, np.int64), points, mask.reshape(-1))
    flat = np.flatnonzero(points)
    del points
    vol = np.ones(shape, np.float32)  # unevaluated = outside
    pts = np.empty((min(batch, len(flat)), 3), np.float64)
    origin_r = (origin * r).astype(np.int64)
    unsupported = np.zeros(shape, bool) if support_fn is not None and min_support > 0 else None
    for s in range(0, len(flat), batch):
        f = flat[s:s + batch]
        k.to_points(f, np.array(shape, np.int64), origin_r, cell, pts[:len(f)])
        vol.reshape(-1)[f] = sdf_fn(pts[:len(f)])
        if unsupported is not None:
            unsupported.reshape(-1)[f] = support_fn(pts[:len(f)]) < min_support
    if unsupported is not None:  # the cube with upper corner p has its 8 lattice points in p - {0, 1}^3
        bad = unsupported.copy()
        for axis in range(3):
            sl = [slice(None)] * 3
            sl[axis] = slice(1, None)
            prev = [slice(None)] * 3
            prev[axis] = slice(None, -1)
            bad[tuple(sl)] |= bad[tuple(prev)]
        mask &= ~bad
        del bad, unsupported
    evaluated = vol.reshape(-1)[flat]
    if not mask.any() or not (evaluated.min() < 0 < evaluated.max()):
        return None
    try:
        # degenerate triangles kept: whether one collapses (a lattice value at, or within float32
        # rounding of, the level) depends on the chunk's origin, so dropping them made a map's
        # block meshes differ from its whole mesh by a few faces
        verts, faces, _, _ = marching_cubes(vol, level=0.0, spacing=(cell,) * 3, mask=mask, allow_degenerate=True)
    except RuntimeError:  # "No surface found": the sign changes only outside the enabled cubes
        return None
    return verts + origin * voxel_size, faces


SURFACE_BLOCK = 32  # cells per block edge: the fused base's marching cubes runs block by block


VolumeFn = Callable[[np.ndarray, int], np.ndarray]
"""``f(origin (3,) int cell coordinates, size) ->`` the signed distance (size, size, size) float32 of the cells
``origin + (a, b, c)``, NaN where none is held"""


def cells_surface(cells: Iterable[tuple[np.ndarray, np.ndarray]], volume_fn: VolumeFn, cell: float,
                  keep_block: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64 metres, faces (F, 3) int64): the zero level set of a fused base's
    signed distance (positive outside) held at the centres ``(ijk + 1/2) * cell`` of sparse cells,
    over every cube of 8 held centres, as TSDF fusion meshes its blocks (filling a missing corner
    from its neighbours was measured and rejected, D53-9). ``cells``: batches of (cell coordinates
    (n, 3) int, signed distance (n,), NaN: none), the blocks to mesh; ``volume_fn``: the same
    distances as dense volumes (:meth:`~h3edge.mapping.color_base.FusedDistances.volume`). Runs block
    by block (``SURFACE_BLOCK`` cells a side, scratch of one block); ``keep_block(block_ijk (B, 3))
    -> (B,) bool`` picks the blocks meshed (default: all). Vertices on block faces are merged."""
    from h3edge.mapping.voxels import pack

    blocks = np.zeros(0, np.int64)
    for ijk, vals in cells:
        held = np.asarray(ijk, np.int64).reshape(-1, 3)[np.isfinite(vals)]
        blocks = np.unique(np.concatenate([blocks, pack(np.floor_divide(held, SURFACE_BLOCK))]))
    if keep_block is not None:
        blocks = blocks[np.asarray(keep_block(unpack(blocks)), bool)]
    return _march_blocks(volume_fn, cell, blocks)


def _march_blocks(volume_fn: VolumeFn, cell: float, blocks: np.ndarray,
                  keep_faces: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of :func:`cells_surface` over the blocks with keys ``blocks``; each block's
    volume (``volume_fn``) holds its cells and, as its upper halo, the cells on the lower faces of
    the 7 blocks above it. ``keep_faces(centroids (F, 3) m) -> (F,) bool``: the faces of each block
    kept (the rest dropped block by block, so that only the kept surface accumulates)."""
    empty = np.zeros((0, 3), np.float64), np.zeros((0, 3), np.int64)
    b = SURFACE_BLOCK
    verts, faces, n = [], [], 0
    for block in unpack(np.asarray(blocks, np.int64).reshape(-1)):
        vol = volume_fn(block * b, b + 1)
        ok = np.isfinite(vol)
        cube = ok[1:, 1:, 1:] & ok[:-1, 1:, 1:] & ok[1:, :-1, 1:] & ok[1:, 1:, :-1]
        cube &= ok[:-1, :-1, 1:] & ok[:-1, 1:, :-1] & ok[1:, :-1, :-1] & ok[:-1, :-1, :-1]
        if not cube.any():
            continue
        mask = np.zeros(vol.shape, bool)
        mask[1:, 1:, 1:] = cube  # scikit-image's mask[p] enables the cube whose upper corner is p
        filled = np.where(ok, vol, np.float32(1.0))
        if not (filled[ok].min() < 0 < filled[ok].max()):
            continue
        try:
            v, f, _, _ = marching_cubes(filled, level=0.0, mask=mask, allow_degenerate=True)
        except RuntimeError:  # the sign changes only outside the enabled cubes
            continue
        if keep_faces is not None:
            f = f[keep_faces((v[f].mean(1) + block * b + 0.5) * cell)]
            if len(f) == 0:
                continue
            used, f = np.unique(f, return_inverse=True)
            v, f = v[used], f.reshape(-1, 3)
        verts.append(v + block * b)
        faces.append(f + n)
        n += len(v)
    if not verts:
        return empty
    v, f = np.concatenate(verts).astype(np.float64), np.concatenate(faces).astype(np.int64)
    if len(verts) > 1:
        v, f = _merge_chunk_faces(v, f, float(b), 1e-3)
    return (v + 0.5) * cell, f


def left_out_cubes(points: np.ndarray, voxel_keys: np.ndarray, voxel_size: float, resolution: int,
                   support_fn: SupportFn, min_support: float, batch: int = 1 << 18) -> np.ndarray:
    """(N,) bool: whether the lattice cube of :func:`extract_mesh` (``resolution`` cubes per voxel
    edge) holding each point (N, 3) m lies in one of ``voxel_keys`` and was left out of its mesh
    for lack of support (a lattice point under ``min_support``). ``batch`` points at a time."""
    from h3edge.mapping.voxels import lookup, pack

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.zeros(len(pts), bool)
    if min_support <= 0:
        return out
    spacing = voxel_size / resolution
    region = np.sort(voxel_keys)
    for s in range(0, len(pts), batch):
        cubes, of_point = np.unique(pack(np.floor(pts[s:s + batch] / spacing).astype(np.int64)), return_inverse=True)
        q = unpack(cubes)
        inside = np.flatnonzero(lookup(region, pack(np.floor_divide(q, resolution))) >= 0)
        if len(inside) == 0:
            continue
        corners, of_corner = np.unique(pack((q[inside, None, :] + CORNERS).reshape(-1, 3)), return_inverse=True)
        low = support_fn(unpack(corners) * spacing) < min_support
        left = np.zeros(len(cubes), bool)
        left[inside] = low[of_corner.reshape(-1)].reshape(-1, 8).any(1)
        out[s:s + batch] = left[of_point.reshape(-1)]
    return out


def fill_scratch_bytes(n_cells: int) -> int:
    """Peak scratch memory of a mesh's fill from a base of ``n_cells`` cells, before the surface
    itself: a batch of ``FILL_BATCH`` cells read from the base and tested by :func:`left_out_cubes`
    (~300 bytes a batch cell), one block's volume and its masks, and the owner blocks' keys (64
    bytes a 32-cell run); the base's cells are read in place
    (:class:`~h3edge.mapping.color_base.FusedDistances`), and each block's faces are cut to the
    left-out cubes before the next block is marched. Measured (tracemalloc) on the real set's map
    of 969,081 cells: 20.7 MB (this says 22.0; 117 MB when every cell was copied and indexed, D53-9)."""
    return 300 * FILL_BATCH + 12 * (SURFACE_BLOCK + 1) ** 3 + 64 * (n_cells // SURFACE_BLOCK) if n_cells else 0


FILL_BATCH = 1 << 16  # cells a batch of the fill tests at a time (1 << 18: the same time, 4x the scratch)


def left_out_surface(cells: Iterable[tuple[np.ndarray, np.ndarray]], volume_fn: VolumeFn, cell: float,
                     voxel_keys: np.ndarray, voxel_size: float, resolution: int, support_fn: SupportFn,
                     min_support: float, aabb: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) metres, faces (F, 3)): the surface of a fused base (:func:`cells_surface`'s,
    of cells of side ``cell`` m) where :func:`extract_mesh` of the same voxels (optionally cut to
    ``aabb``), ``resolution`` and support left its lattice cubes out: the faces whose centroid lies
    in such a cube (:func:`left_out_cubes`). Where the map's priors carry no evidence yet, a mesh
    shows the surface the frames fused there, as a render does. ``cells``: batches of (cell
    coordinates (n, 3) int, signed distance (n,), NaN: none) that may lie there (the base's, or a
    subset near the voxels); ``volume_fn``: the base's distances as dense volumes. Scratch:
    :func:`fill_scratch_bytes`."""
    from h3edge.mapping.voxels import pack

    empty = np.zeros((0, 3), np.float64), np.zeros((0, 3), np.int64)
    region = pack(_region(voxel_keys, voxel_size, aabb))
    if len(region) == 0 or min_support <= 0:
        return empty
    # the blocks owning a base cube with a corner in a left-out lattice cube (every base cube that
    # overlaps a lattice cube has a corner inside it), a batch of cells at a time
    owners = np.zeros(0, np.int64)
    for ijk, vals in cells:
        ijk = np.asarray(ijk, np.int64).reshape(-1, 3)
        for s in range(0, len(ijk), FILL_BATCH):
            part = ijk[s:s + FILL_BATCH]
            left = left_out_cubes((part + 0.5) * cell, region, voxel_size, resolution, support_fn, min_support)
            near = part[left & np.isfinite(vals[s:s + FILL_BATCH])]
            if len(near):
                owners = np.unique(np.concatenate([owners] + [pack(np.floor_divide(near - o, SURFACE_BLOCK))
                                                              for o in CORNERS]))
    if len(owners) == 0:
        return empty
    return _march_blocks(volume_fn, cell, owners,
                         lambda c: left_out_cubes(c, region, voxel_size, resolution, support_fn, min_support))
