"""Leaf voxels and SDF priors on a fronto-parallel wall, where projective SDF = true SDF."""

import numpy as np
import pytest
import torch

from h3edge.geometry.camera import Intrinsics, backproject, look_at
from h3edge.mapping.trilinear import CORNERS
from h3edge.mapping.voxels import VoxelConfig, VoxelMap, lookup, pack, points_by_voxel, unpack

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


def _locate_reference(vm: VoxelMap, pts: np.ndarray, eps: float = 1e-5) -> np.ndarray:
    """``locate``'s rule point by point in plain Python: the floor voxel, else the first allocated
    voxel across the faces the point lies on, the lower side first along each such axis."""
    ids = {int(k): i for i, k in enumerate(vm.voxel_keys)}
    out = []
    for p in pts / vm.cfg.voxel_size:
        g = np.floor(p).astype(np.int64)
        a = np.round(p).astype(np.int64)
        on = np.abs(p - a) < eps
        found = ids.get(int(pack(g[None])[0]), -1)
        for c in range(8):
            if found >= 0:
                break
            bits = CORNERS[c].astype(bool)
            if (bits & ~on).any():
                continue
            cand = np.where(on, np.where(bits, a, a - 1), g)
            found = ids.get(int(pack(cand[None])[0]), -1)
        out.append(found)
    return np.array(out)


def test_locate_follows_its_rule_on_faces_edges_and_corners():
    vm = VoxelMap(VoxelConfig(min_points=3, neighbour_margin=0.4))
    vm.allocate(wall_depth(), INTR, POSE)
    rng = np.random.default_rng(1)
    ijk = unpack(vm.voxel_keys)
    vs = vm.cfg.voxel_size
    # half-voxel lattice around allocated voxels: faces, edges and corners, some of unallocated ones
    lattice = (ijk[rng.integers(0, len(ijk), 400)] * 2 + rng.integers(-1, 4, (400, 3))) * (vs / 2)
    inner = (ijk[rng.integers(0, len(ijk), 200)] + rng.random((200, 3))) * vs
    pts = np.concatenate([lattice, inner, rng.uniform(-3, 3, (200, 3))])
    vox, frac = vm.locate(pts)
    assert np.array_equal(vox, _locate_reference(vm, pts))
    # the torch lookup the torch backend trains with (on the map's device): the same voxels and positions
    for compact in (True, False):  # the CPU's compaction and the GPU's fixed shapes
        t_vox, t_frac = vm.locate_tensor(torch.from_numpy(pts), compact=compact)
        assert np.array_equal(t_vox.numpy(), vox) and np.allclose(t_frac.numpy(), frac, atol=1e-6)
    bad = torch.tensor([[np.nan, 0.0, 0.0], [np.inf, 1.0, 1.0], [1e9, 0.0, 0.0]])
    assert (vm.locate_tensor(bad)[0] == -1).all()  # NaN, infinite and unpackable points are outside
    assert (VoxelMap(vm.cfg).locate_tensor(torch.from_numpy(pts))[0] == -1).all()  # an empty map
    assert (vox[:400] >= 0).mean() > 0.5 and (vox[400:600] >= 0).all()
    ok = vox >= 0
    assert np.allclose(frac[ok], pts[ok] / vs - ijk[vox[ok]], atol=1e-9)  # relative to the voxel found
    assert (frac >= 0).all() and (frac <= 1).all()


def test_allocation_lists_the_voxels_every_nth_valid_pixel_observes():
    """The keyframe policy's observed voxels come from allocation's pass over the points: the same
    as locating every 4th valid pixel's point, with holes, a sloped surface and refused voxels."""
    rng = np.random.default_rng(5)
    vm = VoxelMap(VoxelConfig(min_points=3, max_voxels=40))
    slope = (WALL_Y + np.linspace(-0.4, 0.6, INTR.width, dtype=np.float32))[None, :].repeat(INTR.height, 0)
    for depth in (wall_depth(), slope):
        depth = depth.copy()
        depth[rng.random(depth.shape) < 0.3] = 0.0  # holes: the stride counts valid pixels only
        pose = look_at(np.array([0.1, 0.0, 0.05]), np.array([0.3, 1.0, 0.1]))
        new, observed = vm.allocate_observing(depth, INTR, pose, every=4)
        pts = backproject(depth, INTR, pose).reshape(-1, 3)
        vox, _ = vm.locate(pts[np.flatnonzero(depth.reshape(-1) > 0)[::4]])
        assert np.array_equal(observed, np.unique(vox[vox >= 0])) and len(observed)
    assert vm.refused > 0  # the cap left some of the frame's voxels out: they are not observed


