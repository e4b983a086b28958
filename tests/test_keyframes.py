"""Keyframe insertion rules, greedy coverage selection, round reset and adaptive pruning."""

import numpy as np
import pytest

from h3edge.mapping.keyframes import KeyframeConfig, KeyframeSet


def ids(*r):
    return np.arange(*r)


def test_insertion_rules():
    ks = KeyframeSet(KeyframeConfig(insert_iou=0.85, max_interval=10))
    assert ks.should_insert(ids(0, 100))
    ks.insert(0, ids(0, 100))
    assert not ks.should_insert(ids(0, 95))  # IoU 0.95
    assert ks.should_insert(ids(20, 120))  # IoU 80/120 = 0.67
    ks2 = KeyframeSet(KeyframeConfig(max_interval=10))
    ks2.insert(0, ids(0, 100))
    decisions = [ks2.should_insert(ids(0, 100)) for _ in range(10)]
    assert decisions == [False] * 9 + [True]  # the 10th frame since the last keyframe


def test_greedy_coverage_and_persistence():
    ks = KeyframeSet(KeyframeConfig(per_iteration=2, adaptive_pruning=False))
    ks.insert(0, ids(0, 10))
    ks.insert(1, ids(5, 30))  # largest
    ks.insert(2, ids(28, 40))
    ks.insert(3, ids(40, 44))
    first = [k.frame_id for k in ks.select()]
    assert first == [1, 2]  # 25 voxels, then 10 new ones (38, 39 are new; 28, 29 covered)
    second = [k.frame_id for k in ks.select()]
    assert second == [0, 3]  # only the unobserved remain: 0..4 and 40..43
    assert ks.observed[:44].all()
    third = [k.frame_id for k in ks.select()]  # round over: reset, start again
    assert third == [1, 2]


def test_scores_steer_selection():
    ks = KeyframeSet(KeyframeConfig(per_iteration=1))
    ks.insert(0, ids(0, 20))  # many weak-texture voxels
    ks.insert(1, ids(20, 25), scores=np.full(5, 10.0))  # few rich-texture voxels seen close up
    assert ks.select()[0].frame_id == 1


def test_adaptive_pruning_removes_unselected():
    ks = KeyframeSet(KeyframeConfig(per_iteration=1, adaptive_pruning=True))
    ks.insert(0, ids(0, 10))
    ks.insert(1, ids(0, 5))  # redundant: fully covered by frame 0
    ks.insert(2, ids(10, 12))
    assert [k.frame_id for k in ks.select()] == [0]
    assert [k.frame_id for k in ks.select()] == [2]
    ks.select()  # all observed: the round ends; frame 1 was never selected -> pruned
    assert [k.frame_id for k in ks.keyframes] == [0, 2] and ks.pruned == 1


def test_last_keyframe_survives_pruning():
    ks = KeyframeSet(KeyframeConfig(per_iteration=1))
    ks.insert(0, ids(0, 10))
    ks.insert(1, ids(0, 3))
    ks.select()
    ks.select()
    assert [k.frame_id for k in ks.keyframes] == [0, 1]


def test_scores_must_match():
    with pytest.raises(ValueError):
        KeyframeSet().insert(0, ids(0, 3), scores=np.ones(2))


def test_cap_evicts_least_informative_never_newest():
    from h3edge.mapping.keyframes import KeyframeConfig, KeyframeSet

    ks = KeyframeSet(KeyframeConfig(max_keyframes=3))
    for i, score in enumerate([5.0, 1.0, 9.0, 0.5]):
        ks.insert(i, np.arange(4) + i, np.full(4, score))
    assert [k.frame_id for k in ks.keyframes] == [0, 2, 3]  # frame 1 (total 4) evicted; 3 is newest
    ks.insert(4, np.arange(4), np.full(4, 0.1))
    assert [k.frame_id for k in ks.keyframes] == [0, 2, 4] and ks.evicted == 2


def test_repeated_frame_ids_do_not_break_selection():
    """Frame ids come from the publisher and may repeat; keyframes compare by identity."""
    from h3edge.mapping.keyframes import KeyframeConfig, KeyframeSet

    ks = KeyframeSet(KeyframeConfig(per_iteration=3))
    ks.insert(1, np.arange(5), np.ones(5))
    ks.insert(1, np.arange(3, 12), np.ones(9))
    chosen = ks.select()
    assert len(chosen) == 2


def _stored(h: int = 30, w: int = 40, seed: int = 0):
    from h3edge.geometry.camera import Intrinsics
    from h3edge.mapping.keyframes import StoredFrame

    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.3, 7.0, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.7] = 0  # 70 % invalid, as at a Kinect's worst
    color = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    intr = Intrinsics(w, h, 30.0, 30.0, w / 2, h / 2)
    return StoredFrame.of(color, depth, np.eye(4), intr), color, depth


def test_byte_cap_evicts_least_informative_never_newest():
    kf, _, _ = _stored()
    ks = KeyframeSet(KeyframeConfig(max_bytes=3 * kf.nbytes))
    for i, score in enumerate([5.0, 1.0, 9.0, 0.5]):
        ks.insert(i, np.arange(4) + i, np.full(4, score), payload=_stored(seed=i)[0])
    assert [k.frame_id for k in ks.keyframes] == [0, 2, 3] and ks.evicted == 1


