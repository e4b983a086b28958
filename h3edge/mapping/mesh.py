"""Mesh extraction: marching cubes of an SDF over the allocated leaf voxels, per-vertex colour.

The SDF is sampled on a regular lattice of ``resolution`` cells per voxel edge (8 = the authors'
1.25 cm at 10 cm voxels), only at lattice points of allocated voxels; scikit-image's marching
cubes runs on the bounding volume with a mask of evaluated cubes, so nothing is invented in
unobserved space. Vertex colours come from the colour field at the vertices.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh
from skimage.measure import marching_cubes

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
    if color_fn is not None and len(verts):
        rgb = np.concatenate([color_fn(verts[s:s + batch]) for s in range(0, len(verts), batch)])
        rgba = np.concatenate([np.clip(rgb * 255 + 0.5, 0, 255).astype(np.uint8),
                               np.full((len(verts), 1), 255, np.uint8)], 1)
        mesh.visual.vertex_colors = rgba
    return mesh


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