def test_points_by_voxel_counts_and_sums_like_a_sort():
    rng = np.random.default_rng(2)
    pts = np.concatenate([rng.normal(0, 3, (50_000, 3)), rng.normal(1, 0.05, (20_000, 3))])  # > 2^13 voxels
    pts[rng.random(len(pts)) < 0.1, rng.integers(0, 3)] = np.nan  # invalid rows are skipped
    keys, counts, sums, picked = points_by_voxel(pts, 0.1, every=3)
    ok = np.isfinite(pts).all(1)
    ref_keys, inv, ref_counts = np.unique(pack(np.floor(pts[ok] / 0.1)), return_inverse=True, return_counts=True)
    assert np.array_equal(keys, ref_keys) and np.array_equal(counts, ref_counts)
    ref_sums = np.stack([np.bincount(inv, weights=pts[ok][:, k]) for k in range(3)], -1)
    assert np.allclose(sums, ref_sums, rtol=1e-12, atol=1e-9)
    # every third valid row, counted by voxel
    assert np.array_equal(picked, np.bincount(inv[::3], minlength=len(keys)))
    assert np.array_equal(points_by_voxel(pts, 0.1)[3], counts)  # every row
    with pytest.raises(ValueError):
        points_by_voxel(pts, 0.1, every=0)
    with pytest.raises(ValueError):
        points_by_voxel(np.array([[1e6, 0.0, 0.0]]), 0.1)
    assert len(points_by_voxel(np.full((4, 3), np.nan), 0.1)[0]) == 0


BACK_WALL_Y = 2.095  # 5 mm in front of a voxel face: the face neighbour behind the wall is allocated


def back_wall_map(observed_behind: float) -> VoxelMap:
    """A wall seen from the front: its voxel layer [2.0, 2.1] and the neighbour layer behind it."""
    vm = VoxelMap(VoxelConfig(min_points=3, observed_behind=observed_behind))
    vm.allocate(np.full((INTR.height, INTR.width), BACK_WALL_Y, np.float32), INTR, POSE)
    assert set(np.unique(unpack(vm.voxel_keys)[:, 1])) == {20, 21}
    return vm


