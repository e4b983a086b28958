"""Silhouettes on real-like depth: a slatted chair back in front of a wall, Kinect-like depth
(holes at every depth edge, axial noise). Each root cause of the inflated silhouettes that real
data showed (issue 15) has a check here that fails without its fix:

- SDF priors tried only once, when a voxel is allocated: on depth with holes at every edge most
  voxels by the slats never get their priors (``voxels.prior_retry``);
- the renderer accepted a fine window with (almost) no rendering weight as a surface, at the
  weights' mean depth, where the prior march had stopped on a phantom crossing
  (``render.min_weight``), and rays whose surface the prior misses need the full-SDF fallback
  (``render.fallback_step``);
- the renderer took the priors' first crossing for the surface: where the residual carries a
  surface the priors' 10 cm lattice cannot (a 4 cm table top's front face), rays went through it
  to the floor behind; the full SDF is now searched in front of the prior's crossing
  (``render.field_step``);
- the renderer's fine window needed rendering weight: a field steeper than the unit slope leaves
  the 2.5 mm kernel between two 1 cm samples, and the ray marched on through the surface
  (``render.window_crossing``: the window's zero crossing is the surface);
- projective priors behind a silhouette were written down to -init_range (24.5 cm behind the
  surface), a thick shadow; truncated like a TSDF (``voxels.prior_clamp``) they are not;
- the mesh took the field's zero level everywhere in the allocated voxels, also where no
  observation ever set a prior (the prior reads 0 there: phantom surfaces); it now meshes only
  cubes with observed support (``mapper.mesh_min_support``);
- structured light spills the foreground's depth past its outline (and flying pixels between):
  mapped as measured, a rim in front of the background; the near side of every depth edge is left
  out (``mapper.edge_radius``).
(The SDF loss's units, the largest single fix, are checked in ``test_rendering_losses``.)
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from h3edge.eval.metrics import depth_error_shares
from h3edge.geometry.camera import Intrinsics, look_at, project
from h3edge.geometry.raycast import MeshRaycaster
from h3edge.io.sequence import Frame
from h3edge.mapping.engine import MapEngine, MapperConfig, MapSettings
from h3edge.mapping.field import FieldConfig
from h3edge.mapping.raymarch import RenderConfig
from h3edge.mapping.voxels import VoxelConfig
from h3edge.sim.sensor import SensorModel, degrade_depth
from tests.helpers import SHIPPED_FIXES, with_shipped_fixes

INTR = Intrinsics(320, 240, 280.0, 280.0, 160.0, 120.0)
SLAT_X = np.arange(-0.30, 0.31, 0.06)  # 3 cm slats, 3 cm gaps


def box(size, centre) -> trimesh.Trimesh:
    return trimesh.creation.box(size, trimesh.transformations.translation_matrix(centre))


def wall_and_floor() -> list[trimesh.Trimesh]:
    """A wall at y = 2 m and the floor (the first 24 faces: lit light by :func:`frames`)."""
    return [box((4.0, 0.05, 2.5), (0, 2.025, 1.25)), box((4.0, 4.0, 0.05), (0, 0.5, -0.025))]


def slatted_scene(slats: bool = True) -> trimesh.Trimesh:
    """The wall and floor, and 0.8 m in front of the wall either vertical slats (3 x 2 x 60 cm,
    3 cm apart) or one solid block of the same outline (63 x 20 x 60 cm)."""
    parts = wall_and_floor()
    if slats:
        parts += [box((0.03, 0.02, 0.6), (x, 1.2, 0.9)) for x in SLAT_X]
    else:
        parts.append(box((0.63, 0.2, 0.6), (0, 1.3, 0.9)))
    return trimesh.util.concatenate(parts)


def frames(mesh: trimesh.Trimesh, n: int, heldout: bool = False, noisy: bool = True, spill: int = 0) -> list[Frame]:
    """Views from 1 m in front of the slats, sweeping sideways; held-out views sit between them.
    ``spill``: pixels the foreground's depth spills past its outline (structured light)."""
    caster = MeshRaycaster(mesh.vertices, mesh.faces)
    rng = np.random.default_rng(1 if heldout else 0)
    out = []
    for i in range(n):
        s = (i + (0.5 if heldout else 0.0)) / max(n - 1, 1)
        eye = np.array([-0.6 + 1.2 * s, 0.1, 1.0 + 0.15 * np.sin(3 * s)])
        pose = look_at(eye, np.array([0.0, 1.6, 0.85]))
        hits = caster.hits(INTR, pose)
        shade = np.where(hits.prim[..., None] < 24, 200, 90).astype(np.uint8)  # wall/floor light, slats dark
        color = np.repeat(shade, 3, -1)
        color[..., 0] = np.where(hits.valid, color[..., 0], 0)
        depth = hits.depth
        if noisy:
            depth = degrade_depth(depth, hits.cos_incidence, SensorModel(depth_noise=True, missing_depth=True,
                                                                         dropout=0.0, edge_spill_px=spill), rng)
        out.append(Frame(i, float(i) / 30, color, depth.astype(np.float32), pose, INTR))
    return out


