"""Mesh extraction on an analytic sphere: radius error, orientation, colours, AABB cut."""

import numpy as np

from h3edge.mapping.mesh import extract_mesh
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