def test_vertices_record_how_far_behind_the_surface_a_frame_saw_them():
    vm = back_wall_map(0.05)
    xyz = unpack(vm.vertex_keys) * vm.cfg.voxel_size
    y = xyz[:, 1]
    seen = np.isfinite(vm.seen_behind)
    assert seen.mean() > 0.5
    assert np.allclose(vm.seen_behind[seen], y[seen] - BACK_WALL_Y, atol=1e-5)  # camera z = world y
    # a view from behind the wall sees the far layer's vertices in front of its surface
    back = look_at(np.array([0.0, 4.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    before = vm.seen_behind.copy()
    vm.allocate(np.full((INTR.height, INTR.width), 4.0 - BACK_WALL_Y, np.float32), INTR, back)
    far = seen & (y > 2.15) & (np.abs(xyz[:, [0, 2]]).max(1) < 1.0)  # in both views
    assert far.any() and (vm.seen_behind[far] < 0).all() and (vm.seen_behind <= before).all()


def test_support_ends_where_every_view_saw_only_through_a_surface():
    """A back shell (the field crossing zero 9 cm behind the only surface any view saw) is no mesh:
    support ends ``observed_behind`` behind the surface; without the limit the shell is meshed."""
    from h3edge.mapping.mesh import extract_mesh
    from h3edge.mapping.raymarch import PriorLookup

    probes = np.array([[0.0, BACK_WALL_Y + d, 0.0] for d in (0.0, 0.03, 0.07, 0.09)])
    meshes = {}
    for limit in (0.05, np.inf):
        vm = back_wall_map(limit)
        y = unpack(vm.vertex_keys)[:, 1]
        with torch.no_grad():  # inside behind the wall, drifting up at the far layer's back: a shell at ~2.167
            vm.priors[torch.from_numpy(y == 21)] = -1.0
            vm.priors[torch.from_numpy(y == 22)] = 0.5
        vm.prior_set[y == 22] = True
        lookup = PriorLookup(vm)
        support = lookup.support(probes)
        if limit == 0.05:
            assert (support[:2] > 0.5).all() and (support[2:] == 0).all(), support
        else:
            assert (support > 0.25).all(), support
        mesh = extract_mesh(vm.voxel_keys, vm.cfg.voxel_size, lambda p, lk=lookup: lk(p)[0], resolution=5,
                            support_fn=lookup.support, min_support=0.25)
        centre = np.abs(mesh.vertices[:, [0, 2]]).max(1) < 1.0  # away from the map's edges
        meshes[limit] = mesh.vertices[centre, 1]
    assert len(meshes[0.05]) and meshes[0.05].max() < BACK_WALL_Y + 0.05  # the wall, nothing behind it
    assert (meshes[np.inf] > BACK_WALL_Y + 0.05).mean() > 0.3  # without the limit: the shell too


def test_seen_behind_survives_state_dict_and_old_states_read_as_seen():
    vm = back_wall_map(0.05)
    meta, arrays = vm.state_dict()
    back = VoxelMap(vm.cfg)
    back.load_state_dict(meta, arrays)
    assert np.array_equal(back.seen_behind, vm.seen_behind)
    assert np.array_equal(vm.frozen_copy().seen_behind, vm.seen_behind)
    old = VoxelMap(vm.cfg)
    old.load_state_dict(meta, {k: v for k, v in arrays.items() if k != "seen_behind"})
    assert (old.seen_behind == -np.inf).all() and len(old.seen_behind) == len(vm.prior_set)
    # its support is the one it was saved with: the set priors' share, wherever a voxel is
    from h3edge.mapping.raymarch import PriorLookup

    pts = (unpack(old.voxel_keys) + 0.5) * old.cfg.voxel_size
    share, _ = PriorLookup(old)(pts, old.prior_set.astype(np.float64))
    assert share.max() > 0 and np.allclose(PriorLookup(old).support(pts), share)


def test_trained_rays_count_per_voxel_grow_with_the_map_and_survive_state_dict():
    vm = back_wall_map(0.05)
    n = len(vm)
    assert n > 2 and vm.trained.shape == (n,) and (vm.trained == 0).all()
    vm.count_trained(np.array([0, 0, 1, -1, n + 5]))  # repeats count; none (-1) and unknown ids do not
    assert vm.trained[0] == 2 and vm.trained[1] == 1 and vm.trained[2:].sum() == 0
    meta, arrays = vm.state_dict()
    back = VoxelMap(vm.cfg)
    back.load_state_dict(meta, arrays)
    assert np.array_equal(back.trained, vm.trained)
    frozen = vm.frozen_copy()
    frozen.trained[:] = 7
    assert vm.trained[2] == 0  # a query copy's count is its own
    old = VoxelMap(vm.cfg)
    old.load_state_dict(meta, {k: v for k, v in arrays.items() if k != "trained"})
    assert len(old.trained) == n and (old.trained == np.inf).all()  # from before the count: trained
    with pytest.raises(ValueError, match="trained-ray counts"):  # a state whose counts do not fit its voxels
        VoxelMap(vm.cfg).load_state_dict(meta, {**arrays, "trained": arrays["trained"][:-1]})
    vm._insert(np.array([pack(np.array([[900, 900, 900]]))[0]]))
    assert len(vm.trained) == n + 1 and vm.trained[-1] == 0
    # the torch backend counts on its device (fixed shapes) and the host array takes them when read
    vm.count_trained(torch.tensor([0, 1, 1, -1, n + 9]))
    vm._insert(np.array([pack(np.array([[901, 900, 900]]))[0]]))  # a voxel added between two steps
    vm.count_trained(torch.tensor([n + 1, 0]))
    assert vm._trained_pending is not None and vm.trained_nbytes == 4 * (n + 2)
    assert vm.trained[:3].tolist() == [4, 3, 0] and vm.trained[n + 1] == 1 and vm._trained_pending is None
