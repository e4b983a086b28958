"""Fine free-space votes (:mod:`h3edge.mapping.cell_votes`): what one frame votes, majorities across
frames, the lookup the trainer uses, the free-cell sampler and the state."""

import numpy as np
import pytest
import torch

from h3edge.geometry.camera import Intrinsics, look_at
from h3edge.mapping.cell_votes import CellVotes, VoteConfig
from h3edge.mapping.voxels import VoxelConfig, VoxelMap, unpack

INTR = Intrinsics(64, 48, 40.0, 40.0, 32.0, 24.0)
FRONT = look_at(np.zeros(3), np.array([0.0, 1.0, 0.0]))  # looking along +y at a wall 2 m away
SIDE = look_at(np.array([2.0, 2.0, 0.0]), np.array([0.0, 2.0, 0.0]))  # looking along -x, 4 m deep
# cell centres on the axis (x, z = 5 mm: off the voxel faces): 7.5 cm in front of the wall, 1.5 cm
# in front (within the margin), 1.5 cm behind, 8.5 cm behind (past the band)
PROBES = np.array([[0.005, 1.925, 0.005], [0.005, 1.985, 0.005], [0.005, 2.015, 0.005], [0.005, 2.085, 0.005]])


def wall_map() -> VoxelMap:
    vm = VoxelMap(VoxelConfig(voxel_size=0.1, min_points=1, prior_clamp=1.0))  # votes ship with clamped priors
    vm.allocate(np.full((INTR.height, INTR.width), 2.0, np.float32), INTR, FRONT)
    return vm


def votes_at(cv: CellVotes, vm: VoxelMap, pts: np.ndarray) -> np.ndarray:
    vox, frac = vm.locate(pts)
    assert (vox >= 0).all()
    c = np.floor(frac * cv.n).astype(int)
    return cv.votes[vox, (c[:, 0] * cv.n + c[:, 1]) * cv.n + c[:, 2]]


def test_a_frame_votes_free_in_front_and_inside_just_behind_its_depth():
    vm = wall_map()
    cv = CellVotes(VoteConfig(cell=0.01, margin=0.03), voxel_size=0.1, behind=0.05)
    wall = np.full((INTR.height, INTR.width), 2.0, np.float32)
    assert cv.mark(vm, wall, INTR, FRONT) == len(vm)  # every voxel is in view
    assert votes_at(cv, vm, PROBES).tolist() == [1, 0, -1, 0]
    cv.mark(vm, wall, INTR, FRONT)
    assert votes_at(cv, vm, PROBES).tolist() == [2, 0, -2, 0]
    holes = wall.copy()
    holes[:] = np.nan  # no valid depth: no vote either way
    cv.mark(vm, holes, INTR, FRONT)
    assert votes_at(cv, vm, PROBES).tolist() == [2, 0, -2, 0]
    assert cv.seen_free(*vm.locate(PROBES)).tolist() == [True, False, False, False]


@pytest.mark.parametrize("interleave", [2, 3])
def test_interleaved_frames_vote_every_cell_once_between_them(interleave):
    """With ``interleave`` k, k consecutive frames vote on disjoint cell sets that together are
    every cell: k frames of the same view leave the votes one full frame leaves."""
    vm = wall_map()
    depth = np.full((INTR.height, INTR.width), 2.0, np.float32)
    depth[10:20, 5:40] = 1.93  # a step: cells on either side of it vote differently
    full = CellVotes(VoteConfig(cell=0.01, margin=0.03), voxel_size=0.1, behind=0.05)
    full.mark(vm, depth, INTR, FRONT)
    split = CellVotes(VoteConfig(cell=0.01, margin=0.03, interleave=interleave), voxel_size=0.1, behind=0.05)
    voted = (full.votes != 0).sum()
    for _ in range(interleave):
        before = split.votes.copy() if split.rows else np.zeros_like(full.votes)
        split.mark(vm, depth, INTR, FRONT)
        assert abs((split.votes != before).sum() / voted - 1 / interleave) < 0.05  # each frame its share
    assert np.array_equal(split.votes, full.votes) and voted > 1000
    split.mark(vm, depth, INTR, FRONT)  # the cycle starts again: the first set votes a second time
    assert ((split.votes == 2 * full.votes) | (split.votes == full.votes)).all()
    assert (np.abs(split.votes) == 2).sum() > 0