SETTINGS = with_shipped_fixes(MapSettings(
    mapper=MapperConfig(device="cpu", rays_per_iteration=2048, iterations=2, extent=6.4),
    voxels=VoxelConfig(min_points=3), field=FieldConfig(sdf_layers=2, geo_log2_table=16, tex_log2_table=16)))


@pytest.fixture(scope="module")
def scene():
    mesh = slatted_scene()
    return frames(mesh, 16), frames(mesh, 15, heldout=True, noisy=False)


def mapped(train, settings) -> MapEngine:
    m = MapEngine(settings)
    for f in train:
        m.process(f)
    return m


def error_share(m: MapEngine, views, kind: str, render: RenderConfig | None = None) -> float:
    """Mean share of valid pixels rendered > 5 cm off the true depth, ``kind`` "front_share" (in
    front) or "behind_share", over held-out views."""
    view = m.view()
    if render is not None:
        view.render_cfg = render
    return float(np.mean([depth_error_shares(view.render(f.intrinsics, f.pose)[1], f.depth)[kind]
                          for f in views[3:12:2]]))


def front_share(m: MapEngine, views, render: RenderConfig | None = None) -> float:
    """Mean share of valid pixels rendered > 5 cm in front of the true depth, over held-out views."""
    return error_share(m, views, "front_share", render)


@pytest.fixture(scope="module")
def fixed(scene):
    return mapped(scene[0], SETTINGS)


def table_scene() -> trimesh.Trimesh:
    """The wall and floor, and a 4 cm thick table top (80 x 60 cm) 0.72 m above the floor, its edges
    on voxel faces: no prior lattice vertex lies inside it."""
    return trimesh.util.concatenate(wall_and_floor() + [box((0.8, 0.6, 0.04), (0.0, 1.2, 0.74))])


@pytest.fixture(scope="module")
def block():
    mesh = slatted_scene(slats=False)
    train, held = frames(mesh, 16), frames(mesh, 15, heldout=True, noisy=False)
    return held, mapped(train, SETTINGS)


OLD = dataclasses.replace(SETTINGS, voxels=dataclasses.replace(SETTINGS.voxels, prior_retry=False, prior_clamp=0.0),
                          render=dataclasses.replace(SETTINGS.render, min_weight=1e-6, fallback_step=0.0))


def test_priors_are_retried_until_set(scene, fixed):
    """One try at allocation leaves most priors by the slats unset; retrying in later frames sets them."""
    once = mapped(scene[0], dataclasses.replace(SETTINGS, voxels=dataclasses.replace(SETTINGS.voxels,
                                                                                      prior_retry=False)))
    set_once, set_retried = once.voxels.prior_set.mean(), fixed.voxels.prior_set.mean()
    assert set_retried > set_once + 0.15, (set_once, set_retried)
    unset_voxels = (~fixed.voxels.prior_set[fixed.voxels.voxel_vertices]).all(1).mean()
    assert unset_voxels < 0.25


def test_no_halo_around_a_solid_object(block):
    """The silhouette of a block in front of a wall renders where it is: few held-out pixels more
    than 5 cm in front of the true depth. With the old priors and renderer (one try, no truncation,
    any weight taken as a surface) the same scene has a halo (measured 4.8 % vs 1.3 %)."""
    held, m = block
    assert front_share(m, held) < 0.025
    old_m = mapped(frames(slatted_scene(slats=False), 16), OLD)
    assert front_share(old_m, held) > 0.035


