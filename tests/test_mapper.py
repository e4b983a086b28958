"""The incremental mapper end to end on the tiny simulated scene, its drop rules and the renderer."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from h3edge.eval.metrics import psnr
from h3edge.geometry.camera import PIXEL_CENTER_OFFSET, Intrinsics, look_at, pixel_rays_world
from h3edge.io.replica import ReplicaSequence
from h3edge.mapping.engine import MapEngine, MapperConfig, MapSettings
from h3edge.mapping.field import Field, FieldConfig
from h3edge.mapping.raymarch import MapRenderer, RenderConfig
from h3edge.mapping.voxels import PriorAdam, VoxelConfig, VoxelMap, unpack

LEAN = MapSettings(mapper=MapperConfig(device="cpu", rays_per_iteration=1024, mesh_resolution=2),
                   voxels=VoxelConfig(min_points=3), field=FieldConfig(sdf_layers=2, geo_log2_table=16,
                                                                      tex_log2_table=16))


@pytest.fixture(scope="module")
def mapped(tiny_scene):
    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(LEAN)
    results = [m.process(f) for f in seq]
    return seq, m, results


def test_maps_tiny_scene(mapped):
    seq, m, results = mapped
    assert all(r.mapped for r in results)
    assert results[0].keyframe and results[0].new_voxels > 0
    # a keyframe at least every max_interval frames
    kf = [i for i, r in enumerate(results) if r.keyframe]
    assert np.diff(kf).max() <= m.settings.keyframes.max_interval
    held = seq.heldout[0]
    rgb, depth = m.render(held.intrinsics, held.pose)
    valid = (held.depth > 0) & (depth > 0)
    assert valid.mean() > 0.9
    assert np.median(np.abs(depth[valid] - held.depth[valid])) < 0.02  # metres
    assert psnr(rgb, held.color) > 15.0
    summary = m.timings.summary()
    assert {"read", "priors", "texture", "keyframes", "training", "frame", "render"} <= set(summary)
    assert summary["training"]["count"] == len(seq)
    # H3: texture patterns every update_interval frames, quasi-heterogeneous features, gradient scores
    assert summary["texture"]["count"] == -(-len(seq) // m.settings.texture.update_interval)
    assert m.field.texture.out_dim == 4 * 4 * 2 and len(m.field.texture.weak) > 0
    assert sum(m.stats()["texture_classes"].values()) == len(m.voxels)
    assert any(k.scores.max() > 1 for k in m.keyframes.keyframes)


def test_uniform_texture_variant(tiny_scene):
    """H2-Mapping's uniform grid and voxel-count keyframe score behind the same mapper."""
    from h3edge.mapping.keyframes import KeyframeConfig
    from h3edge.mapping.texture_patterns import TextureConfig

    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(dataclasses.replace(LEAN, texture=TextureConfig(quasi_heterogeneous=False),
                                   keyframes=KeyframeConfig(gradient_aided=False)))
    for f in list(seq)[:3]:
        assert m.process(f).mapped
    assert m.field.texture.out_dim == 4 * 2 and "texture" not in m.timings.summary()
    assert all((k.scores == 1).all() for k in m.keyframes.keyframes)


def test_mesh_is_near_the_surface(mapped, tiny_scene):
    import trimesh
    from scipy.spatial import cKDTree

    _, m, _ = mapped
    mesh = m.mesh()
    assert len(mesh.faces) > 1000
    assert mesh.visual.vertex_colors.shape == (len(mesh.vertices), 4)
    gt = trimesh.load(tiny_scene / "gt_mesh.ply", process=False)
    d, _ = cKDTree(trimesh.sample.sample_surface(gt, 100_000, seed=0)[0]).query(mesh.vertices)
    assert np.median(d) < 0.03


