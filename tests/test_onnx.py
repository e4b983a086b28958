"""ONNX-exported decoders: parity with PyTorch (random and real sample points), no stale export,
shared sessions that follow the weights, providers reported and missing ones warned about."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from h3edge.geometry.camera import backproject
from h3edge.io.replica import ReplicaSequence
from h3edge.mapping.engine import MapEngine, MapperConfig, MapSettings
from h3edge.mapping.field import Field, FieldConfig
from h3edge.mapping.onnx_decoders import DecoderRuntime, InferenceConfig, OrtMLP, export_decoders, mlp_to_onnx
from h3edge.mapping.voxels import VoxelConfig

SETTINGS = MapSettings(mapper=MapperConfig(device="cpu", rays_per_iteration=512, mesh_resolution=2),
                       voxels=VoxelConfig(min_points=3),
                       field=FieldConfig(sdf_layers=2, geo_log2_table=14, tex_log2_table=14))
ONNX = InferenceConfig(decoders="onnx", threads=1)


def test_random_field_parity():
    f = Field(FieldConfig(geo_log2_table=10, tex_log2_table=10), np.array([[0.0] * 3, [4.0] * 3]), 0.1)
    models = export_decoders(f)
    g = torch.Generator().manual_seed(0)
    for name, mlp, n_in in (("sdf", f.sdf_mlp, f.geo_grid.spec.out_dim), ("color", f.color_mlp, f.texture.out_dim)):
        x = torch.randn(5000, n_in, generator=g) * 0.5
        with torch.no_grad():
            ref = mlp(x)
        out = OrtMLP(models[name], ONNX)(x)
        assert out.shape == ref.shape and (out - ref).abs().max() <= 1e-4, name


def test_batched_and_padded_runs_match_one_run():
    """Row batches (and the fixed-shape padding TensorRT gets) give the one-run answer, row for row."""
    f = Field(FieldConfig(geo_log2_table=10, tex_log2_table=10), np.array([[0.0] * 3, [4.0] * 3]), 0.1)
    model = export_decoders(f)["color"]
    x = torch.randn(5003, f.texture.out_dim, generator=torch.Generator().manual_seed(1))
    one = OrtMLP(model, ONNX)(x)
    batched = OrtMLP(model, InferenceConfig(threads=1, batch_rows=1000))
    close = lambda a, b: a.shape == b.shape and (a - b).abs().max() <= 1e-6  # noqa: E731
    assert close(batched(x), one)
    batched.pad = True  # as with the TensorRT provider
    assert close(batched(x), one) and close(batched(x[:7]), one[:7])


def test_unsupported_layer_is_refused():
    with pytest.raises(TypeError, match="Tanh"):
        mlp_to_onnx(torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.Tanh()), "x")


@pytest.fixture(scope="module")
def mapped(tiny_scene):
    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(SETTINGS)
    for f in list(seq)[:12]:
        m.process(f)
    return seq, m


def test_real_points_parity_and_queries(mapped):
    seq, m = mapped
    f = seq[6]
    pts = backproject(f.depth, f.intrinsics, f.pose).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(1)][::7]
    pts = np.concatenate([pts, pts + np.random.default_rng(0).normal(0, 0.03, pts.shape)])  # off the surface too
    eager, exported = m.view().frozen(), m.view().frozen(DecoderRuntime(ONNX))
    assert isinstance(exported.field.sdf_mlp, OrtMLP)
    assert np.abs(eager.sdf_np(pts) - exported.sdf_np(pts)).max() <= 1e-4
    assert np.abs(eager.color_np(pts) - exported.color_np(pts)).max() <= 1e-4
    (rgb_e, d_e), (rgb_o, d_o) = eager.render(f.intrinsics, f.pose), exported.render(f.intrinsics, f.pose)
    assert np.abs(d_e - d_o).max() < 1e-3 and np.abs(rgb_e.astype(int) - rgb_o).max() <= 1
    assert len(exported.mesh(2).faces) == len(eager.mesh(2).faces)


def test_export_follows_training(mapped):
    seq, m = mapped
    x = torch.randn(256, m.field.geo_grid.spec.out_dim)
    before = OrtMLP(export_decoders(m.field)["sdf"], ONNX)(x)
    for f in list(seq)[12:15]:
        m.process(f)
    after = OrtMLP(export_decoders(m.field)["sdf"], ONNX)(x)
    with torch.no_grad():
        ref = m.field.sdf_mlp(x)
    assert (after - before).abs().max() > 1e-5  # a new export carries the new weights
    assert (after - ref).abs().max() <= 1e-4


def test_snapshots_share_one_session_and_follow_the_weights(mapped):
    """Every snapshot runs the runtime's one session per decoder (one TensorRT engine), each with
    its own weights: a snapshot taken after more training answers with the new weights."""
    seq, m = mapped
    runtime = DecoderRuntime(ONNX)
    x = torch.randn(300, m.field.geo_grid.spec.out_dim, generator=torch.Generator().manual_seed(2))
    first = m.view().frozen(runtime)
    before = first.field.sdf_mlp(x)
    for f in list(seq)[15:18]:
        m.process(f)
    second = m.view().frozen(runtime)
    assert second.field.sdf_mlp.session is first.field.sdf_mlp.session
    assert second.field.color_mlp.session is first.field.color_mlp.session
    assert len(runtime._sessions) == 2
    with torch.no_grad():
        ref = m.field.sdf_mlp(x)
    after = second.field.sdf_mlp(x)
    assert (after - ref).abs().max() <= 1e-4 and (after - before).abs().max() > 1e-5
    assert (first.field.sdf_mlp(x) - before).abs().max() == 0  # the older snapshot keeps its weights


def test_missing_provider_is_a_warning_naming_it_and_the_build(caplog):
    import onnxruntime

    absent = [p for p in ("TensorrtExecutionProvider", "CUDAExecutionProvider", "NoSuchExecutionProvider")
              if p not in onnxruntime.get_available_providers()]
    cfg = InferenceConfig(providers=",".join(absent + ["CPUExecutionProvider"]))
    with caplog.at_level("WARNING"):
        runtime = DecoderRuntime(cfg)
    assert all(p in caplog.text for p in absent) and "onnxruntime" in caplog.text
    d = runtime.describe()
    assert d["missing"] == absent
    assert d["active"] == ["CPUExecutionProvider"] and d["onnxruntime"].startswith("onnxruntime")


def test_unknown_decoder_backend_is_refused():
    with pytest.raises(ValueError, match="onnx or torch"):
        InferenceConfig(decoders="tensorflow")
