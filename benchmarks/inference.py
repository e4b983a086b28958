"""Query inference benchmark: PyTorch eager vs onnxruntime decoders, same process, same points.

Maps the default scene (every 4th frame, cached as a checkpoint in the work folder), then times
on frozen snapshots of that map: the two decoders alone on 1M feature rows, a full mesh
extraction at 2 cm, and 640x480 renders at training poses. Medians of repeated runs, both paths
interleaved. Writes research/bench_inference.md / .json.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.tables import median_time
from h3edge.config import load_profile
from h3edge.io.replica import ReplicaSequence
from h3edge.mapping.engine import MapEngine
from h3edge.mapping.map_file import read_checkpoint, write_checkpoint
from h3edge.mapping.onnx_decoders import DecoderRuntime, InferenceConfig
from h3edge.sim.make import PRESETS, ensure_scene

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--work", default="out/bench_inference")
    ap.add_argument("--out", default="research/bench_inference")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    prof = load_profile(args.profile)
    settings = prof.map_settings()
    work = Path(args.work)
    seq = ReplicaSequence(ensure_scene(work / "scene_default", PRESETS["default"]))
    ckpt = work / "map.h3ckpt"
    if ckpt.exists():
        header, arrays = read_checkpoint(ckpt)
        m = MapEngine.from_state_dict(settings, header["state"], arrays)
    else:
        m = MapEngine(settings)
        for i in range(0, len(seq), 4):
            m.process(seq[i])
        meta, arrays = m.state_dict()
        write_checkpoint(ckpt, {"state": meta, "frames_mapped": m.frames_mapped}, arrays)
    cfg = prof.inference if prof.inference.decoders == "onnx" else InferenceConfig(decoders="onnx")
    runtime = DecoderRuntime(cfg, cache_dir=work / "trt_cache")
    eager = m.view().frozen()
    m.view().frozen(runtime)  # first snapshot: builds the shared sessions
    t = time.perf_counter()
    onnx_view = m.view().frozen(runtime)
    snapshot_export_s = time.perf_counter() - t
    providers = onnx_view.field.sdf_mlp.providers
    rows = []
    # decoders alone
    g = torch.Generator().manual_seed(0)
    for name, mlp, n_in in (("SDF decoder, 1M rows", m.field.sdf_mlp, m.field.geo_grid.spec.out_dim),
                            ("colour decoder, 1M rows", m.field.color_mlp, m.field.texture.out_dim)):
        x = torch.randn(1_000_000, n_in, generator=g) * 0.3
        ort_mlp = runtime.mlp(mlp)

        def run_torch():
            with torch.no_grad():
                mlp(x)

        te = median_time(run_torch, args.repeats)
        to = median_time(lambda: ort_mlp(x), args.repeats)
        rows.append((name, te, to))
        b = cfg.batch_rows  # how much of the gain is the batching alone: torch run in the same row batches

        def run_torch_batched():
            with torch.no_grad():
                for s in range(0, len(x), b):
                    mlp(x[s:s + b])

        rows.append((f"{name}, torch also in {b}-row batches", median_time(run_torch_batched, args.repeats), to))
    # full mesh at 2 cm and 640x480 renders
    te = median_time(lambda: eager.mesh(5), args.repeats)
    to = median_time(lambda: onnx_view.mesh(5), args.repeats)
    rows.append(("mesh extraction, 2 cm", te, to))
    views = [seq[i] for i in (50, 150, 250)]
    te = float(np.median([median_time(lambda f=f: eager.render(f.intrinsics, f.pose), 1, False) for f in views]))
    to = float(np.median([median_time(lambda f=f: onnx_view.render(f.intrinsics, f.pose), 1, False) for f in views]))
    rows.append(("render 640x480", te, to))
    lines = [f"### query inference: PyTorch eager vs onnxruntime ({', '.join(providers)}), {args.profile}", "",
             "| what | eager [s] | onnxruntime [s] | speed-up |", "|---|---|---|---|"]
    lines += [f"| {n} | {a:.3f} | {b:.3f} | {a / b:.2f}x |" for n, a, b in rows]
    lines += [
        "",
        f"Map: default scene, {m.frames_mapped} frames (every 4th), {len(m.voxels)} voxels; a snapshot with "
        f"both decoders on the shared sessions {snapshot_export_s * 1000:.0f} ms; "
        f"torch threads {torch.get_num_threads()}. "
        f"`python -m benchmarks.inference` ({time.strftime('%Y-%m-%d')}, 2-core CPU).",
    ]
    text = "\n".join(lines)
    print(text)
    Path(f"{args.out}.md").write_text(text + "\n")
    Path(f"{args.out}.json").write_text(json.dumps({"providers": providers, "rows": [
        {"what": n, "eager_s": a, "onnxruntime_s": b, "speedup": a / b} for n, a, b in rows],
        "snapshot_export_s": snapshot_export_s, "frames": m.frames_mapped, "voxels": len(m.voxels)}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
