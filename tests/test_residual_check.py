"""The residual check (:mod:`h3edge.mapping.residual_check`): the gain on the colour residual over
the base, scored on fresh frames' pixels before the base fuses them, and what renders apply."""

import numpy as np
import pytest
import torch

from h3edge.geometry.camera import Intrinsics, backproject, look_at
from h3edge.mapping.color_base import ColorBase, ColorBaseConfig, compose
from h3edge.mapping.residual_check import GAINS, MIN_SAMPLES, PROBE_PIXELS, ResidualCheck, ResidualProbe, take_probe

INTR = Intrinsics(64, 48, 40.0, 40.0, 32.0, 24.0)
FRONT = look_at(np.zeros(3), np.array([0.0, 1.0, 0.0]))  # looking along +y at a wall 2 m away
WALL = np.full((INTR.height, INTR.width), 2.0, np.float32)


def test_compose_applies_the_gain_to_the_residual_in_logit_space():
    base = torch.tensor([[0.2, 0.5, 0.9]])
    field, neutral, known = torch.tensor([[0.8, 0.3, 0.6]]), torch.tensor([[0.45, 0.5, 0.55]]), torch.tensor([True])
    full = compose(field, base, known, neutral)
    assert torch.allclose(compose(field, base, known, neutral, 0.0), base, atol=1e-6)  # the base alone
    # gain 1 through the logit form reads what the odds form reads
    lg = torch.logit
    assert torch.allclose(torch.sigmoid(lg(base) + lg(field) - lg(neutral)), full, atol=1e-5)
    half = compose(field, base, known, neutral, 0.5)
    assert torch.allclose(lg(half), (lg(base) + lg(full)) / 2, atol=1e-4)
    # where the base knows nothing the field's colour stands, whatever the gain
    assert torch.equal(compose(field, base, torch.tensor([False]), neutral, 0.0), field)


class _ConstantField:
    """A stand-in colour field: one colour everywhere, neutral 0.5."""

    def __init__(self, rgb: float):
        self.rgb = rgb

    def color_field(self, points, voxel_index):
        return torch.full((len(points), 3), self.rgb), torch.full((1, 3), 0.5)


def _probe(n: int, base: float, target: float) -> ResidualProbe:
    pts = np.zeros((n, 3), np.float32)
    return ResidualProbe(pts, np.full((n, 3), target, np.float32), np.full((n, 3), base, np.float32))


@pytest.mark.parametrize("target, expected", [(0.4, 0.0), (0.8, 1.0), (0.6, None)])
def test_the_gain_is_the_one_whose_composition_fresh_pixels_confirm(target, expected):
    """The field's residual brightens a grey base 0.4 to 0.8: fresh pixels at 0.4 confirm none of it,
    at 0.8 all of it, at 0.6 part of it; the gain stays 1 until enough pixels have been scored."""
    check, field = ResidualCheck(), _ConstantField(0.8)
    vox = torch.zeros(PROBE_PIXELS, dtype=torch.long)
    check.score(field, _probe(PROBE_PIXELS, 0.4, target), vox)
    assert check.samples < MIN_SAMPLES and check.gain == 1.0
    for _ in range(3):
        check.score(field, _probe(PROBE_PIXELS, 0.4, target), vox)
    if expected is None:  # the gain whose composition lies nearest 0.6 in colour
        colours = [float(compose(torch.tensor([[0.8]]), torch.tensor([[0.4]]), torch.tensor([True]),
                                 torch.tensor([[0.5]]), g)) for g in GAINS]
        expected = GAINS[int(np.argmin(np.abs(np.array(colours) - target)))]
        assert 0.0 < expected < 1.0
    assert check.gain == expected and check.probes == 4


def test_points_outside_the_map_are_not_scored_and_the_state_round_trips():
    check, field = ResidualCheck(), _ConstantField(0.8)
    check.score(field, _probe(100, 0.4, 0.4), torch.full((100,), -1, dtype=torch.long))
    assert check.probes == 0 and check.samples == 0
    for _ in range(4):
        check.score(field, _probe(PROBE_PIXELS, 0.4, 0.4), torch.zeros(PROBE_PIXELS, dtype=torch.long))
    again = ResidualCheck()
    again.load_state_dict(check.state_dict())
    assert again.gain == check.gain == 0.0 and np.array_equal(again.sse, check.sse)
    bad = dict(check.state_dict(), gain=0.3)
    with pytest.raises(ValueError):
        again.load_state_dict(bad)


def test_a_probe_reads_the_base_as_it_was_before_the_frame():
    base = ColorBase(ColorBaseConfig(cell=0.01, band=1, stride=1))
    grey = np.full((INTR.height, INTR.width, 3), 100, np.uint8)
    assert take_probe(base, grey, WALL, np.arange(WALL.size), INTR, FRONT, 0) is None  # nothing fused yet
    base.fuse(grey, WALL, INTR, FRONT)
    white = np.full_like(grey, 250)
    probe = take_probe(base, white, WALL, np.arange(WALL.size), INTR, FRONT, 5)
    assert probe is not None and 0.9 * PROBE_PIXELS < len(probe.points) <= PROBE_PIXELS  # where the base knows
    assert np.allclose(probe.base * 255, 100, atol=0.5) and np.allclose(probe.target * 255, 250)
    # at the pixels' measured surface points
    wall_pts = backproject(WALL, INTR, FRONT).reshape(-1, 3)
    assert np.abs(probe.points[:, 1] - wall_pts[0, 1]).max() < 1e-5


def test_a_map_scores_fresh_frames_and_renders_at_the_gain_it_keeps(tiny_scene):
    """Mapped with training between frames, the map scores probes and keeps a gain of GAINS; a render
    with ``render.checked_residual`` applies it, the residual as trained renders otherwise, and the
    gain is saved with the map."""
    import dataclasses

    from h3edge.io.replica import ReplicaSequence
    from h3edge.mapping.engine import MapEngine, MapperConfig, MapSettings
    from h3edge.mapping.raymarch import RenderConfig
    from h3edge.mapping.voxels import VoxelConfig

    seq = ReplicaSequence(tiny_scene)
    st = MapSettings(mapper=MapperConfig(device="cpu", train_between_frames=True), voxels=VoxelConfig(min_points=3),
                     color_base=ColorBaseConfig(cell=0.02), render=RenderConfig(checked_residual=True))
    m = MapEngine(st)
    for i in range(15):
        assert m.integrate(seq[i]).mapped
        m.train_between_frames()
    assert m.residual_check.probes >= 4 and m.field.residual_gain == m.residual_check.gain in GAINS
    f = seq.heldout[0]
    view = m.view().frozen()
    view.field.residual_gain = 0.0  # the frozen view's own copy of the field
    checked = view.render(f.intrinsics, f.pose)
    view.render_cfg = dataclasses.replace(view.render_cfg, checked_residual=False)
    as_trained = view.render(f.intrinsics, f.pose)
    assert np.array_equal(checked[1], as_trained[1]) and not np.array_equal(checked[0], as_trained[0])
    hit = checked[1] > 0  # gain 0: the base's colour where it knows one
    base, known = m.color_base.sample(torch.from_numpy(backproject(checked[1], f.intrinsics, f.pose)[hit]))
    diff = np.abs(checked[0][hit][known.numpy()] / 255.0 - base[known].numpy())
    assert np.median(diff) < 0.01
    meta, arrays = m.state_dict()
    r = MapEngine.from_state_dict(st, meta, arrays)
    assert r.field.residual_gain == m.field.residual_gain and r.residual_check.probes == m.residual_check.probes
