"""Training between frames: the mapper's keyframe-only iteration, the offline live replay at a
camera rate (queue overflow skips, training while no frame waits, settling) and the service's
training rate in ``status``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from h3edge.apps.offline import map_sequence
from h3edge.eval.metrics import psnr
from h3edge.io.replica import ReplicaSequence
from h3edge.mapping.field import FieldConfig
from h3edge.mapping.mapper import Mapper, MapperConfig, MapSettings
from h3edge.mapping.voxels import VoxelConfig

LEAN = MapSettings(mapper=MapperConfig(device="cpu", rays_per_iteration=512, mesh_resolution=2),
                   voxels=VoxelConfig(min_points=3), field=FieldConfig(sdf_layers=2, geo_log2_table=14,
                                                                      tex_log2_table=14))


class FakeClock:
    """Wall time that advances only when asked: ``step`` per reading, plus explicit sleeps."""

    def __init__(self, step: float):
        self.t, self.step = 0.0, step

    def __call__(self) -> float:
        self.t += self.step
        return self.t

    def sleep(self, s: float) -> None:
        self.t += max(s, 1e-3)


def test_nothing_to_train_on_before_a_keyframe_or_when_turned_off(tiny_scene):
    m = Mapper(LEAN)
    assert m.train_between_frames() is None  # no field, no keyframes
    off = Mapper(dataclasses.replace(LEAN, mapper=dataclasses.replace(LEAN.mapper, train_between_frames=False)))
    seq = ReplicaSequence(tiny_scene)
    off.process(seq[0])
    assert off.train_between_frames() is None and off.iterations["between_frames"] == 0


def test_training_between_frames_improves_the_map(tiny_scene):
    """Same frames, same fixed iterations per frame; extra keyframe iterations between frames give a
    better held-out render, are counted apart and timed as ``idle_training``."""
    seq = ReplicaSequence(tiny_scene)
    held = seq.heldout[len(seq.heldout) // 2]
    scores = {}
    for extra in (0, 4):
        m = Mapper(LEAN)
        for f in seq:
            m.process(f)
            for _ in range(extra):
                assert m.train_between_frames() is not None
        assert m.iterations == {"frame": len(seq) * LEAN.mapper.iterations, "between_frames": extra * len(seq)}
        rgb, _ = m.render(held.intrinsics, held.pose)
        scores[extra] = psnr(rgb, held.color)
        if extra:
            assert m.timings.summary()["idle_training"]["count"] == extra * len(seq)
    assert scores[4] > scores[0] + 0.5, scores


def test_live_replay_skips_what_it_cannot_keep_up_with(tiny_scene):
    """A camera faster than the mapper: the ingest queue overflows, older frames are skipped, and the
    mapper never trains between frames (a frame is always waiting)."""
    seq = ReplicaSequence(tiny_scene)
    m = Mapper(LEAN)
    clock = FakeClock(step=0.05)  # ~4 clock reads per frame: a frame takes ~0.2 s of "wall time"
    results = map_sequence(seq, m, camera_hz=50.0, clock=clock, sleep=clock.sleep, progress_every=0)
    skipped = [r for r in results if r.reason == "queue_full"]
    mapped = [r for r in results if r.mapped]
    assert len(results) == len(seq) and skipped and mapped
    assert sorted(r.frame_id for r in results) == list(range(len(seq)))  # every frame accounted for once
    assert m.frames_mapped == len(mapped)
    assert results[-1].mapped  # the newest frame is never the one skipped


def test_live_replay_trains_while_the_camera_is_slow_and_settles(tiny_scene):
    seq = ReplicaSequence(tiny_scene)
    m = Mapper(LEAN)
    clock = FakeClock(step=0.01)
    results = map_sequence(seq, m, frames=6, camera_hz=2.0, settle_s=0.5, clock=clock, sleep=clock.sleep,
                           progress_every=0)
    assert [r.mapped for r in results] == [True] * 6  # a slow camera: nothing skipped
    assert m.iterations["between_frames"] > 6  # trained between every pair of frames and after the last
    with pytest.raises(ValueError):
        map_sequence(seq, Mapper(LEAN), camera_hz=0.0)


def test_replay_counts_survive_a_checkpoint(tiny_scene):

    seq = ReplicaSequence(tiny_scene)
    m = Mapper(LEAN)
    m.process(seq[0])
    m.train_between_frames()
    meta, arrays = m.state_dict()
    r = Mapper.from_state_dict(LEAN, meta, arrays)
    assert r.iterations == m.iterations == {"frame": LEAN.mapper.iterations, "between_frames": 1}
    assert np.isfinite(r.train_between_frames()["loss"])
