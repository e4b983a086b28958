"""The field's decoders (SDF residual MLP, colour MLP) as ONNX models, run by onnxruntime.

The graphs are written from the trained weights with ``onnx.helper`` (Gemm, Relu, Sigmoid), not
traced with ``torch.onnx.export``: the exporter takes ~6 s per model on a 2-core CPU, and a
serving map re-exports whenever a query takes a new snapshot; writing the graph takes ~1 ms and
carries the same operators. Parity with PyTorch is tested (max |error| <= 1e-4).

:class:`OrtMLP` is an ``nn.Module`` whose forward runs an onnxruntime session (inputs and outputs
go through host memory), so a frozen :class:`~h3edge.mapping.view.MapView` can swap its
decoders for exported ones and every query path (mesh, render) uses them unchanged.

:class:`DecoderRuntime` owns the sessions of a process (one per decoder architecture): the
serving graphs take the weights as inputs, so every snapshot of a map runs the same session and
the same TensorRT engine with its own weights. TensorRT's engine cache is keyed by the graph, not
by the weights it was built with: an engine built from weights baked in as initializers would be
reused with stale weights after a retrain. The runtime also says which providers run and warns,
naming the missing provider and the installed onnxruntime build, when a requested one is absent.
"""

from __future__ import annotations

import hashlib
import logging
import threading
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnx import TensorProto, helper, numpy_helper
from torch import nn

OPSET = 17
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InferenceConfig:
    decoders: str = "onnx"
    """onnx | torch: how queries (mesh, render) evaluate the decoders"""
    providers: str = "CPUExecutionProvider"
    """onnxruntime execution providers, in order of preference"""
    threads: int = 0
    """onnxruntime intra-op threads (0: onnxruntime's default, one per core)"""
    batch_rows: int = 8192
    """rows per onnxruntime run (a CPU wants ~8k, in cache; a GPU large batches; research/bench_inference.md)"""
    trt_cache_dir: str = ""
    """TensorRT engine and timing cache; empty: the service's <state_dir>/<map_id>/trt_cache, an offline run's
    <out>/trt_cache (a new snapshot then reuses the engine instead of rebuilding it)"""

    def __post_init__(self):
        if self.decoders not in ("onnx", "torch"):
            raise ValueError(f"decoders must be onnx or torch, got {self.decoders!r}")


def _layers(module: nn.Module) -> list[nn.Module]:
    out: list[nn.Module] = []
    for m in module.children() if isinstance(module, nn.Sequential) else [module]:
        out += _layers(m) if isinstance(m, nn.Sequential) else [m]
    return out


def mlp_weights(module: nn.Module) -> dict[str, np.ndarray]:
    """The MLP's weights by ONNX input name (``w{i}`` (out, in), ``b{i}`` (out,)), float32."""
    out = {}
    for i, layer in enumerate(_layers(module)):
        if isinstance(layer, nn.Linear):
            w = layer.weight.detach().cpu().numpy().astype(np.float32)
            b = layer.bias.detach().cpu().numpy() if layer.bias is not None else np.zeros(w.shape[0])
            out[f"w{i}"], out[f"b{i}"] = np.ascontiguousarray(w), b.astype(np.float32)
    return out


def mlp_to_onnx(module: nn.Module, name: str, doc: str = "", weights_as_inputs: bool = False) -> bytes:
    """Serialized ONNX model of an MLP made of Linear / ReLU / Sigmoid layers: input ``x`` (N, in),
    output ``y`` (N, out), float32, N dynamic. With ``weights_as_inputs`` the weights are graph
    inputs named as in :func:`mlp_weights` instead of initializers (one graph serves any weights)."""
    nodes, inits, weight_inputs = [], [], []
    cur = "x"
    n_in = None
    for i, layer in enumerate(_layers(module)):
        out = f"h{i}"
        if isinstance(layer, nn.Linear):
            w = layer.weight.detach().cpu().numpy().astype(np.float32)
            b = (layer.bias.detach().cpu().numpy() if layer.bias is not None else np.zeros(w.shape[0])).astype(
                np.float32
            )
            n_in = w.shape[1] if n_in is None else n_in
            if weights_as_inputs:
                weight_inputs += [helper.make_tensor_value_info(f"w{i}", TensorProto.FLOAT, list(w.shape)),
                                  helper.make_tensor_value_info(f"b{i}", TensorProto.FLOAT, list(b.shape))]
            else:
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
    graph = helper.make_graph(nodes, name, [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", n_in])]
                              + weight_inputs, [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["n", n_out])],
                              inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="h3edge",
                              doc_string=doc)
    model.ir_version = 8  # readable by onnxruntime >= 1.14 (older Jetson builds)
    onnx.checker.check_model(model)
    return model.SerializeToString()


def onnxruntime_build() -> str:
    """The installed onnxruntime distribution and version, e.g. ``onnxruntime-gpu 1.23.2``."""
    for dist in ("onnxruntime-gpu", "onnxruntime-directml", "onnxruntime-openvino", "onnxruntime"):
        try:
            return f"{dist} {metadata.version(dist)}"
        except metadata.PackageNotFoundError:
            continue
    return f"onnxruntime {ort.__version__} (no distribution metadata)"


def resolve_providers(cfg: InferenceConfig) -> tuple[list[str], list[str]]:
    """(requested providers this onnxruntime has, in order; requested ones it lacks). The CPU
    provider closes the list when nothing requested is available."""
    wanted = [p.strip() for p in cfg.providers.split(",") if p.strip()]
    available = ort.get_available_providers()
    have = [p for p in wanted if p in available]
    return have or ["CPUExecutionProvider"], [p for p in wanted if p not in available]