def _reference_votes(votes, corners, depth, c2w, intr, cell, n, margin, behind, stride, phase):
    """The vote rule cell by cell in numpy (``vote_cells``'s docstring), on a copy of ``votes``."""
    out = votes.astype(np.int64)
    idx = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    w2c = np.linalg.inv(c2w)
    centres = corners[:, None, :] + (idx[None] + 0.5) * cell  # (V, n^3, 3)
    cam = centres @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.floor(intr.fx * cam[..., 0] * (1.0 / z) + intr.cx)
        v = np.floor(intr.fy * cam[..., 1] * (1.0 / z) + intr.cy)
    ok = (z > 1e-3) & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height) & (idx.sum(1) % stride == phase)
    d = np.zeros(z.shape)
    d[ok] = depth[v[ok].astype(int), u[ok].astype(int)]
    ok &= (d > 0) & np.isfinite(d)
    s = d - z
    out[ok & (s > margin)] += 1
    out[ok & (s <= 0) & (s >= -behind)] -= 1
    return np.clip(out, -127, 127).astype(np.int8)


def test_the_kernel_votes_as_the_rule_says_cell_by_cell():
    """The parallel kernel's votes equal the rule's in numpy, on a surface with steps, slopes and
    holes (0, NaN, inf), from views far, near (voxels around and behind the camera plane) and
    partly outside, with votes starting at saturation and with interleaved cells."""
    intr = Intrinsics(96, 72, 60.0, 62.0, 47.3, 35.6)
    rng = np.random.default_rng(3)
    uu = np.mgrid[0:72, 0:96][1]  # pixel columns
    surface = (1.6 + 0.25 * np.sin(uu / 9.0) + 0.002 * uu).astype(np.float32)
    surface[20:45, 30:60] = 1.1  # a box in front
    vm = VoxelMap(VoxelConfig(voxel_size=0.1, min_points=1, prior_clamp=1.0))
    home = look_at(np.zeros(3), np.array([0.1, 1.0, 0.05]))
    vm.allocate(surface, intr, home)
    vm.allocate(surface, intr, look_at(np.array([0.3, 0.1, 0.0]), np.array([0.0, 1.6, 0.1])))
    corners = unpack(vm.voxel_keys).astype(np.float64) * 0.1
    views = [home,
             look_at(np.array([-0.4, 0.2, 0.1]), np.array([0.2, 1.8, -0.1])),  # partly outside
             look_at(np.array([0.05, 1.05, 0.0]), np.array([0.3, 2.5, 0.2])),  # among the voxels
             look_at(np.array([0.013, 1.9, 0.021]), np.array([0.0, 0.0, 0.0]))]  # back through the map
    for interleave in (1, 3):
        cv = CellVotes(VoteConfig(cell=0.01, margin=0.03, interleave=interleave), voxel_size=0.1, behind=0.05)
        cv.mark(vm, np.zeros_like(surface), intr, home)  # rows for every voxel, no vote
        cv.votes = rng.choice(np.array([-127, -126, -1, 0, 1, 126, 127], np.int8), size=cv.votes.shape)
        for i, c2w in enumerate(views * 2):
            depth = surface * np.float32(1.0 + 0.3 * (i % 3)) + rng.normal(0, 0.01, surface.shape).astype(np.float32)
            holes = rng.random(surface.shape)
            depth[holes < 0.04] = 0.0
            depth[(holes > 0.5) & (holes < 0.51)] = np.nan
            depth[(holes > 0.6) & (holes < 0.605)] = np.inf
            depth[:, 70:] = 0.0  # a strip with no depth
            phase = cv._frames % interleave
            expect = _reference_votes(cv.votes, corners, depth, c2w, intr, 0.01, cv.n, 0.03, 0.05, interleave, phase)
            cv.mark(vm, depth, intr, c2w)
            changed = (expect != cv.votes).sum()
            assert changed == 0, f"view {i}, interleave {interleave}: {changed} cells differ"
    assert (cv.votes == 127).sum() > 1000 and ((cv.votes < 0) & (cv.votes > -126)).sum() > 1000


