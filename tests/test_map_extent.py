"""The map grows with the robot: no bound fixed by the first frame (voxels, priors, hash grids,
the renderer's voxel table and mesh extraction all work in world coordinates)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from h3edge.eval.metrics import psnr
from h3edge.io.replica import ReplicaSequence
from h3edge.mapping import mesh as mesh_mod
from h3edge.mapping.engine import MapEngine
from h3edge.mapping.hashgrid import HashGrid, HashGridSpec
from h3edge.mapping.raymarch import PriorLookup
from h3edge.mapping.voxels import VoxelConfig, VoxelMap, pack, unpack
from tests.test_mapper import LEAN


def _shifted(frame, offset):
    pose = frame.pose.copy()
    pose[:3, 3] += offset
    return dataclasses.replace(frame, pose=pose)


def _held_out_quality(m, seq, offset=np.zeros(3)):
    held = seq.heldout[0]
    rgb, depth = m.render(held.intrinsics, _shifted(held, offset).pose)
    valid = (held.depth > 0) & (depth > 0)
    return valid.mean(), float(np.median(np.abs(depth[valid] - held.depth[valid]))), psnr(rgb, held.color)


@pytest.fixture(scope="module")
def small_cube_map(tiny_scene):
    """The tiny scene mapped with a reference cube of 0.5 m: nearly all of it lies outside."""
    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(dataclasses.replace(LEAN, mapper=dataclasses.replace(LEAN.mapper, extent=0.5)))
    results = [m.process(f) for f in seq]
    return seq, m, results


def test_a_scene_larger_than_the_reference_cube_maps_whole(small_cube_map):
    seq, m, results = small_cube_map
    assert all(r.mapped for r in results), [r.reason for r in results if not r.mapped]
    lo, hi = m.bound
    ijk = unpack(m.voxels.voxel_keys)
    world = (ijk + 0.5) * m.settings.voxels.voxel_size
    outside = ~np.all((world >= lo) & (world <= hi), axis=1)
    assert outside.mean() > 0.5  # most of the map lies outside the cube, and it is mapped
    coverage, depth_err, p = _held_out_quality(m, seq)
    assert coverage > 0.9 and depth_err < 0.02 and p > 15.0


def test_a_far_first_frame_does_not_fix_the_map(tiny_scene):
    """A valid first frame 100 m from the rest maps where it is; the later frames map as usual."""
    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(LEAN)
    far = _shifted(seq[0], np.array([100.0, -60.0, 20.0]))
    assert m.process(dataclasses.replace(far, timestamp=seq[0].timestamp - 1.0)).mapped
    results = [m.process(f) for f in seq]
    assert all(r.mapped for r in results), [r.reason for r in results if not r.mapped]
    coverage, depth_err, p = _held_out_quality(m, seq)
    assert coverage > 0.9 and depth_err < 0.02 and p > 15.0
    # the voxel table is sized by the voxel count, not by the 100 m bounding box
    table = m.voxels.table()
    assert len(table.hkeys) <= 4 * len(m.voxels) + 16
    # and the mesh is extracted chunk by chunk around both places
    mesh = m.mesh()
    assert len(mesh.faces) > 0 and mesh_mod.working_bytes(m.voxels.voxel_keys, m.settings.voxels.voxel_size,
                                                          m.cfg.mesh_resolution) < 512 * 1024 * 1024


def test_an_absurd_first_pose_is_refused_and_places_nothing(tiny_scene):
    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(LEAN)
    r = m.process(_shifted(seq[0], np.array([1e9, 0.0, 0.0])))
    assert not r.mapped and m.dropped == {"bad_pose": 1} and "max_position" in r.reason
    assert m.field is None and len(m.voxels) == 0
    assert all(m.process(f).mapped for f in seq)
    assert np.allclose(m.bound.mean(0), seq[0].pose[:3, 3])


def test_a_translated_world_maps_the_same(tiny_scene):
    """World coordinates 300 m from the origin: the same scene, the same quality."""
    seq = ReplicaSequence(tiny_scene)
    offset = np.array([300.0, -200.0, 50.0])
    m = MapEngine(LEAN)
    assert all(m.process(_shifted(f, offset)).mapped for f in seq)
    coverage, depth_err, p = _held_out_quality(m, seq, offset)
    assert coverage > 0.9 and depth_err < 0.02 and p > 15.0


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_hash_grid_is_not_clamped_to_its_cube(backend):
    spec = HashGridSpec(levels=4, features=2, log2_table=12, base_resolution=4, per_level_scale=2.0)
    g = HashGrid(spec, np.array([[0.0] * 3, [1.0] * 3]), backend=backend, init_scale=1.0, seed=3)
    far = torch.tensor([[5.3, 5.3, 5.3], [7.1, -4.2, 9.9], [1.0, 1.0, 1.0]])
    f = g(far)
    # clamping would give all three the features of the cube's corner (1, 1, 1)
    assert not torch.allclose(f[0], f[2]) and not torch.allclose(f[1], f[2])
    # and gradients reach the rows the far points read
    f.sum().backward()
    rows, grads = g.take_sparse_grad()
    assert len(rows) > 0 and torch.isfinite(grads).all()


def test_hash_backends_agree_outside_the_cube():
    spec = HashGridSpec(levels=3, features=2, log2_table=12, base_resolution=4, per_level_scale=2.0)
    bound = np.array([[0.0] * 3, [1.0] * 3])
    a = HashGrid(spec, bound, backend="torch", init_scale=1.0, seed=5)
    b = HashGrid(spec, bound, backend="numba", init_scale=1.0, seed=5)
    x = torch.from_numpy(np.random.default_rng(0).uniform(-20, 20, (500, 3)).astype(np.float32))
    assert torch.allclose(a(x), b(x), atol=1e-5)


def test_voxel_table_finds_voxels_far_apart():
    vm = VoxelMap(VoxelConfig(voxel_size=0.1), "cpu")
    ijk = np.array([[0, 0, 0], [1, 0, 0], [5000, -3000, 200], [-9000, 7, 8]], np.int64)
    vm._insert(np.sort(pack(ijk)))
    look = PriorLookup(vm)
    pts = (ijk + 0.5) * 0.1
    _, vox = look(np.concatenate([pts, pts + 0.1 * np.array([[0, 3, 0]])]))
    assert list(vox[:4]) == list(vm.locate(pts)[0]) and (vox[:4] >= 0).all()
    assert (vox[4:] == -1).all()
    assert len(look.table.hkeys) <= 16 and set(vm.voxel_keys) == set(pack(ijk))


def test_chunked_mesh_equals_one_volume(small_cube_map, monkeypatch):
    _, m, _ = small_cube_map
    whole = m.mesh()
    monkeypatch.setattr(mesh_mod, "MESH_CHUNK", 3)
    assert len(mesh_mod._chunks(unpack(m.voxels.voxel_keys))) > 4
    chunked = m.mesh()
    assert len(chunked.faces) == len(whole.faces)
    # shared vertices merged (a few distinct ones closer than 1e-3 cell may merge too)
    assert abs(len(chunked.vertices) - len(whole.vertices)) <= 1e-3 * len(whole.vertices)
    assert abs(chunked.area - whole.area) < 1e-6 * whole.area