def test_the_near_side_of_depth_edges_is_left_out(block):
    """Structured-light depth spills the block's depth 3 px past its outline onto the wall (the
    outermost pixels half-way between: flying pixels). Mapped as measured, the spill is a rim in
    front of the wall around the block; without the near side of every depth edge
    (``mapper.edge_radius`` 2) the rim goes and the block's own silhouette stays."""
    held, _ = block
    train = frames(slatted_scene(slats=False), 16, spill=3)
    cleaned = mapped(train, SETTINGS)
    as_measured = mapped(train, dataclasses.replace(SETTINGS, mapper=dataclasses.replace(SETTINGS.mapper,
                                                                                         edge_radius=0)))
    front, front_raw = front_share(cleaned, held), front_share(as_measured, held)
    assert front < 0.5 * front_raw, (front, front_raw)  # measured 1.3 % vs 6.7 %
    behind = error_share(cleaned, held, "behind_share")
    assert behind < 0.02, behind  # the block itself is not eroded away


def test_renderer_needs_weight_and_falls_back_to_the_field(block):
    """On one map: a renderer that takes a window without weight as a surface puts more pixels in
    front of the surface; without the full-SDF fallback, rays whose surface the prior misses
    render empty."""
    held, m = block
    good = front_share(m, held)
    loose = front_share(m, held, dataclasses.replace(m.settings.render, min_weight=1e-6, fallback_step=0.0))
    assert loose > good + 0.005, (good, loose)
    view = m.view()
    view.render_cfg = dataclasses.replace(m.settings.render, fallback_step=0.0)
    f = held[7]
    holes = depth_error_shares(view.render(f.intrinsics, f.pose)[1], f.depth)["missing_share"]
    filled = depth_error_shares(m.render(f.intrinsics, f.pose)[1], f.depth)["missing_share"]
    assert filled <= holes and filled < 0.005


def test_a_steep_field_renders_where_it_crosses_zero(block):
    """The same surfaces with the field three times as steep (priors and residual scaled: the zero
    set is unchanged) render at the same depth. A renderer that needs rendering weight in a fine
    window misses every crossing that falls between two 1 cm samples (the 2.5 mm kernel sits
    between them), marches on and renders the wall behind the block (Replica's chair seats: 1.4 %
    of a view's pixels rendered through them); the window's zero crossing is a surface."""
    import torch

    held, m = block
    view = m.view().frozen()
    with torch.no_grad():
        view.voxels.priors.mul_(3.0)
        view.field.sdf_mlp[-1].weight.mul_(3.0)
        view.field.sdf_mlp[-1].bias.mul_(3.0)

    def behind(render: RenderConfig) -> float:
        view.render_cfg = render
        return float(np.mean([depth_error_shares(view.render(f.intrinsics, f.pose)[1], f.depth)["behind_share"]
                              for f in held[3:12:2]]))

    base = error_share(m, held, "behind_share")
    steep = behind(m.settings.render)
    weights_only = behind(dataclasses.replace(m.settings.render, window_crossing=False))
    assert steep < base + 0.005, (base, steep)  # measured 0.13 % and 0.22 %
    assert weights_only > base + 0.03, (base, weights_only)  # measured 6.0 %


@pytest.fixture(scope="module")
def table():
    mesh = table_scene()
    return frames(mesh, 15, heldout=True, noisy=False), mapped(frames(mesh, 16), SETTINGS)


def test_renderer_finds_the_surface_the_residual_carries(table):
    """A thin table top's front face lies where the priors have no crossing: a renderer that follows
    the priors' first crossing sees through it to the floor (measured 4.2 % of held-out pixels more
    than 5 cm behind the true depth); searching the full SDF in front of that crossing renders it
    (2.2 % at the default 1 cm step; most of the rest is the field's own hole at the face: 1.9 %
    remain at 5 mm)."""
    held, m = table
    held = held[3:12:2]
    view = m.view()

    def behind(field_step: float) -> float:
        view.render_cfg = dataclasses.replace(m.settings.render, field_step=field_step)
        return float(np.mean([depth_error_shares(view.render(f.intrinsics, f.pose)[1], f.depth)["behind_share"]
                              for f in held]))

    searched, prior_only = behind(m.settings.render.field_step), behind(0.0)
    assert prior_only > 0.03, prior_only
    assert searched < 0.75 * prior_only, (searched, prior_only)