def test_the_majority_of_frames_decides_behind_a_thin_wall():
    """The cell 1.5 cm behind the front view's wall: inside for that view, seen through by a side
    view that measures 4 m past it. One vote each is a tie (not free); a second side frame decides."""
    vm = wall_map()
    cv = CellVotes(VoteConfig(cell=0.01), voxel_size=0.1, behind=0.05)
    cv.mark(vm, np.full((INTR.height, INTR.width), 2.0, np.float32), INTR, FRONT)
    side = np.full((INTR.height, INTR.width), 4.0, np.float32)
    cv.mark(vm, side, INTR, SIDE)
    assert not cv.seen_free(*vm.locate(PROBES[2:3]))[0]
    cv.mark(vm, side, INTR, SIDE)
    assert cv.seen_free(*vm.locate(PROBES[2:3]))[0]
    strict = CellVotes(VoteConfig(cell=0.01, min_votes=3), voxel_size=0.1, behind=0.05)
    strict.votes = cv.votes
    assert not strict.seen_free(*vm.locate(PROBES[2:3]))[0]


def test_votes_saturate_and_points_outside_the_map_are_not_free():
    vm = wall_map()
    cv = CellVotes(VoteConfig(cell=0.02), voxel_size=0.1, behind=0.05)
    assert cv.n == 5 and cv.nbytes == 0
    wall = np.full((INTR.height, INTR.width), 2.0, np.float32)
    for _ in range(130):
        cv.mark(vm, wall, INTR, FRONT)
    assert cv.votes.max() == 127 and cv.votes.min() == -127 and cv.nbytes == len(vm) * 125
    vox, frac = vm.locate(np.array([[5.0, 5.0, 5.0]]))
    assert vox[0] == -1 and not cv.seen_free(vox, frac)[0]


def test_off_by_default_and_a_cell_must_divide_the_voxel():
    cv = CellVotes(VoteConfig(), voxel_size=0.1, behind=0.05)
    assert not cv.enabled and cv.mark(wall_map(), np.ones((48, 64), np.float32), INTR, FRONT) == 0
    with pytest.raises(ValueError, match="divide"):
        CellVotes(VoteConfig(cell=0.03), voxel_size=0.1, behind=0.05)
    for bad in ({"cell": -0.01}, {"cell": float("nan")}, {"margin": -1.0}, {"min_votes": 0}, {"min_votes": 200},
                {"points": -1}):
        with pytest.raises(ValueError):
            VoteConfig(**bad)
    with pytest.raises(ValueError, match="more than"):
        CellVotes(VoteConfig(cell=0.001), voxel_size=0.1, behind=0.05)  # 10^9 bytes a voxel
    from h3edge.config import apply_overrides
    from h3edge.mapping.engine import MapSettings

    with pytest.raises(ValueError, match="divide"):  # refused when the profile loads
        apply_overrides(MapSettings(), ["votes.cell=0.03"])


def test_free_points_are_drawn_in_free_cells_near_a_prior_surface():
    vm = wall_map()
    cv = CellVotes(VoteConfig(cell=0.01), voxel_size=0.1, behind=0.05)
    cv.mark(vm, np.full((INTR.height, INTR.width), 2.0, np.float32), INTR, FRONT)
    gen = torch.Generator().manual_seed(0)
    pts, vox, frac = cv.sample_free(500, vm, gen)
    assert 0 < len(pts) <= 500
    assert np.allclose(vm.locate(pts)[0], vox) and np.allclose(vm.locate(pts)[1], frac)
    assert cv.seen_free(*vm.locate(pts)).all()
    assert (pts[:, 1] < 2.0 - 0.03 + 0.01).all()  # in front of the wall, beyond the margin (cell-rounded)
    with torch.no_grad():
        prior, _ = vm.coarse_sdf(torch.from_numpy(pts))
    assert (prior.numpy() < 1.0).all()
    assert len(cv.sample_free(0, vm, gen)[0]) == 0
    again = cv.sample_free(500, vm, torch.Generator().manual_seed(0))
    assert np.array_equal(again[0], pts)  # reproducible from the generator