def test_bad_frames_are_dropped_and_the_map_is_untouched(mapped, tiny_scene):
    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(LEAN)
    m.process(seq[0])
    m.process(seq[1])
    state = (len(m.voxels), m.voxels.priors.detach().clone(), m.field.geo_grid.table.detach().clone())
    f = seq[2]
    bad = {
        "duplicate": dataclasses.replace(f, timestamp=seq[1].timestamp),
        "out of order": dataclasses.replace(f, timestamp=seq[0].timestamp),
        "non-rigid": dataclasses.replace(f, pose=f.pose * np.array([[1.1], [1], [1], [1]])),
        "nan pose": dataclasses.replace(f, pose=np.full((4, 4), np.nan)),
        "wrong size": dataclasses.replace(f, depth=f.depth[:-1]),
        "no depth": dataclasses.replace(f, depth=np.zeros_like(f.depth)),
        "all nan depth": dataclasses.replace(f, depth=np.full_like(f.depth, np.nan)),
        "grey colour": dataclasses.replace(f, color=f.color[..., 0]),
    }
    for name, frame in bad.items():
        r = m.process(frame)
        assert not r.mapped and r.reason, name
    assert sum(m.dropped.values()) == len(bad)
    assert m.dropped == {"stale_timestamp": 2, "bad_pose": 2, "bad_depth": 1, "no_depth": 2, "bad_colour": 1}
    assert len(m.voxels) == state[0]
    assert torch.equal(m.voxels.priors.detach(), state[1])
    assert torch.equal(m.field.geo_grid.table.detach(), state[2])
    # partly NaN / negative depth is cleaned, not dropped
    d = f.depth.copy()
    d[::2] = np.nan
    d[1::4] = -1
    assert m.process(dataclasses.replace(f, depth=d)).mapped


def test_render_finds_an_analytic_plane():
    """Priors set to a plane's SDF and a zero residual: the renderer puts the surface on the plane."""
    intr = Intrinsics(64, 48, 50.0, 50.0, 32.0, 24.0)
    c2w = look_at(np.array([0.03, 0.02, 1.5]), np.array([0.03, 0.02, 0.0]), up=np.array([0.0, 1.0, 0.0]))
    o, d = pixel_rays_world(intr, c2w)
    t = (0.0 - o[2]) / d[..., 2]  # plane z = 0: ray hits at t (= z-depth)
    depth = t.astype(np.float32)
    vm = VoxelMap(VoxelConfig(min_points=1))
    vm.allocate(depth, intr, c2w)
    z = unpack(vm.vertex_keys)[:, 2]  # vertex z index
    vm.priors.data[:] = torch.from_numpy((z * vm.cfg.voxel_size / vm.cfg.truncation).astype(np.float32))
    fld = Field(FieldConfig(geo_log2_table=12, tex_log2_table=12), np.array([[-2.0] * 3, [2.0] * 3]), 0.1)
    with torch.no_grad():
        fld.sdf_mlp[-1].weight.zero_()
        fld.sdf_mlp[-1].bias.zero_()
    rgb, out = MapRenderer(fld, vm).render(intr, c2w)
    hit = out > 0
    assert hit.mean() > 0.95
    assert np.abs(out[hit] - depth[hit]).max() < 0.003
    with pytest.raises(ValueError, match="exceeds the cap"):
        MapRenderer(fld, vm, RenderConfig(max_pixels=100)).render(intr, c2w)


