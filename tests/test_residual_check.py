"""The residual check (:mod:`h3edge.mapping.residual_check`): the gain on the colour residual over
the base, scored on fresh frames' pixels before the base fuses them, and what renders apply."""

import numpy as np
import pytest
import torch

from h3edge.geometry.camera import Intrinsics, backproject, look_at
from h3edge.mapping.color_base import ColorBase, ColorBaseConfig, compose
from h3edge.mapping.residual_check import (
    GAINS,
    MIN_SAMPLES,
    PROBE_PIXELS,
    RESERVOIR,
    ResidualCheck,
    ResidualProbe,
    take_probe,
)

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


def _scored(check: ResidualCheck, field) -> float:
    return check.score(field, torch.zeros(len(check.points()), dtype=torch.long))


@pytest.mark.parametrize("target, expected", [(0.4, 0.0), (0.8, 1.0), (0.6, None)])
def test_the_gain_is_the_one_whose_composition_the_kept_pixels_confirm(target, expected):
    """The field's residual brightens a grey base 0.4 to 0.8: kept pixels at 0.4 confirm none of it,
    at 0.8 all of it, at 0.6 part of it; the gain stays 1 until enough pixels are kept."""
    check, field = ResidualCheck(), _ConstantField(0.8)
    check.add(_probe(PROBE_PIXELS, 0.4, target))
    assert len(check.points()) < MIN_SAMPLES and _scored(check, field) == 1.0
    for _ in range(3):
        check.add(_probe(PROBE_PIXELS, 0.4, target))
    if expected is None:  # the gain whose composition lies nearest 0.6 in colour
        colours = [float(compose(torch.tensor([[0.8]]), torch.tensor([[0.4]]), torch.tensor([True]),
                                 torch.tensor([[0.5]]), g)) for g in GAINS]
        expected = GAINS[int(np.argmin(np.abs(np.array(colours) - target)))]
        assert 0.0 < expected < 1.0
    assert _scored(check, field) == expected and check.gain == expected
    # the MLP as it stands is scored: once it reads the pixels' colour, all of its residual counts
    assert _scored(check, _ConstantField(target if target > 0.4 else 0.4)) == (1.0 if target > 0.4 else 0.0)


def test_the_kept_probes_are_an_even_sample_of_every_probe_offered():
    check = ResidualCheck(seed=3)
    for i in range(10 * RESERVOIR):
        check.add(_probe(4, 0.5, i))  # the target tells the probe apart
    kept = np.array([p.target[0, 0] for p in check.probes])
    assert len(kept) == RESERVOIR and check.seen == 10 * RESERVOIR
    assert kept.min() < 2 * RESERVOIR and kept.max() > 8 * RESERVOIR  # from the whole run, not its end
    assert 3 * RESERVOIR < np.median(kept) < 7 * RESERVOIR


def test_probes_replaced_while_a_scoring_runs_leave_it_to_the_probes_it_located():
    """Integration may replace a kept probe between the training thread locating the kept points
    (under the map lock) and scoring them (outside it): the scoring reads the probes it located."""
    check, field = ResidualCheck(), _ConstantField(0.8)
    for _ in range(RESERVOIR):
        check.add(_probe(PROBE_PIXELS, 0.4, 0.4))
    located = list(check.probes)
    for _ in range(4 * RESERVOIR):
        check.add(_probe(7, 0.4, 0.8))  # other sizes, other colours
    assert len(check.points()) != len(located) * PROBE_PIXELS
    vox = torch.zeros(len(located) * PROBE_PIXELS, dtype=torch.long)
    assert check.score(field, vox, located) == 0.0  # the located probes' verdict


def test_points_outside_the_map_are_not_scored_and_the_state_round_trips():
    check, field = ResidualCheck(), _ConstantField(0.8)
    for _ in range(4):
        check.add(_probe(PROBE_PIXELS, 0.4, 0.4))
    assert check.score(field, torch.full((4 * PROBE_PIXELS,), -1, dtype=torch.long)) == 1.0 and check.scored == 0
    assert _scored(check, field) == 0.0
    again = ResidualCheck()
    again.load_state_dict(*check.state_dict())
    assert again.gain == 0.0 and np.array_equal(again.points(), check.points()) and again.seen == 4
    assert np.array_equal(again.state_dict()[1]["base"], check.state_dict()[1]["base"])
    meta, arrays = check.state_dict()
    with pytest.raises(ValueError):
        again.load_state_dict(dict(meta, gain=0.3), arrays)
    with pytest.raises(ValueError):
        again.load_state_dict(meta, dict(arrays, target=arrays["target"][:-1]))
    with pytest.raises(ValueError):  # malformed: refused as such, the check unchanged
        again.load_state_dict(dict(meta, rng="not a state"), arrays)
    with pytest.raises(ValueError):
        again.load_state_dict({k: v for k, v in meta.items() if k != "seen"}, arrays)
    assert again.gain == 0.0 and again.seen == 4


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


def test_a_map_scores_the_frames_no_step_fits_and_renders_at_the_gain_it_keeps(tiny_scene, monkeypatch):
    """Mapped with training between frames, the map keeps probes of the frames that are not
    keyframes, scores them and keeps a gain of GAINS; a render with ``render.checked_residual``
    applies it, the residual as trained renders otherwise, and the check is saved with the map."""
    import dataclasses

    from h3edge.io.replica import ReplicaSequence
    from h3edge.mapping import engine
    from h3edge.mapping.engine import MapEngine, MapperConfig, MapSettings
    from h3edge.mapping.keyframes import KeyframeConfig
    from h3edge.mapping.raymarch import RenderConfig
    from h3edge.mapping.voxels import VoxelConfig

    monkeypatch.setattr(engine, "PROBE_EVERY", 1)  # every frame leaves a probe (a short sequence)
    seq = ReplicaSequence(tiny_scene)
    st = MapSettings(mapper=MapperConfig(device="cpu", train_between_frames=True), voxels=VoxelConfig(min_points=3),
                     keyframes=KeyframeConfig(insert_iou=0.0, max_interval=4),  # a keyframe every 4th frame
                     color_base=ColorBaseConfig(cell=0.02), render=RenderConfig(checked_residual=True))
    m = MapEngine(st)
    keyframes = 0
    for i in range(15):
        result = m.integrate(seq[i])
        assert result.mapped
        keyframes += result.keyframe
        m.train_between_frames()
    check = m.residual_check
    assert check.seen == len(check.probes) == 15 - keyframes  # the first frame's, a keyframe's, none
    assert check.scored >= 1 and m.field.residual_gain == check.gain in GAINS
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
    assert r.field.residual_gain == m.field.residual_gain and r.residual_check.seen == check.seen
    assert np.array_equal(r.residual_check.points(), check.points())