def _random_votes_and_their_cells() -> tuple[VoxelMap, CellVotes, np.ndarray]:
    """A wall map with random votes and priors (2 cm cells, min_votes 2), and the flat indices
    ``row * n^3 + cell`` of the cells a draw may pick: at least 2 votes, centre prior under 0.5."""
    vm = wall_map()
    cv = CellVotes(VoteConfig(cell=0.02, min_votes=2), voxel_size=0.1, behind=0.05)
    cv.mark(vm, np.full((INTR.height, INTR.width), 2.0, np.float32), INTR, FRONT)
    rng = np.random.default_rng(0)
    cv.votes[:] = rng.integers(-3, 4, cv.votes.shape)
    vm.priors = torch.from_numpy(rng.uniform(-1.5, 2.5, len(vm.priors)).astype(np.float32))
    cells = np.arange(cv.n ** 3)
    centres = (np.stack(np.unravel_index(cells, (cv.n,) * 3), 1) + 0.5) / cv.n  # every cell's centre
    with torch.no_grad():
        prior, _ = vm.coarse_sdf(torch.zeros(len(vm) * len(cells), 3),
                                 (torch.from_numpy(np.repeat(np.arange(len(vm)), len(cells))),
                                  torch.from_numpy(np.tile(centres, (len(vm), 1)).astype(np.float32))))
    want = np.flatnonzero((cv.votes.reshape(-1) >= 2) & (prior.numpy() < 0.5))
    assert 0 < len(want) < cv.votes.size
    return vm, cv, want


def test_free_points_come_from_every_voted_cell_whose_centre_prior_reads_near_a_surface_and_no_other():
    from h3edge.mapping import _vote_kernel as k

    vm, cv, want = _random_votes_and_their_cells()
    priors = vm.priors.numpy()
    drawn = k.draw_free_cells(cv.votes, vm.voxel_vertices, priors, cv.n, 2, np.float32(0.5), 30 * len(want), 10 ** 8, 1)
    assert len(drawn) == 30 * len(want)
    assert np.array_equal(np.unique(drawn), want)  # each of them (30 draws each on average), no other
    counts = np.bincount(np.searchsorted(want, drawn), minlength=len(want))
    assert counts.min() > 5 and counts.max() < 70  # uniform: Poisson(30) stays inside by far
    assert len(k.draw_free_cells(cv.votes, vm.voxel_vertices, priors, cv.n, 2, np.float32(-5.0), 10, 1000, 1)) == 0


def test_the_device_draw_keeps_the_rule_of_the_host_draw():
    """``sample_free_tensor`` (the torch backend's draw, fixed shapes on the device) draws from the
    same cells as the host draw (enough votes, centre prior near a surface), all of them and no
    other, each point at the world position of its voxel and fraction; the points it cannot fill
    are marked -1."""
    vm, cv, want = _random_votes_and_their_cells()
    n = 10 * len(want)
    pts, vox, frac = cv.sample_free_tensor(n, vm, torch.Generator().manual_seed(0), near_prior=0.5)
    assert pts.shape == (n, 3) and vox.shape == (n,) and frac.shape == (n, 3)
    ok = vox >= 0
    assert ok.float().mean() > 0.9  # DEVICE_TRIES random cells a point find enough at this acceptance
    c = np.floor(frac[ok].numpy() * cv.n).astype(np.int64)
    drawn = vox[ok].numpy() * cv.n ** 3 + (c[:, 0] * cv.n + c[:, 1]) * cv.n + c[:, 2]
    assert set(drawn.tolist()) <= set(want.tolist()) and len(np.unique(drawn)) > 0.99 * len(want)
    found_vox, found_frac = vm.locate(pts[ok].double().numpy())
    assert np.array_equal(found_vox, vox[ok].numpy()) and np.allclose(found_frac, frac[ok].numpy(), atol=1e-5)
    few = cv.sample_free_tensor(10, vm, torch.Generator().manual_seed(0), near_prior=-5.0)[1]
    assert (few == -1).all()  # no cell passes: every point marked
    again = cv.sample_free_tensor(n, vm, torch.Generator().manual_seed(0), near_prior=0.5)
    assert torch.equal(again[0], pts)  # reproducible from the generator