def test_render_takes_a_surface_just_past_the_allocated_voxels():
    """Voxels end where depth points end, and the residual can carry the surface a few millimetres
    past the region's face (studio's concave corners: black specks where the full SDF left the
    voxels at +0.04-0.08 truncations). The prior march already takes such an exit on the prior;
    the full-SDF fallback takes it too (``exit_tolerance``), at the field's extrapolated zero.
    Here the priors exit at +0.2 (no prior hit) and the residual's -0.16 puts the surface 2 mm
    below the voxels: without the exit rule no ray renders."""
    intr = Intrinsics(64, 48, 50.0, 50.0, 32.0, 24.0)
    c2w = look_at(np.array([0.03, 0.02, 1.5]), np.array([0.03, 0.02, 0.0]), up=np.array([0.0, 1.0, 0.0]))
    o, d = pixel_rays_world(intr, c2w)
    vm = VoxelMap(VoxelConfig(min_points=1))
    vm.allocate((0.05 - o[2]) / d[..., 2], intr, c2w)  # points mid-voxel: the voxels span z 0 .. 0.1
    tr = vm.cfg.truncation
    z = unpack(vm.vertex_keys)[:, 2] * vm.cfg.voxel_size
    assert z.min() == 0.0
    vm.priors.data[:] = torch.from_numpy(((z + 0.01) / tr).astype(np.float32))  # prior zero 1 cm below
    fld = Field(FieldConfig(geo_log2_table=12, tex_log2_table=12), np.array([[-2.0] * 3, [2.0] * 3]), 0.1)
    with torch.no_grad():
        fld.sdf_mlp[-1].weight.zero_()
        fld.sdf_mlp[-1].bias.fill_(-0.008 / tr)  # full SDF zero at z = -0.002
    surface = (-0.002 - o[2]) / d[..., 2]

    def rendered(tolerance: float) -> np.ndarray:
        return MapRenderer(fld, vm, RenderConfig(exit_tolerance=tolerance)).render(intr, c2w)[1]

    assert (rendered(0.0) > 0).mean() == 0.0
    out = rendered(RenderConfig().exit_tolerance)
    hit = out > 0
    assert hit.mean() > 0.2, hit.mean()  # rays whose last 1 cm sample reads <= 0.1 (z < 3 mm)
    assert np.abs(out[hit] - surface[hit]).max() < 0.004


def test_prior_adam_keeps_state_across_growth():
    vm = VoxelMap(VoxelConfig(min_points=1))
    intr = Intrinsics(8, 6, 5.0, 5.0, 4.0, 3.0)
    vm.allocate(np.full((6, 8), 1.0, np.float32), intr, np.eye(4))
    opt = PriorAdam(lr=0.1)
    (vm.priors * torch.arange(len(vm.priors))).sum().backward()
    opt.step(vm)
    m_before = opt.m.clone()
    n = len(vm.priors)
    vm.allocate(np.full((6, 8), 2.0, np.float32), intr, np.eye(4))
    assert len(vm.priors) > n
    (vm.priors[:1] * 1.0).sum().backward()
    opt.step(vm)
    assert len(opt.m) == len(vm.priors)
    assert torch.allclose(opt.m[1:n], m_before[1:n])  # untouched rows keep their moments


def test_a_frame_that_allocates_nothing_is_dropped_not_crashed():
    """A first frame whose depth leaves every voxel under min_points used to reach training on an
    empty map (IndexError, counted as internal_error by the service); it is a counted drop, and
    the next good frame maps."""
    from h3edge.io.sequence import Frame

    intr = Intrinsics(32, 24, 30.0, 30.0, 16.0, 12.0)
    rng = np.random.default_rng(0)
    color = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    sparse = np.zeros((24, 32), np.float32)
    sparse[::6, ::6] = rng.uniform(0.5, 4.0, (4, 6))  # 24 scattered points: no voxel gets 3
    m = MapEngine(LEAN)
    r = m.process(Frame(0, 0.0, color, sparse, np.eye(4), intr))
    assert not r.mapped and m.dropped == {"no_voxels": 1} and m.train_between_frames() is None
    r = m.process(Frame(1, 0.1, color, np.full((24, 32), 2.0, np.float32), np.eye(4), intr))
    assert r.mapped and len(m.voxels) > 0