def test_no_surface_falls_between_the_field_search_and_the_window(table):
    """The renderer finds the field's first crossing wherever it lies: the full-SDF search in
    front of a fine window used to stop one sample short of the window (a crossing between them was
    stepped over), and a window without a surface sent its ray to the next prior crossing past
    whatever the field carried in between. Rays rendered > 2 cm behind the field's first crossing
    (or not at all): measured 2.4 % of a held-out view's rays before, 0.2 % after; on a
    Replica map the fix is worth +0.74 dB held-out PSNR (research/silhouettes.md)."""
    from benchmarks.silhouettes import dense_crossings
    from h3edge.geometry.camera import pixel_rays_world
    from h3edge.mapping.raymarch import render_rays

    held, m = table
    f = held[7]
    origin, dirs = pixel_rays_world(f.intrinsics, np.asarray(f.pose, np.float64))
    dirs = dirs[::3, ::3].reshape(-1, 3)
    first = dense_crossings(m.field, m.voxels, origin, dirs, 0.05, 3.5, step=0.004)[0]
    _, depth = render_rays(m.field, m.voxels, origin, dirs, m.settings.render)
    has = first > 0
    assert has.mean() > 0.9
    passed = np.mean(has & ((depth > first + 0.02) | (depth == 0)))
    assert passed < 0.008, passed


def board_views(n: int) -> tuple[trimesh.Trimesh, list[Frame]]:
    """A 2 cm thick board (40 x 60 cm) 1 m in front of the wall, and ``n`` noise-free views on an
    arc from 60 degrees left of it to 60 degrees right, 1 m away."""
    mesh = trimesh.util.concatenate(wall_and_floor() + [box((0.4, 0.02, 0.6), (0.05, 1.01, 0.9))])
    caster = MeshRaycaster(mesh.vertices, mesh.faces)
    out = []
    for i in range(n):
        a = np.deg2rad(-60 + 120 * i / (n - 1))
        pose = look_at(np.array([0.05 + np.sin(a), 1.0 - np.cos(a), 1.0]), np.array([0.05, 1.0, 0.9]))
        hits = caster.hits(INTR, pose)
        color = np.repeat(np.where(hits.prim[..., None] < 24, 200, 90).astype(np.uint8), 3, -1)
        out.append(Frame(i, i / 30, color, hits.depth.astype(np.float32), pose, INTR))
    return mesh, out


def board_probes(train: list[Frame]) -> tuple[np.ndarray, np.ndarray]:
    """Points on a 2 cm grid behind and beside the board of :func:`board_views`: those outside the
    board that some view of ``train`` saw more than 1 cm past, and those well inside the board."""
    g = np.stack(np.meshgrid(np.linspace(-0.25, 0.35, 31), np.linspace(1.0, 1.12, 7), np.linspace(0.65, 1.15, 13)),
                 -1).reshape(-1, 3)
    board = (np.abs(g[:, 0] - 0.05) <= 0.2) & (g[:, 1] <= 1.02) & (np.abs(g[:, 2] - 0.9) <= 0.3)
    seen = np.zeros(len(g), bool)
    for f in train:  # the view's depth at the pixel a point projects to lies > 1 cm beyond it
        uv, z = project(g, f.intrinsics, f.pose)
        u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (z > 0) & (u >= 0) & (u < f.intrinsics.width) & (v >= 0) & (v < f.intrinsics.height)
        d = np.zeros(len(g))
        d[ok] = f.depth[v[ok], u[ok]]
        seen |= ok & (d > z + 0.01)
    core = board & (np.abs(g[:, 0] - 0.05) <= 0.17) & (np.abs(g[:, 2] - 0.9) <= 0.27)
    return g[seen & ~board], g[core]