def test_stored_frame_draws_every_valid_pixel_and_only_those():
    """A keyframe trains on its whole view: over many draws every valid pixel comes up, uniformly,
    with its own colour and depth (a subset stored once would leave the rest of the view unseen by
    every later iteration: on real data the texture over-fits it, research/continuous_training.md)."""
    kf, color, depth = _stored()
    valid = np.flatnonzero(depth.reshape(-1) > 0)
    assert kf.n_valid == len(valid)
    rng = np.random.default_rng(1)
    pix, rgb, z = kf.draw(200 * len(valid), rng)
    assert len(pix) == len(rgb) == len(z) == 200 * len(valid)
    assert np.isin(pix, valid).all()
    counts = np.bincount(pix, minlength=depth.size)[valid]
    assert counts.min() > 0 and counts.std() / counts.mean() < 0.15  # uniform: Poisson spread ~ 1/sqrt(200)
    assert np.array_equal(rgb, color.reshape(-1, 3)[pix])
    assert np.abs(z - depth.reshape(-1)[pix]).max() <= kf.depth_unit / 2 + 1e-6
    assert kf.depth_unit <= 7.0 / 65535 + 1e-9
    assert len(kf.draw(0, rng)[0]) == 0


def test_stored_frame_without_depth_draws_nothing():
    from h3edge.geometry.camera import Intrinsics
    from h3edge.mapping.keyframes import StoredFrame

    kf = StoredFrame.of(np.zeros((4, 5, 3), np.uint8), np.zeros((4, 5), np.float32), np.eye(4),
                        Intrinsics(5, 4, 5.0, 5.0, 2.5, 2.0))
    assert kf.n_valid == 0 and len(kf.draw(10, np.random.default_rng(0))[0]) == 0


@pytest.mark.parametrize("quantised", [True, False])
def test_device_frame_draws_as_the_host_does_without_a_host_transfer(quantised):
    """The torch backend's ray draw (h3edge.mapping.device_frames): a keyframe's images kept on the
    device draw every valid pixel, uniformly, and only those (a frame whose pixel count is not a
    multiple of the chunk, valid pixels last and first too); each with the colour, depth and ray
    the host path gives it; no host transfer."""
    import torch

    from h3edge.geometry.camera import pixel_rays_camera
    from h3edge.mapping.device_frames import CHUNK, DeviceFrame
    from h3edge.profiling.host_transfers import HostTransfers

    kf, color, depth = _stored()
    flat = depth.reshape(-1).copy()
    flat[:3] = 0.0
    flat[-1] = 1.25  # the padded chunk's last pixel valid
    depth = flat.reshape(depth.shape)
    from h3edge.mapping.keyframes import StoredFrame

    a = 0.7
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    pose[:3, 3] = [1.0, -2.0, 0.5]
    kf = StoredFrame.of(color, depth, pose, kf.intrinsics)
    assert depth.size % CHUNK  # the last chunk is padded
    dev = torch.device("cpu")
    if quantised:
        df = DeviceFrame.upload(kf.color, kf.depth_q, kf.depth_unit, kf.n_valid, kf.pose, kf.intrinsics, dev)
    else:  # as integration leaves it (a NaN is not valid depth either)
        depth.reshape(-1)[np.flatnonzero(depth.reshape(-1) > 0)[5]] = np.nan
        df = DeviceFrame.upload(color, depth, 0.0, int((depth > 0).sum()), kf.pose, kf.intrinsics, dev)
    valid = np.flatnonzero(depth.reshape(-1) > 0)
    g = torch.Generator().manual_seed(3)
    with HostTransfers() as ht:
        pix = df.draw(200 * len(valid), g)
        o, d, z, c = df.rays(pix)
    assert ht.total == 0 and ht.syncs == 0
    pix = pix.numpy()
    assert np.isin(pix, valid).all()
    counts = np.bincount(pix, minlength=depth.size)[valid]
    assert counts.min() > 0 and counts.std() / counts.mean() < 0.15  # uniform, the last pixel too
    hp, hrgb, hz = kf.at(pix)
    assert np.allclose(c.numpy() * 255.0, hrgb) and np.allclose(z.numpy(), hz if quantised else depth.reshape(-1)[pix])
    rot = kf.pose[:3, :3].T.astype(np.float32)
    assert np.allclose(d.numpy(), pixel_rays_camera(kf.intrinsics).reshape(-1, 3)[pix] @ rot, atol=1e-5)
    assert np.allclose(o.numpy(), kf.pose[:3, 3])
    none = DeviceFrame.upload(color, np.zeros_like(depth), 0.0, 0, kf.pose, kf.intrinsics, dev)
    assert len(none.draw(10, g)) == 0 and len(df.draw(0, g)) == 0


def test_the_memory_plan_counts_a_keyframes_copy_on_the_device():
    """On the torch backend a keyframe's images are also kept where training draws its rays: on a
    GPU its RGB and depth (5 bytes a pixel) and valid-pixel counts (8 bytes a 32-pixel chunk), on a
    CPU (shared arrays) the counts only (``auto`` counts as a GPU: at most); the numba backend keeps
    none."""
    import dataclasses

    from h3edge.mapping.engine import MapSettings
    from h3edge.mapping.memory_plan import keyframe_bytes

    s = MapSettings()
    on_cpu = dataclasses.replace(s, field=dataclasses.replace(s.field, backend="torch"),
                                 mapper=dataclasses.replace(s.mapper, device="cpu"))
    on_gpu = dataclasses.replace(on_cpu, mapper=dataclasses.replace(s.mapper, device="cuda"))
    px = 640 * 480
    assert keyframe_bytes(on_cpu, px) - keyframe_bytes(s, px) == px // 32 * 8
    assert keyframe_bytes(on_gpu, px) - keyframe_bytes(s, px) == px * 5 + px // 32 * 8