def test_the_field_built_before_the_first_frame_maps_as_one_built_there(tiny_scene):
    """The field is built when the mapper is (its random tables took ~90 ms of the first frame's
    integration, which skipped the next two frames at 30 Hz) and moved to the first frame's pose:
    the same field as one built at that pose, bit for bit after integration, and within the
    run-to-run noise of parallel float sums after training steps."""
    seq = ReplicaSequence(tiny_scene)
    early, late = MapEngine(LEAN), MapEngine(LEAN)
    assert early.field is None and early._unplaced is not None  # nothing placed before a frame
    late._unplaced = None  # built where the first frame places it, as before
    for m in (early, late):
        for k in range(3):
            assert m.integrate(seq[k]).mapped
    assert early.bound is not None and np.array_equal(early.bound, late.bound)
    for a, b in zip(early.field.state_dict().values(), late.field.state_dict().values()):
        assert torch.equal(a, b)
    for m in (early, late):
        for _ in range(2):
            m.train_once()
    for a, b in zip(early.field.state_dict().values(), late.field.state_dict().values()):
        assert torch.allclose(a, b, atol=1e-4)
    f = seq[3]
    assert np.allclose(early.render(f.intrinsics, f.pose)[1], late.render(f.intrinsics, f.pose)[1], atol=1e-3)


def test_ray_tables_are_a_bounded_counted_cache(tiny_scene):
    """Frames whose intrinsics differ slightly each time keep at most RAY_TABLES ray tables, and
    their bytes are in the memory stats (issue 16, item 5)."""
    from h3edge.mapping.engine import RAY_TABLES

    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(LEAN)
    for k in range(RAY_TABLES + 3):
        f = seq[k]
        f.intrinsics = dataclasses.replace(f.intrinsics, fx=f.intrinsics.fx + 1e-4 * k)
        assert m.process(f).mapped
    assert len(m._rays_cache) == RAY_TABLES
    assert m.stats()["memory_bytes"]["ray_tables"] == RAY_TABLES * 12 * f.intrinsics.width * f.intrinsics.height


def test_surface_color_points_lie_on_the_measured_surface(tiny_scene):
    """``train.surface_color_points``: extra pixels back-projected with their measured depth; each
    point projects back onto its pixel at that depth and carries that pixel's colour; the step
    trains the colour field there."""
    from h3edge.mapping.trainer import TrainConfig, surface_color_loss

    seq = ReplicaSequence(tiny_scene)
    settings = dataclasses.replace(LEAN, train=TrainConfig(surface_color_points=600))
    m = MapEngine(settings)
    f = seq[0]
    assert m.process(f).mapped
    current, _ = m._prepare(f)
    rays = m._sample_rays([current, m.keyframes.keyframes[0].payload])
    assert rays.surface_points.shape == (600, 3) and rays.surface_color.shape == (600, 3)
    w2c = np.linalg.inv(f.pose)
    cam = rays.surface_points.numpy().astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    k = f.intrinsics
    u = np.rint(cam[:, 0] / cam[:, 2] * k.fx + k.cx - PIXEL_CENTER_OFFSET).astype(int)
    v = np.rint(cam[:, 1] / cam[:, 2] * k.fy + k.cy - PIXEL_CENTER_OFFSET).astype(int)
    depth = current.depth[v, u]
    assert (depth > 0).all() and np.allclose(cam[:, 2], depth, atol=2e-4)  # stored depth: uint16 steps
    assert np.allclose(rays.surface_color.numpy() * 255, current.color[v, u], atol=0.5)
    before = float(surface_color_loss(m.field, m.voxels, rays))
    for _ in range(30):
        m._step(rays, "frame")
    assert float(surface_color_loss(m.field, m.voxels, rays)) < 0.7 * before


