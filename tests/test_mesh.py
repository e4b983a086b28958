"""Mesh extraction on an analytic sphere: radius error, orientation, colours, AABB cut; the fused
base's sparse-cell surface and where it fills a mesh's unsupported cubes."""

import numpy as np
import trimesh

from h3edge.mapping.color_base import ColorBase, ColorBaseConfig
from h3edge.mapping.mesh import SURFACE_BLOCK, cells_surface, extract_mesh, left_out_surface
from h3edge.mapping.voxels import pack
from tests.helpers import voxels_near_surface

C = np.array([0.03, -0.02, 0.05])
R = 0.37
VOX = 0.1


def sphere(p):
    return np.linalg.norm(p - C, axis=1) - R


def sphere_voxels():
    return voxels_near_surface(sphere, np.stack([C - 0.6, C + 0.6]), VOX, margin=VOX)


def test_sphere_radius_error_under_quarter_voxel():
    mesh = extract_mesh(sphere_voxels(), VOX, sphere, resolution=8)
    r = np.linalg.norm(mesh.vertices - C, axis=1)
    assert np.abs(r - R).max() < VOX / 4
    assert np.abs(r - R).mean() < 0.002
    assert mesh.is_watertight
    # normals point outwards (towards positive SDF)
    n = mesh.face_normals
    assert (np.einsum("ij,ij->i", n, mesh.triangles_center - C) > 0).mean() > 0.99
    assert abs(mesh.area - 4 * np.pi * R ** 2) / (4 * np.pi * R ** 2) < 0.02


def test_colour_and_aabb():
    keys = sphere_voxels()
    mesh = extract_mesh(keys, VOX, sphere, resolution=4,
                        color_fn=lambda p: np.where(p[:, :1] > C[0], [[1.0, 0, 0]], [[0, 0, 1.0]]))
    red = mesh.visual.vertex_colors[:, 0] == 255
    assert np.array_equal(red, mesh.vertices[:, 0] > C[0])
    half = extract_mesh(keys, VOX, sphere, resolution=4, aabb=np.array([[-1, -1, -1], [1, 1, C[2] - 0.01]]))
    assert 0 < len(half.faces) < len(mesh.faces)
    assert half.vertices[:, 2].max() < C[2] + VOX


def test_empty_inputs():
    assert len(extract_mesh(np.zeros(0, np.int64), VOX, sphere).faces) == 0
    far = voxels_near_surface(lambda p: np.ones(len(p)), np.array([[0, 0, 0], [0.3, 0.3, 0.3]]), VOX, 0.05)
    assert len(far) == 0


def sphere_cells(cell: float, band: float):
    """Cells (ijk, SDF at their centres) within ``band`` m of the sphere, as a fused base holds."""
    lo, hi = np.floor((C - R - 0.05) / cell).astype(int), np.ceil((C + R + 0.05) / cell).astype(int)
    ijk = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), -1).reshape(-1, 3)
    d = sphere((ijk + 0.5) * cell)
    near = np.abs(d) < band
    return ijk[near], d[near].astype(np.float32)


def fused(ijk: np.ndarray, d: np.ndarray, cell: float):
    """The distances ``d`` at cells ``ijk`` as a fused base holds them (NaN: held, no distance)."""
    base = ColorBase(ColorBaseConfig(cell=cell))
    base.load_state_dict({"keys": pack(ijk), "rgb": np.zeros((len(ijk), 3), np.float32),
                          "weight": np.ones(len(ijk), np.float32), "distance": d})
    return base


def surface_of(ijk, d, cell, keep_block=None):
    source = fused(ijk, d, cell).distances()
    return cells_surface(source.batches(1 << 16), source.volume, cell, keep_block)


def test_cells_surface_is_the_closed_sphere_across_blocks():
    cell = 0.01
    ijk, d = sphere_cells(cell, 3 * cell)
    assert np.ptp(np.floor_divide(ijk, SURFACE_BLOCK), axis=0).min() >= 2  # spans several blocks a side
    verts, faces = surface_of(ijk, d, cell)
    mesh = trimesh.Trimesh(verts, faces, process=True)  # merges nothing the block seams left apart
    assert len(mesh.vertices) == len(verts)
    assert mesh.is_watertight
    assert np.abs(np.linalg.norm(verts - C, axis=1) - R).max() < 0.1 * cell
    cut = d.copy()
    cut[(ijk[:, 0] + 0.5) * cell > C[0]] = np.nan  # a cube with a corner not held is not meshed
    v, f = surface_of(ijk, cut, cell)
    assert 0 < len(f) < len(faces) and v[:, 0].max() <= C[0]
    assert len(surface_of(ijk, d, cell, lambda blocks: np.zeros(len(blocks), bool))[1]) == 0


def test_left_out_surface_fills_only_the_cubes_the_mesh_leaves_out():
    cell, res = 0.01, 5
    ijk, d = sphere_cells(cell, 3 * cell)
    keys = sphere_voxels()

    def support(p):  # evidence only on the +x side
        return (p[:, 0] > C[0]).astype(float)

    field = extract_mesh(keys, VOX, sphere, res, support_fn=support, min_support=0.25)
    base = fused(ijk, d, cell)
    source = base.distances()

    def left_out_surface_of(cells, support_fn, min_support):
        return left_out_surface(cells, source.volume, cell, keys, VOX, res, support_fn, min_support)

    verts, faces = left_out_surface_of(source.batches(1 << 18), support, 0.25)
    fill = trimesh.Trimesh(verts, faces, process=False)
    assert field.vertices[:, 0].min() >= C[0] - 1e-9 and len(field.faces)
    # the fill lies on the sphere, on the side without evidence, up to the lattice cube at the cut
    assert np.abs(np.linalg.norm(verts - C, axis=1) - R).max() < 0.1 * cell
    assert fill.triangles_center[:, 0].max() < C[0] + VOX / res
    both = field.area + fill.area
    assert abs(both - 4 * np.pi * R ** 2) / (4 * np.pi * R ** 2) < 0.03
    assert len(left_out_surface_of([(ijk, d)], support, 0.0)[1]) == 0  # nothing left out
    everywhere = left_out_surface_of([(ijk, d)], lambda p: np.ones(len(p)), 0.25)
    assert len(everywhere[1]) == 0
    # the same surface from the base's cells in batches of any size, or from the cells as arrays
    for cells in (source.batches(1000), [(ijk, d)]):
        v2, f2 = left_out_surface_of(cells, support, 0.25)
        assert np.array_equal(v2, verts) and np.array_equal(f2, faces)
    # a cell the base holds no distance at (weight 0) is not meshed
    gone = (ijk[:, 0] + 0.5) * cell < C[0] - R / 2
    base.cells[:len(ijk)][gone, 3] = 0
    assert 0 < len(left_out_surface_of(base.distances().batches(1 << 18), support, 0.25)[1]) < len(faces)