def test_seen_free_on_the_device_and_the_mirror_follow_every_mark():
    vm = wall_map()
    cv = CellVotes(VoteConfig(cell=0.01), voxel_size=0.1, behind=0.05)
    rng = np.random.default_rng(3)
    vox = torch.from_numpy(rng.integers(-1, len(vm), 5000))
    frac = torch.from_numpy(rng.uniform(0, 1, (5000, 3)).astype(np.float32))
    mirror = cv._mirrored(torch.device("cpu"))  # what a CUDA device gets: a copy kept up to date
    assert len(mirror) == 0 and not cv.seen_free_tensor(mirror, vox, frac).any()
    for depth in (2.0, 2.0, 1.5):
        cv.mark(vm, np.full((INTR.height, INTR.width), depth, np.float32), INTR, FRONT)
        mirror = cv._mirrored(torch.device("cpu"))
        assert np.array_equal(mirror.numpy(), cv.votes) and mirror.data_ptr() != cv.votes.ctypes.data
        want = cv.seen_free(vox.numpy(), frac.numpy().astype(np.float64))
        assert want.any() and np.array_equal(cv.seen_free_tensor(mirror, vox, frac).numpy(), want)
        assert np.array_equal(cv.seen_free_tensor(cv.on_device(torch.device("cpu")), vox, frac).numpy(), want)


def test_state_round_trip_and_a_state_at_another_cell_size_starts_empty():
    vm = wall_map()
    cv = CellVotes(VoteConfig(cell=0.01), voxel_size=0.1, behind=0.05)
    cv.mark(vm, np.full((INTR.height, INTR.width), 2.0, np.float32), INTR, FRONT)
    back = CellVotes(VoteConfig(cell=0.01), voxel_size=0.1, behind=0.05)
    back.load_state_dict(cv.state_dict())
    assert np.array_equal(back.votes, cv.votes)
    other = CellVotes(VoteConfig(cell=0.02), voxel_size=0.1, behind=0.05)
    other.load_state_dict(cv.state_dict())
    assert other.votes.shape == (0, 125)
    other.load_state_dict({})
    assert other.votes.shape == (0, 125)


def test_storage_grows_by_doubling_keeps_the_votes_and_stops_at_the_voxel_cap():
    cv = CellVotes(VoteConfig(cell=0.05), voxel_size=0.1, behind=0.05, max_voxels=10)
    cv._grow(3)
    cv.votes[:] = 5
    cv._grow(4)
    assert cv.votes.shape == (4, 8) and len(cv._store) == 6 and (cv.votes[:3] == 5).all() and (cv.votes[3] == 0).all()
    cv._grow(7)
    assert len(cv._store) == 10 and cv.rows == 7  # doubling capped at max_voxels
    assert (cv.votes[:3] == 5).all()


def test_seen_free_points_that_read_outside_are_left_out_with_the_same_loss_and_gradient():
    """The trainer evaluates the seen-free points once without autograd and keeps those reading
    inside: the hinge is flat at s >= 0, so the loss and every gradient (MLP, priors, hash rows) are
    those of all the points, at a fraction of the backward pass."""
    from h3edge.mapping.field import Field, FieldConfig
    from h3edge.mapping.trainer import reading_inside, seen_free_loss

    vm = wall_map()
    rng = np.random.default_rng(0)
    with torch.no_grad():
        vm.priors.copy_(torch.from_numpy(rng.uniform(-1.0, 1.0, len(vm.priors)).astype(np.float32)))
    vm.priors.requires_grad_(True)
    bound = np.array([[-1.0, 0.0, -1.0], [1.0, 3.0, 1.0]])
    fld = Field(FieldConfig(geo_log2_table=10, tex_log2_table=10, sdf_layers=2), bound, 0.1)
    vox = rng.integers(0, len(vm), 2000)
    frac = rng.uniform(0, 1, (2000, 3))
    pts = (unpack(vm.voxel_keys[vox]) + frac) * 0.1
    tr = vm.cfg.truncation

    def grads(loss):
        for p in list(fld.sdf_mlp.parameters()) + [vm.priors]:
            p.grad = None
        loss.backward()
        rows, g = fld.geo_grid.take_sparse_grad()
        order = torch.argsort(rows)
        return ([p.grad.clone() for p in fld.sdf_mlp.parameters()] + [vm.priors.grad.clone()], rows[order], g[order])

    pts, vox, frac = (torch.from_numpy(pts.astype(np.float32)), torch.from_numpy(vox),
                      torch.from_numpy(frac.astype(np.float32)))
    sdf, inside = fld.sdf(pts, vm, (vox, frac))
    full = seen_free_loss(sdf, inside, tr)
    g_full = grads(full)
    (kp, kv, kf), count = reading_inside(fld, vm, (pts, vox, frac))
    assert count == 2000 and 0 < len(kp) < 0.9 * count
    sdf_k, inside_k = fld.sdf(kp, vm, (kv, kf))
    assert (sdf_k < 0).all()
    kept = seen_free_loss(sdf_k, inside_k, tr, count)
    g_kept = grads(kept)
    assert torch.allclose(full, kept, rtol=1e-5, atol=0)
    for a, b in zip(g_full[0], g_kept[0]):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-9)
    hit = g_full[2].abs().sum(1) > 0  # hash rows only the left-out points touched carry zero gradient
    assert torch.equal(g_full[1][hit], g_kept[1]) and torch.allclose(g_full[2][hit], g_kept[2], rtol=1e-4, atol=1e-9)