def test_edge_rays_come_from_beside_the_silhouettes(tiny_scene):
    """``mapper.edge_rays``: that share of each frame's rays, keyframes' included, is drawn among the
    far side of its depth edges (the background beside a silhouette), with ``edge_rays_near_too``
    among both sides; the rest uniformly. ``edge_rays`` 0 is the paper's uniform draw."""
    from h3edge.geometry.depth_edges import far_side_of_edges

    seq = ReplicaSequence(tiny_scene)
    settings = dataclasses.replace(LEAN, mapper=dataclasses.replace(LEAN.mapper, edge_rays=0.5, edge_rays_radius=4,
                                                                     edge_rays_near_too=False))
    m = MapEngine(settings)
    f = seq[0]
    assert m.process(f).mapped
    current, _ = m._prepare(f)
    stored = m.keyframes.keyframes[0].payload
    step = m.cfg.edge_radius + 1
    jump = m.edge_jump(f.intrinsics, step)
    far = far_side_of_edges(current.depth, 4, jump, step).reshape(-1)
    assert 0.001 < far.mean() < 0.2  # the scene has silhouettes, and they are a small part of the view
    assert np.array_equal(stored.edge_pixels(4, jump, step), np.flatnonzero(far))
    rays = m._sample_rays([current, stored])
    pix = _ray_pixels(rays, f)
    on_far = far[pix]
    n = len(rays.depth)
    expected = 0.5 + 0.5 * far.sum() / (current.depth > 0).sum()
    assert abs(on_far.mean() - expected) < 4 * np.sqrt(expected * (1 - expected) / n), (on_far.mean(), expected)
    assert np.allclose(rays.depth.numpy(), current.depth.reshape(-1)[pix], atol=2e-4)
    near_too = dataclasses.replace(settings.mapper, edge_rays_near_too=True)
    both = MapEngine(dataclasses.replace(settings, mapper=near_too))
    assert both.process(f).mapped
    edges = np.zeros(far.shape, bool)
    edges[both.keyframes.keyframes[0].payload.edge_pixels(4, jump, step, True)] = True
    assert edges.sum() > far.sum()  # the near side too
    near_rays = both._sample_rays([both._prepare(f)[0]])
    expected = 0.5 + 0.5 * edges.sum() / (current.depth > 0).sum()
    on_edges = edges[_ray_pixels(near_rays, f)].mean()
    sigma = np.sqrt(expected * (1 - expected) / len(near_rays.depth))
    assert abs(on_edges - expected) < 4 * sigma, (on_edges, expected)
    uniform = MapEngine(dataclasses.replace(LEAN, mapper=dataclasses.replace(LEAN.mapper, edge_rays=0.0)))
    assert uniform.process(f).mapped
    plain = uniform._sample_rays([uniform._prepare(f)[0]])
    share = far.sum() / (current.depth > 0).sum()  # the paper's uniform draw: edges at their share
    assert abs(far[_ray_pixels(plain, f)].mean() - share) < 4 * np.sqrt(share * (1 - share) / len(plain.depth))


def _ray_pixels(rays, f) -> np.ndarray:
    """Flat pixel index in frame ``f`` of each ray's measured surface point."""
    w2c = np.linalg.inv(f.pose)
    cam = (rays.origins + rays.dirs * rays.depth[:, None]).numpy().astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    k = f.intrinsics
    u = np.rint(cam[:, 0] / cam[:, 2] * k.fx + k.cx - PIXEL_CENTER_OFFSET).astype(int)
    v = np.rint(cam[:, 1] / cam[:, 2] * k.fy + k.cy - PIXEL_CENTER_OFFSET).astype(int)
    return v * k.width + u


def test_grid_cell_sets_the_hash_grids_level0_cell_apart_from_the_voxel():
    """``field.grid_cell`` 0 keeps the paper's one level-0 cell per leaf voxel; a value in metres
    keeps the grids' resolution when the leaf voxel (the priors' lattice) changes."""
    bound = np.array([[-2.0] * 3, [2.0] * 3])
    cfg = FieldConfig(geo_log2_table=10, tex_log2_table=10)
    paper = Field(cfg, bound, 0.1)
    halved = Field(cfg, bound, 0.05)
    kept = Field(FieldConfig(geo_log2_table=10, tex_log2_table=10, grid_cell=0.1), bound, 0.05)
    assert paper.geo_grid.spec.base_resolution == 40
    assert halved.geo_grid.spec.base_resolution == 80
    assert kept.geo_grid.spec.base_resolution == 40
    assert kept.texture.grid.spec.base_resolution == 40
    with pytest.raises(ValueError, match="grid_cell"):
        Field(FieldConfig(grid_cell=-0.1), bound, 0.05)