def make_session(model: bytes, cfg: InferenceConfig = InferenceConfig(), providers: list | None = None
                 ) -> ort.InferenceSession:
    so = ort.SessionOptions()
    if cfg.threads > 0:
        so.intra_op_num_threads = cfg.threads
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # no busy-waiting between runs: the hash kernels (numba / OpenMP) and training share the cores,
    # and spinning pool threads slowed mesh extraction 1.8x (research/bench_inference.md)
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(model, so, providers=providers or resolve_providers(cfg)[0])


class OrtMLP(nn.Module):
    """An exported MLP behind the ``nn.Module`` interface (inference only).

    ``model`` is either serialized ONNX bytes (weights inside; a session of its own) or an existing
    session whose graph takes the weights as inputs, with those weights in ``weights``.
    """

    def __init__(self, model: bytes | ort.InferenceSession, cfg: InferenceConfig = InferenceConfig(),
                 weights: dict[str, np.ndarray] | None = None):
        super().__init__()
        self.session = model if isinstance(model, ort.InferenceSession) else make_session(model, cfg)
        self.weights = dict(weights or {})
        self.batch_rows = max(1, cfg.batch_rows)
        self.n_out = int(self.session.get_outputs()[0].shape[1])
        # TensorRT builds an engine per input shape: every run gets the same (padded) shape
        self.pad = "TensorrtExecutionProvider" in self.providers

    @property
    def providers(self) -> list[str]:
        return self.session.get_providers()

    def _run(self, x: np.ndarray) -> np.ndarray:
        return self.session.run(["y"], {"x": x, **self.weights})[0]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xn = np.ascontiguousarray(x.detach().cpu().numpy(), dtype=np.float32)
        b = self.batch_rows
        if len(xn) <= b and not self.pad:
            return torch.from_numpy(self._run(xn)).to(x.device)
        y = np.empty((len(xn), self.n_out), np.float32)
        for s in range(0, len(xn), b):
            part = xn[s:s + b]
            if self.pad and len(part) < b:
                part = np.concatenate([part, np.zeros((b - len(part), xn.shape[1]), np.float32)])
            y[s:s + b] = self._run(part)[:min(b, len(xn) - s)]
        return torch.from_numpy(y).to(x.device)


class DecoderRuntime:
    """The onnxruntime sessions of one process, one per decoder architecture, shared by every
    snapshot (thread-safe: onnxruntime sessions run concurrently).

        runtime = DecoderRuntime(profile.inference, cache_dir=state_dir / "trt_cache")
        view = mapper.view().frozen(runtime)      # decoders run by the shared sessions
        runtime.describe()                        # {"requested", "active", "missing", "onnxruntime"}
    """

    def __init__(self, cfg: InferenceConfig, cache_dir: str | Path | None = None):
        self.cfg = cfg
        self.requested = [p.strip() for p in cfg.providers.split(",") if p.strip()]
        names, self.missing = resolve_providers(cfg)
        if self.missing:
            log.warning("onnxruntime execution provider(s) %s requested but not in the installed build (%s, "
                        "available: %s); query decoders run on %s", ", ".join(self.missing), onnxruntime_build(),
                        ", ".join(ort.get_available_providers()), ", ".join(names))
        raw = cfg.trt_cache_dir or cache_dir
        self.cache_dir = Path(raw) if raw else None
        self._providers: list = []
        for n in names:
            if n == "TensorrtExecutionProvider" and self.cache_dir is not None:
                self.cache_dir.mkdir(parents=True, exist_ok=True)
                self._providers.append((n, {"trt_engine_cache_enable": True,
                                            "trt_engine_cache_path": str(self.cache_dir),
                                            "trt_timing_cache_enable": True,
                                            "trt_timing_cache_path": str(self.cache_dir)}))
            else:
                self._providers.append(n)
        self._sessions: dict[str, ort.InferenceSession] = {}
        self._lock = threading.Lock()
        self.active: list[str] = []

    def session(self, module: nn.Module) -> ort.InferenceSession:
        """The shared session for ``module``'s architecture (built on first use)."""
        graph = mlp_to_onnx(module, "decoder", weights_as_inputs=True)
        key = hashlib.sha256(graph).hexdigest()
        with self._lock:
            sess = self._sessions.get(key)
            if sess is None:
                sess = self._sessions[key] = make_session(graph, self.cfg, self._providers)
                first = not self.active
                self.active = sess.get_providers()
                if first and self.requested and self.requested[0] not in self.active:
                    log.warning("query decoders: %s requested first, session runs on %s (%s)", self.requested[0],
                                ", ".join(self.active), onnxruntime_build())
            return sess

    def mlp(self, module: nn.Module) -> OrtMLP:
        """``module`` (Linear / ReLU / Sigmoid) as an :class:`OrtMLP` on the shared session."""
        return OrtMLP(self.session(module), self.cfg, mlp_weights(module))

    def describe(self) -> dict:
        return {"requested": self.requested, "active": self.active or [p if isinstance(p, str) else p[0]
                                                                        for p in self._providers],
                "missing": self.missing, "onnxruntime": onnxruntime_build(),
                "trt_cache_dir": str(self.cache_dir) if self.cache_dir else None}


def export_decoders(field) -> dict[str, bytes]:
    """{'sdf': ..., 'color': ...} ONNX models of a field's decoders."""
    return {"sdf": mlp_to_onnx(field.sdf_mlp, "sdf_residual", "SDF residual MLP: geometry features -> SDF"),
            "color": mlp_to_onnx(field.color_mlp, "color", "colour MLP: texture features -> RGB in [0, 1]")}