def sdf_at(m: MapEngine, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(full SDF, voxel id) at points (no grad)."""
    import torch

    from h3edge.mapping.raymarch import PriorLookup

    prior, vox = PriorLookup(m.voxels)(pts)
    with torch.no_grad():
        res = m.field.sdf_mlp(m.field.geo_grid(torch.from_numpy(pts.astype(np.float32))))[:, 0].numpy()
    return prior + res, vox


def test_space_most_frames_saw_through_stays_free_with_cell_votes():
    """Fine free-space votes (``votes.cell``): the band samples behind the board's face in cells
    the majority of the frames saw through take no negative target, and points drawn in those
    cells take s >= 0, so fewer of the points some view saw through read inside; the board itself
    keeps its inside."""
    from h3edge.mapping.cell_votes import VoteConfig

    _, train = board_views(16)
    seen_free, core = board_probes(train)
    base = dataclasses.replace(SETTINGS, mapper=dataclasses.replace(SETTINGS.mapper, iterations=6, edge_radius=0))

    def shares(votes: VoteConfig) -> tuple[float, float]:
        """Means over three seeds: one seed's share of core points reading outside moves by
        +0.01..+0.07 between samplers of the same distribution (the core's points lie on the
        board's faces, 1 cm from its middle)."""
        out = []
        for seed in range(3):
            m = mapped(train, dataclasses.replace(base, votes=votes,
                                                  mapper=dataclasses.replace(base.mapper, seed=seed)))
            f, vox = sdf_at(m, seen_free)
            b, _ = sdf_at(m, core)
            out.append((np.mean(f[vox >= 0] < 0), np.mean(b > 0)))
        return tuple(float(x) for x in np.mean(out, 0))

    # measured: phantom 0.48 -> 0.32, holes 0.10 -> 0.14 (seeds 0-2)
    (phantom_off, holes_off), (phantom, holes) = shares(VoteConfig()), shares(VoteConfig(cell=0.01, points=4096))
    assert phantom < 0.75 * phantom_off, (phantom_off, phantom)
    assert holes < holes_off + 0.06, (holes_off, holes)


def test_mesh_leaves_out_unobserved_cubes(block):
    """Fewer mesh samples far (> 5 cm) from the true surface with the support rule, little lost."""
    from h3edge.eval.metrics import mesh_to_mesh

    _, m = block
    truth = slatted_scene(slats=False)
    view = m.view()
    assert view.mesh_min_support == m.settings.mapper.mesh_min_support > 0
    kept = mesh_to_mesh(view.mesh(color=False), truth, n=50_000)
    view.mesh_min_support = 0.0
    every = mesh_to_mesh(view.mesh(color=False), truth, n=50_000)
    assert kept["a_to_b_far_share"] < 0.7 * every["a_to_b_far_share"], (kept, every)
    assert kept["a_to_b_mean"] < every["a_to_b_mean"]


@pytest.mark.xfail(strict=True, reason="open (issue 15): the band's negative SDF targets behind the slats fill the "
                   "3 cm gaps at this test's 32 training steps (sdf_behind = 0 opens them, and costs the real set "
                   "its pixels behind; the cell votes open them at 384 steps: "
                   "test_slat_gaps_open_with_cell_votes_given_the_steps; research/silhouettes.md)")
def test_slat_gaps_are_seen_through(scene, fixed):
    """Pixels between the slats render at the wall, not at the slats (no fused blob), at least as
    many as TSDF fusion at 1 cm on the same 16 frames opens (measured 0.47-0.51 in views 5, 7, 9)."""
    assert gap_pixels_at_wall(fixed, scene[1][7]) > 0.45


def test_slat_gaps_open_with_cell_votes_given_the_steps(scene):
    """The fix for the filled gaps that keeps the real set's targets behind: fine free-space votes
    (``votes.*``, x86-cpu's) take the band's negative targets away only in cells most frames saw
    through. At the same budget, 24 iterations a frame (384 steps), the gaps open with them and stay
    filled without (measured over views 5 / 7 / 9: 0.42-0.48 against 0.06; TSDF 0.47-0.51), and the
    slats stay (0.98-0.99 of their pixels within 5 cm). At the strict test's 32 steps they do not
    yet (0.01)."""
    from h3edge.mapping.cell_votes import VoteConfig

    steps = dataclasses.replace(SETTINGS, mapper=dataclasses.replace(SETTINGS.mapper, iterations=24))
    votes = mapped(scene[0], dataclasses.replace(steps, votes=VoteConfig(cell=0.01, min_votes=2, points=4096)))
    without = mapped(scene[0], steps)
    opened, filled = gap_pixels_at_wall(votes, scene[1][7]), gap_pixels_at_wall(without, scene[1][7])
    assert opened > 0.3, opened
    assert filled < 0.15, filled
    assert slat_pixels_at_slats(votes, scene[1][7]) > 0.95


def test_slat_gaps_open_without_sdf_targets_behind_the_depth(scene, fixed):
    """The cause of the filled gaps above, pinned: the slat rays' negative SDF targets behind their
    measured depth. Without them (``train.sdf_behind = 0``) the same training opens the gaps
    (measured 0 % -> 93 % of the pixels between the slats at the wall); the real set needs the
    targets (its pixels behind 1.7 -> 6.8 % at 1 cm, research/silhouettes.md)."""
    none_behind = mapped(scene[0], dataclasses.replace(SETTINGS, train=dataclasses.replace(SETTINGS.train,
                                                                                          sdf_behind=0.0)))
    opened, filled = gap_pixels_at_wall(none_behind, scene[1][7]), gap_pixels_at_wall(fixed, scene[1][7])
    assert opened > 0.8, opened
    assert filled < 0.2, filled


def gap_pixels_at_wall(m: MapEngine, f: Frame) -> float:
    """Share of the held-out view's pixels that see the wall between two slats (their ray crosses
    the slats' front plane between the slats' bottom and top) and render within 5 cm of it. The
    wall below and above the slats is left out: it is no gap (every map renders it)."""
    return slat_band_rendered_within_5cm(m, f, f.depth > 1.9)


def slat_pixels_at_slats(m: MapEngine, f: Frame) -> float:
    """Share of the held-out view's slat pixels (measured nearer than 1.5 m, their ray crossing the
    slats' front plane between the slats' bottom and top) that render within 5 cm of it."""
    return slat_band_rendered_within_5cm(m, f, (f.depth > 0) & (f.depth < 1.5))


def slat_band_rendered_within_5cm(m: MapEngine, f: Frame, measured: np.ndarray) -> float:
    """Share of the pixels of ``measured`` (a mask on ``f``'s depth) in the view's middle 120
    columns whose ray crosses the slats' front plane (y = 1.19) between the slats' bottom and top,
    that the map renders within 5 cm of the measured depth."""
    _, depth = m.render(f.intrinsics, f.pose)
    k = f.intrinsics
    rows, cols = np.nonzero(measured & (np.abs(np.arange(f.depth.shape[1]) - f.depth.shape[1] / 2) < 60)[None])
    rays = np.stack([(cols + 0.5 - k.cx) / k.fx, (rows + 0.5 - k.cy) / k.fy, np.ones(len(cols))], 1) @ f.pose[:3, :3].T
    z = f.pose[2, 3] + (1.19 - f.pose[1, 3]) / rays[:, 1] * rays[:, 2]  # height where the ray crosses y = 1.19
    band = (z > 0.6) & (z < 1.2)
    return float(np.mean(np.abs(depth[rows[band], cols[band]] - f.depth[rows[band], cols[band]]) < 0.05))


def test_the_fixes_ship():
    """The renderer's fixes are the defaults; the departures from the paper these tests check are
    on in every device profile (tests.helpers.SHIPPED_FIXES, D0-2..D0-7)."""
    from h3edge.config import load_profile

    assert RenderConfig().min_weight >= 0.01 and RenderConfig().fallback_step > 0 and RenderConfig().field_step > 0
    assert RenderConfig().window_crossing and VoxelConfig().prior_retry
    for name in ("x86-cpu", "orin-agx", "orin-nx", "orin-nano"):
        mapping = load_profile(name).mapping
        for table, values in SHIPPED_FIXES.items():
            assert {k: getattr(getattr(mapping, table), k) for k in values} == values, (name, table)
