"""Training between frames: the mapper's keyframe-only iteration, the offline live replay at a
camera rate (queue overflow skips, training while no frame waits, settling) and the service's
training rate in ``status``."""

from __future__ import annotations

import dataclasses
import os
import threading
import time

import numba
import numpy as np
import pytest
import torch

from h3edge.apps.offline import LAST_FRAME, map_sequence
from h3edge.eval.metrics import psnr
from h3edge.io.replica import ReplicaSequence
from h3edge.mapping.engine import MapEngine, MapperConfig, MapSettings
from h3edge.mapping.field import FieldConfig
from h3edge.mapping.voxels import VoxelConfig
from tests.helpers import with_shipped_fixes

LEAN = with_shipped_fixes(MapSettings(mapper=MapperConfig(device="cpu", rays_per_iteration=512, mesh_resolution=2),
                                      voxels=VoxelConfig(min_points=3),
                                      field=FieldConfig(sdf_layers=2, geo_log2_table=14, tex_log2_table=14)))


def test_nothing_to_train_on_before_a_keyframe_or_when_turned_off(tiny_scene):
    m = MapEngine(LEAN)
    assert m.train_between_frames() is None  # no field, no keyframes
    off = MapEngine(dataclasses.replace(LEAN, mapper=dataclasses.replace(LEAN.mapper, train_between_frames=False)))
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
        m = MapEngine(LEAN)
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
    """A camera faster than integration: the ingest queue overflows, older frames are skipped, every
    frame is accounted for once and the newest one is never the one skipped."""
    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(LEAN)
    results = map_sequence(seq, m, camera_hz=2000.0, progress_every=0)
    skipped = [r for r in results if r.reason == "queue_full"]
    mapped = [r for r in results if r.mapped]
    assert len(results) == len(seq) and skipped and mapped
    assert sorted(r.frame_id for r in results) == list(range(len(seq)))
    assert m.frames_mapped == len(mapped)
    assert results[-1].mapped


def test_live_replay_integrates_every_frame_trains_apart_and_settles(tiny_scene):
    """A camera the integration keeps up with: nothing skipped, no training step inline (they run on
    the training thread, ``between_frames``), training goes on after the last frame, and a mark is
    called with the replay's time at its place, the last frame's after every frame."""
    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(LEAN)
    seen = []
    results = map_sequence(seq, m, frames=6, camera_hz=5.0, settle_s=0.6, progress_every=0,
                           marks=[("last", LAST_FRAME), ("half", 0.5)],
                           on_mark=lambda label, t, res: seen.append((label, t, len(res), m.frames_mapped)))
    assert [r.mapped for r in results] == [True] * 6
    assert m.iterations["frame"] == 0 and m.iterations["between_frames"] > 0
    assert m.timings.summary()["integration"]["count"] == 6
    (l1, t1, n1, f1), (l2, t2, n2, f2) = seen
    assert l1 == "half" and 0.5 <= t1 < 1.0 and f1 == n1 < 6
    assert l2 == "last" and t2 >= 1.0 and n2 == f2 == 6
    with pytest.raises(ValueError):
        map_sequence(seq, MapEngine(LEAN), camera_hz=0.0)


def test_inline_replay_trains_each_frame_and_between_frames(tiny_scene):
    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(LEAN)
    # 3 s of settling: the last frame's inline steps may run past a shorter one on a loaded machine
    results = map_sequence(seq, m, frames=4, camera_hz=4.0, settle_s=3.0, progress_every=0, inline=True)
    assert sorted(r.frame_id for r in results) == list(range(4)) and results[-1].mapped
    mapped = sum(r.mapped for r in results)
    assert m.iterations["frame"] == mapped * LEAN.mapper.iterations and m.iterations["between_frames"] > 0


def test_replay_counts_survive_a_checkpoint(tiny_scene):

    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(LEAN)
    m.process(seq[0])
    m.train_between_frames()
    meta, arrays = m.state_dict()
    r = MapEngine.from_state_dict(LEAN, meta, arrays)
    assert r.iterations == m.iterations == {"frame": LEAN.mapper.iterations, "between_frames": 1}
    assert np.isfinite(r.train_between_frames()["loss"])


@pytest.mark.skipif(not hasattr(os, "setpriority"), reason="per-thread nice is Linux's")
def test_the_training_thread_runs_below_integration_with_the_pools_sized(tiny_scene):
    """``training_nice`` levels below the thread that integrates (which keeps its own), and the
    training thread's numba kernels and torch run ``threads`` threads."""
    from h3edge.mapping.background import BackgroundTraining

    cfg = dataclasses.replace(LEAN.mapper, training_nice=7, threads=1)
    m = MapEngine(dataclasses.replace(LEAN, mapper=cfg))
    seq = ReplicaSequence(tiny_scene)
    mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    seen = {}

    def probe():
        seen.update(nice=os.getpriority(os.PRIO_PROCESS, threading.get_native_id()),
                    numba=numba.get_num_threads(), torch=torch.get_num_threads())

    m.step_hook = probe
    torch_before = torch.get_num_threads()
    bt = BackgroundTraining(m).start()
    try:
        for f in list(seq)[:4]:
            assert m.integrate(f).mapped
        deadline = time.monotonic() + 60
        while not seen and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        bt.stop()
        torch.set_num_threads(torch_before)  # integrate() sized this thread's pools: the suite's go on as they were
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    assert seen == {"nice": min(19, mine + 7), "numba": 1, "torch": 1}
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == mine
