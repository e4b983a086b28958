"""The field's decoders (SDF residual MLP, colour MLP) as ONNX models, run by onnxruntime.

The graphs are written from the trained weights with ``onnx.helper`` (Gemm, Relu, Sigmoid), not
traced with ``torch.onnx.export``: the exporter takes ~6 s per model on a 2-core CPU, and a
serving map re-exports whenever a query takes a new snapshot; writing the graph takes ~1 ms and
carries the same operators. Parity with PyTorch is tested (max |error| <= 1e-4).

:class:`OrtMLP` is an ``nn.Module`` whose forward runs an onnxruntime session (inputs and outputs
go through host memory), so a frozen :class:`~h3edge.mapping.snapshot.MapView` can swap its
decoders for exported ones and every query path (mesh, render) uses them unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnx import TensorProto, helper, numpy_helper
from torch import nn

OPSET = 17


@dataclass(frozen=True)
class InferenceConfig:
    decoders: str = "onnx"  # onnx | torch: how queries (mesh, render) evaluate the decoders
    providers: str = "CPUExecutionProvider"  # onnxruntime execution providers, in order of preference
    threads: int = 0  # onnxruntime intra-op threads (0: onnxruntime's default, one per core)
    # rows per onnxruntime run: on a CPU, 8k rows keep a 64-wide layer's activations (2 MB) in
    # cache; one run over 1M rows was 2x slower (docs/bench_inference.md). GPUs want large batches.
    batch_rows: int = 8192


def _layers(module: nn.Module) -> list[nn.Module]:
    out: list[nn.Module] = []
    for m in module.children() if isinstance(module, nn.Sequential) else [module]:
        out += _layers(m) if isinstance(m, nn.Sequential) else [m]
    return out


def mlp_to_onnx(module: nn.Module, name: str, doc: str = "") -> bytes:
    """Serialized ONNX model of an MLP made of Linear / ReLU / Sigmoid layers: input ``x`` (N, in),
    output ``y`` (N, out), float32, N dynamic."""
    nodes, inits = [], []
    cur = "x"
    n_in = None
    for i, layer in enumerate(_layers(module)):
        out = f"h{i}"
        if isinstance(layer, nn.Linear):
            w = layer.weight.detach().cpu().numpy().astype(np.float32)
            b = (layer.bias.detach().cpu().numpy() if layer.bias is not None else np.zeros(w.shape[0])).astype(np.float32)
            n_in = w.shape[1] if n_in is None else n_in
            inits += [numpy_helper.from_array(w, f"w{i}"), numpy_helper.from_array(b, f"b{i}")]
            nodes.append(helper.make_node("Gemm", [cur, f"w{i}", f"b{i}"], [out], transB=1))
            n_out = w.shape[0]
        elif isinstance(layer, nn.ReLU):
            nodes.append(helper.make_node("Relu", [cur], [out]))
        elif isinstance(layer, nn.Sigmoid):
            nodes.append(helper.make_node("Sigmoid", [cur], [out]))
        else:
            raise TypeError(f"cannot export layer {type(layer).__name__} (Linear, ReLU, Sigmoid only)")
        cur = out
    if n_in is None:
        raise ValueError("the module has no Linear layer")
    nodes.append(helper.make_node("Identity", [cur], ["y"]))
    graph = helper.make_graph(nodes, name, [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", n_in])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["n", n_out])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="h3edge",
                              doc_string=doc)
    model.ir_version = 8  # readable by onnxruntime >= 1.14 (JetPack 5 builds)
    onnx.checker.check_model(model)
    return model.SerializeToString()


def make_session(model: bytes, cfg: InferenceConfig = InferenceConfig()) -> ort.InferenceSession:
    so = ort.SessionOptions()
    if cfg.threads > 0:
        so.intra_op_num_threads = cfg.threads
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # no busy-waiting between runs: the hash kernels (numba / OpenMP) and training share the cores,
    # and spinning pool threads slowed mesh extraction 1.8x (docs/bench_inference.md)
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    wanted = [p.strip() for p in cfg.providers.split(",") if p.strip()]
    available = ort.get_available_providers()
    providers = [p for p in wanted if p in available] or ["CPUExecutionProvider"]
    return ort.InferenceSession(model, so, providers=providers)


class OrtMLP(nn.Module):
    """An exported MLP behind the ``nn.Module`` interface (inference only)."""

    def __init__(self, model: bytes, cfg: InferenceConfig = InferenceConfig()):
        super().__init__()
        self.model = model
        self.session = make_session(model, cfg)
        self.batch_rows = max(1, cfg.batch_rows)
        self.n_out = int(self.session.get_outputs()[0].shape[1])
        # TensorRT builds an engine per input shape: every run gets the same (padded) shape
        self.pad = "TensorrtExecutionProvider" in self.providers

    @property
    def providers(self) -> list[str]:
        return self.session.get_providers()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xn = np.ascontiguousarray(x.detach().cpu().numpy(), dtype=np.float32)
        b = self.batch_rows
        if len(xn) <= b and not self.pad:
            return torch.from_numpy(self.session.run(["y"], {"x": xn})[0]).to(x.device)
        y = np.empty((len(xn), self.n_out), np.float32)
        for s in range(0, len(xn), b):
            part = xn[s:s + b]
            if self.pad and len(part) < b:
                part = np.concatenate([part, np.zeros((b - len(part), xn.shape[1]), np.float32)])
            y[s:s + b] = self.session.run(["y"], {"x": part})[0][:min(b, len(xn) - s)]
        return torch.from_numpy(y).to(x.device)


def export_decoders(field) -> dict[str, bytes]:
    """{'sdf': ..., 'color': ...} ONNX models of a field's decoders."""
    return {"sdf": mlp_to_onnx(field.sdf_mlp, "sdf_residual", "SDF residual MLP: geometry features -> SDF"),
            "color": mlp_to_onnx(field.color_mlp, "color", "colour MLP: texture features -> RGB in [0, 1]")}
