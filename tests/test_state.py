"""MapEngine state round trip (what checkpoints hold), frozen query snapshots, keyframe pixel subsets."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

from h3edge.io.replica import ReplicaSequence
from h3edge.mapping.engine import MapEngine, MapperConfig, MapSettings
from h3edge.mapping.field import FieldConfig
from h3edge.mapping.voxels import VoxelConfig

SETTINGS = MapSettings(mapper=MapperConfig(device="cpu", rays_per_iteration=512, mesh_resolution=2),
                       voxels=VoxelConfig(min_points=3),
                       field=FieldConfig(sdf_layers=2, geo_log2_table=14, tex_log2_table=14))


@pytest.fixture(scope="module")
def half_mapped(tiny_scene):
    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(SETTINGS)
    for f in list(seq)[:20]:
        assert m.process(f).mapped
    return seq, m


def _params(m: MapEngine) -> dict[str, torch.Tensor]:
    out = {k: v.detach().clone() for k, v in m.field.state_dict().items()}
    out["priors"] = m.voxels.priors.detach().clone()
    return out


def _clone(m: MapEngine) -> MapEngine:
    """A deep copy of a mapper (the OpenCV line detector and numba kernels are not copyable)."""
    det, kerns = m.patterns._detector, [(g, g._kern) for g in m.field.hash_grids()]
    m.patterns._detector = None
    for g, _ in kerns:
        g._kern = None
    try:
        return copy.deepcopy(m)
    finally:
        m.patterns._detector = det
        for g, k in kerns:
            g._kern = k


def test_keyframes_keep_whole_images(half_mapped):
    seq, m = half_mapped
    kf = m.keyframes.keyframes[-1].payload
    frame = next(f for f in seq if f.index == m.keyframes.keyframes[-1].frame_id)
    h, w = kf.intrinsics.height, kf.intrinsics.width
    assert kf.color.shape == (h, w, 3) and np.array_equal(kf.color, frame.color)
    # the cleaned depth, quantised to uint16 steps of max depth / 65535
    clean = m.clean_depth(frame.depth, frame.intrinsics)
    assert np.array_equal(kf.depth > 0, clean > 0) and kf.n_valid == np.count_nonzero(clean)
    assert np.abs(kf.depth - clean).max() <= kf.depth_unit / 2 + 1e-6 < 1e-4
    assert kf.nbytes <= 5 * h * w + 2 * 8 * 16  # images, poses
    # read-only, and the captured state holds the arrays themselves (no second copy of the keyframes)
    assert not kf.color.flags.writeable and not kf.depth_q.flags.writeable
    _, arrays = m.state_dict()
    last = len(m.keyframes.keyframes) - 1
    assert arrays[f"kf/color/{last}"] is kf.color and arrays[f"kf/depth_q/{last}"] is kf.depth_q
    restored = MapEngine.from_state_dict(SETTINGS, *m.state_dict()).keyframes.keyframes[-1].payload
    assert np.array_equal(restored.color, kf.color) and np.array_equal(restored.depth_q, kf.depth_q)
    assert restored.depth_unit == kf.depth_unit and restored.n_valid == kf.n_valid


def test_restored_mapper_continues_identically(half_mapped):
    """Restore from the captured state: identical parameters; mapping goes on from there."""
    seq, m = half_mapped
    meta, arrays = m.state_dict()
    # sparse tables: far fewer rows stored than the tables hold
    assert len(arrays["grid/geo/rows"]) < len(m.field.geo_grid.table)
    r = MapEngine.from_state_dict(SETTINGS, meta, arrays)
    a, b = _params(m), _params(r)
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert r.frames_mapped == m.frames_mapped and len(r.voxels) == len(m.voxels)
    assert [k.frame_id for k in r.keyframes.keyframes] == [k.frame_id for k in m.keyframes.keyframes]
    for a_kf, b_kf in zip(m.keyframes.keyframes, r.keyframes.keyframes):
        assert np.array_equal(a_kf.payload.depth_q, b_kf.payload.depth_q)
        assert np.array_equal(a_kf.payload.color, b_kf.payload.color)
    # continue mapping from the restored state and from the original: the same map (the parallel
    # gradient scatter sums in a nondeterministic order, so "the same" is up to rounding noise)
    cont = _clone(m)
    for f in list(seq)[20:26]:
        assert r.process(f).mapped and cont.process(f).mapped
    held = seq.heldout[2]
    (_, d_r), (_, d_c) = r.render(held.intrinsics, held.pose), cont.render(held.intrinsics, held.pose)
    both = (d_r > 0) & (d_c > 0) & (held.depth > 0)
    assert both.mean() > 0.8
    assert np.median(np.abs(d_r[both] - d_c[both])) < 0.002
    assert np.median(np.abs(d_r[both] - held.depth[both])) < 0.02
    assert r.frames_mapped == 26 and not torch.equal(_params(r)["geo_grid.table"], b["geo_grid.table"])


def test_restore_refuses_other_configuration(half_mapped):
    _, m = half_mapped
    meta, arrays = m.state_dict()
    other = dataclasses.replace(SETTINGS, field=dataclasses.replace(SETTINGS.field, sdf_hidden=32))
    with pytest.raises(ValueError, match="shape"):
        MapEngine.from_state_dict(other, meta, arrays)


def test_frozen_view_is_independent(half_mapped):
    seq, m = half_mapped
    frozen = m.view().frozen()
    f = seq[5]
    before = frozen.render(f.intrinsics, f.pose)
    live_before = m.render(f.intrinsics, f.pose)
    assert np.array_equal(before[1], live_before[1])
    table = frozen.field.geo_grid.table.clone()
    scratch = _clone(m)  # train a copy, so the module fixture stays as it was
    snap = scratch.view().frozen()
    for fr in list(seq)[20:23]:
        scratch.process(fr)
    assert torch.equal(snap.field.geo_grid.table, table)  # the snapshot did not see training
    assert not torch.equal(scratch.field.geo_grid.table, table)
    assert snap.field.geo_grid.adam_m.numel() == 0  # no optimiser state copied
    mesh = frozen.mesh(resolution=2)
    assert len(mesh.faces) > 100


def test_state_from_before_whole_image_keyframes_keeps_the_map(half_mapped):
    """A version-1 state (keyframes kept a pixel subset) resumes with its map and no keyframes;
    mapping goes on and rebuilds the set. An unknown version is refused."""
    seq, m = half_mapped
    meta, arrays = m.state_dict()
    old = {k: v for k, v in arrays.items() if not k.startswith(("kf/color/", "kf/depth_q/"))}
    n = len(m.keyframes.keyframes)
    old.update({"kf/pix": np.zeros(5 * n, np.int32), "kf/pix_offsets": np.arange(0, 5 * n + 1, 5),
                "kf/rgb": np.zeros((5 * n, 3), np.uint8), "kf/rgb_offsets": np.arange(0, 5 * n + 1, 5),
                "kf/depth": np.ones(5 * n, np.float32), "kf/depth_offsets": np.arange(0, 5 * n + 1, 5)})
    r = MapEngine.from_state_dict(SETTINGS, {**meta, "state_version": 1}, old)
    assert r.keyframes.keyframes == [] and len(r.voxels) == len(m.voxels)
    a, b = _params(m), _params(r)
    assert all(torch.equal(a[k], b[k]) for k in a)
    f = list(seq)[20]
    assert r.process(f).mapped and len(r.keyframes.keyframes) == 1
    with pytest.raises(ValueError, match="state version 7"):
        MapEngine.from_state_dict(SETTINGS, {**meta, "state_version": 7}, arrays)
