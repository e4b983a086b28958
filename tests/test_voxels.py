"""Leaf voxels and SDF priors on a fronto-parallel wall, where projective SDF = true SDF."""

import numpy as np
import pytest
import torch

from h3edge.geometry.camera import Intrinsics, look_at
from h3edge.mapping.trilinear import CORNERS
from h3edge.mapping.voxels import VoxelConfig, VoxelMap, lookup, pack, unpack

INTR = Intrinsics(64, 48, 40.0, 40.0, 32.0, 24.0)
WALL_Y = 2.03  # wall plane y = 2.03, camera at the origin looking along +y
POSE = look_at(np.array([0.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))


def wall_depth():
    return np.full((INTR.height, INTR.width), WALL_Y, np.float32)  # camera z = world y here


def test_pack_roundtrip_and_lookup():
    ijk = np.array([[0, 0, 0], [-5, 7, 3], [1000, -1000, 12]])
    keys = pack(ijk)
    assert np.array_equal(unpack(keys), ijk)
    s = np.sort(keys)
    assert np.array_equal(lookup(s, keys), np.searchsorted(s, keys))
    assert lookup(s, pack(np.array([[9, 9, 9]])))[0] == -1
    with pytest.raises(ValueError):
        pack(np.array([[1 << 21, 0, 0]]))


def test_allocation_covers_the_wall_only():
    vm = VoxelMap(VoxelConfig(min_points=3))
    new = vm.allocate(wall_depth(), INTR, POSE)
    assert len(new) == len(vm) > 0
    ijk = unpack(vm.voxel_keys)
    assert set(np.unique(ijk[:, 1])) == {20}  # y in [2.0, 2.1): the wall's voxel layer, 3 cm into it
    assert len(vm.allocate(wall_depth(), INTR, POSE)) == 0  # same frame again: nothing new
    nan = wall_depth()
    nan[:] = np.nan
    assert len(vm.allocate(nan, INTR, POSE)) == 0


def test_neighbour_allocated_when_surface_near_a_face():
    vm = VoxelMap(VoxelConfig(min_points=3, neighbour_margin=0.4))  # mean point 0.3 into the voxel
    vm.allocate(wall_depth(), INTR, POSE)
    assert set(np.unique(unpack(vm.voxel_keys)[:, 1])) == {19, 20}


def test_priors_are_the_sdf_and_interpolate_exactly():
    cfg = VoxelConfig(min_points=3, prior_clamp=0.0)  # the paper's rule: untruncated projective SDF
    vm = VoxelMap(cfg)
    vm.allocate(wall_depth(), INTR, POSE)
    assert vm.prior_set.mean() > 0.5
    ijk = unpack(vm.vertex_keys[vm.prior_set])
    y = ijk[:, 1] * cfg.voxel_size
    assert np.allclose(vm.priors.detach().numpy()[vm.prior_set], (WALL_Y - y) / cfg.truncation, atol=1e-4)
    # points inside fully initialised voxels near the image centre
    pts = torch.tensor([[0.01, 2.03, 0.02], [0.05, 2.05, -0.03], [-0.02, 2.001, 0.0]], dtype=torch.float32)
    sdf, inside = vm.coarse_sdf(pts)
    assert inside.all()
    assert torch.allclose(sdf, (WALL_Y - pts[:, 1]) / cfg.truncation, atol=1e-4)
    sdf.sum().backward()
    assert vm.priors.grad is not None and (vm.priors.grad != 0).sum() <= 8 * 3
    _, inside = vm.coarse_sdf(torch.tensor([[0.0, 1.0, 0.0]]))
    assert not inside.any()


def test_priors_truncated_like_a_tsdf():
    """prior_clamp = 1: priors are the projective SDF truncated to [-1, 1] truncation units, and a
    vertex seen far in front of the surface reads +1 (free), not 0 (surface)."""
    cfg = VoxelConfig(min_points=3, prior_clamp=1.0)
    vm = VoxelMap(cfg)
    vm.allocate(wall_depth(), INTR, POSE)
    ijk = unpack(vm.vertex_keys[vm.prior_set])
    y = ijk[:, 1] * cfg.voxel_size
    expect = np.clip((WALL_Y - y) / cfg.truncation, -1.0, 1.0)
    assert np.allclose(vm.priors.detach().numpy()[vm.prior_set], expect, atol=1e-4)
    assert (vm.priors.detach().numpy() >= -1 - 1e-6).all() and (vm.priors.detach().numpy() <= 1 + 1e-6).all()
    paper = VoxelMap(VoxelConfig(min_points=3, prior_clamp=0.0))
    paper.allocate(wall_depth(), INTR, POSE)
    assert vm.prior_set.sum() >= paper.prior_set.sum()


def test_voxel_cap_refuses_and_counts():
    vm = VoxelMap(VoxelConfig(min_points=3, max_voxels=5))
    vm.allocate(wall_depth(), INTR, POSE)
    assert len(vm) == 5 and vm.refused > 0
    assert len(vm.voxel_vertices) == 5


def test_growth_keeps_existing_priors():
    cfg = VoxelConfig(min_points=3)
    vm = VoxelMap(cfg)
    vm.allocate(wall_depth(), INTR, POSE)
    was_set = vm.prior_set.copy()
    before = dict(zip(vm.vertex_keys[was_set].tolist(), vm.priors.detach().numpy()[was_set].tolist()))
    moved = look_at(np.array([1.5, 0.0, 0.0]), np.array([1.5, 1.0, 0.0]))
    assert len(vm.allocate(wall_depth(), INTR, moved)) > 0
    after = dict(zip(vm.vertex_keys.tolist(), vm.priors.detach().numpy().tolist()))
    assert all(after[k] == v for k, v in before.items())  # set once, never overwritten or lost
    assert vm.prior_set.sum() > was_set.sum()


def test_ids_are_stable_as_the_map_grows():
    vm = VoxelMap(VoxelConfig(min_points=3))
    vm.allocate(wall_depth(), INTR, POSE)
    keys, verts = vm.voxel_keys.copy(), vm.voxel_vertices.copy()
    vm.allocate(wall_depth(), INTR, look_at(np.array([1.5, 0.0, 0.0]), np.array([1.5, 1.0, 0.0])))
    assert np.array_equal(vm.voxel_keys[:len(keys)], keys)  # append-only
    assert np.array_equal(vm.voxel_vertices[:len(verts)], verts)
    # every voxel's vertex ids point at its own corners
    corners = unpack(vm.vertex_keys[vm.voxel_vertices])
    assert np.array_equal(corners - unpack(vm.voxel_keys)[:, None, :], np.broadcast_to(CORNERS, corners.shape))
    assert len(np.unique(vm.vertex_keys)) == len(vm.vertex_keys) == len(vm.priors)


def test_dense_lookup_matches_locate_on_faces_and_inside():
    """The renderer's and mesher's fused lookup gives the training lookup's prior and inside mask,
    including lattice points on the faces of the allocated region (which ``floor`` alone misses)."""
    from h3edge.mapping.raymarch import PriorLookup

    vm = VoxelMap(VoxelConfig(min_points=3, neighbour_margin=0.4))
    vm.allocate(wall_depth(), INTR, POSE)
    rng = np.random.default_rng(0)
    ijk = unpack(vm.voxel_keys)
    vs = vm.cfg.voxel_size
    inner = (ijk[rng.integers(0, len(ijk), 500)] + rng.random((500, 3))) * vs
    lattice = (ijk[rng.integers(0, len(ijk), 500)] * 5 + rng.integers(0, 6, (500, 3))) * (
        vs / 5
    )  # 2 cm lattice, faces incl.
    outside = rng.uniform(-3, 3, (500, 3))
    pts = np.concatenate([inner, lattice, outside])
    sdf, vox = PriorLookup(vm)(pts)
    ref_vox, _ = vm.locate(pts)
    ref_sdf, ref_inside = vm.coarse_sdf(torch.from_numpy(pts.astype(np.float32)))
    assert np.array_equal(vox >= 0, ref_inside.numpy()) and np.array_equal(vox >= 0, ref_vox >= 0)
    assert (vox[500:1000] >= 0).all()  # every lattice point of an allocated voxel is found
    assert np.abs(sdf - ref_sdf.detach().double().numpy()).max() < 1e-4
    # a point on a face belongs to a voxel that contains it
    g = ijk[vox[vox >= 0]]
    rel = pts[vox >= 0] / vs - g
    assert (rel > -1e-6).all() and (rel < 1 + 1e-6).all()