def test_a_window_of_seen_free_samples_renders_no_surface():
    """The voxels in front of the wall hold a prior crossing 9 cm in front of it (a phantom an
    untrained voxel keeps) where two frames saw through. At the shipped floor the window around
    that crossing carries no weight and the ray renders the wall; at 0.1 truncation units each of
    its samples weighed 0.1 and the window rendered the phantom (D53-7); the settings refuse that floor."""
    from h3edge.config import load_profile
    from h3edge.mapping.engine import MapSettings
    from h3edge.mapping.field import Field, FieldConfig
    from h3edge.mapping.raymarch import MapRenderer, RenderConfig, floor_window_weight

    vm = wall_map()
    cv = CellVotes(VoteConfig(cell=0.01, min_votes=2), voxel_size=0.1, behind=0.05)
    for _ in range(2):
        cv.mark(vm, np.full((INTR.height, INTR.width), 2.0, np.float32), INTR, FRONT)
    y = torch.from_numpy(unpack(vm.vertex_keys)[:, 1])
    with torch.no_grad():
        vm.priors[y == 19], vm.priors[y == 20], vm.priors[y == 21] = 0.1, -0.9, -1.0  # crossing at 1.91 m
    fld = Field(FieldConfig(geo_log2_table=10, tex_log2_table=10, sdf_layers=2), np.array([[-3.0] * 3, [3.0] * 3]), 0.1)
    shipped = load_profile("x86-cpu").map_settings()
    assert floor_window_weight(shipped.render, shipped.field.beta) < 1e-3
    depth = MapRenderer(fld, vm, shipped.render, cv).render(INTR, FRONT)[1]
    assert np.all(np.abs(depth - 2.0) < 0.04)
    low = RenderConfig(free_floor=0.1)
    assert floor_window_weight(low, shipped.field.beta) > low.min_weight
    assert np.median(MapRenderer(fld, vm, low, cv).render(INTR, FRONT)[1]) < 1.95
    with pytest.raises(ValueError, match="free_floor"):
        MapSettings(render=low)


def test_the_render_floor_lifts_the_sdf_in_free_cells_only():
    """``render.free_floor``: where the votes say free, the SDF a render or mesh reads is at least
    the floor; elsewhere (a cell just in front of or behind the wall, outside the map) it is untouched
    (-inf bound), and it follows the votes as they change."""
    from h3edge.mapping.raymarch import free_floor_fn

    vm = wall_map()
    cv = CellVotes(VoteConfig(cell=0.01, min_votes=2), voxel_size=0.1, behind=0.05)
    wall = np.full((INTR.height, INTR.width), 2.0, np.float32)
    for _ in range(2):
        cv.mark(vm, wall, INTR, FRONT)
    pts = np.concatenate([PROBES, [[50.0, 50.0, 50.0]]])
    vox = vm.locate(pts)[0]
    floor = free_floor_fn(cv, vm, 0.1)
    assert floor(pts, vox).tolist() == [0.1, -np.inf, -np.inf, -np.inf, -np.inf]
    assert free_floor_fn(cv, vm, 0.0) is None and free_floor_fn(None, vm, 0.1) is None
    cv.votes[:] = 0
    assert floor(pts, vox)[0] == -np.inf
