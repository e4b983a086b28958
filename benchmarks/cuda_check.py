"""End-to-end check of the CUDA path, for a machine with a GPU (a Jetson, or a lent CUDA box).

    python -m benchmarks.cuda_check [--profile orin-agx] [--frames 40] [--out out/cuda_check]
    deploy/check-cuda.sh OUT_DIR     # this, then the mapping tests with the device forced to CUDA

In one process, a few minutes:
1. parity of the hash encodings on CPU and CUDA (torch backend, the same table and points):
   forward values, the touched rows and their gradients, one sparse Adam step
   (:func:`h3edge.apps.doctor.encoding_parity`, which ``h3edge doctor`` runs too);
2. the tiny simulated scene mapped with the profile's settings on CUDA (default orin-agx), then a
   mesh and a render at a held-out pose, both evaluated against the scene's ground truth, with
   the per-frame time; the same on CPU for the first frames as a reference;
3. query decoders through onnxruntime with the profile's providers (which ones ran is reported).
Prints a table and writes OUT/cuda_check.json; exit 1 when a parity bound or a quality bound
fails, 2 when CUDA is not available (nothing to check).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch

from h3edge.apps.doctor import encoding_parity

log = logging.getLogger(__name__)


def map_and_query(profile_name: str, device: str, frames: int, work: Path) -> dict:
    """Map the tiny scene on ``device`` with the profile's settings; mesh + render + metrics."""
    from h3edge.config import load_profile
    from h3edge.eval.metrics import depth_l1, psnr
    from h3edge.io.replica import ReplicaSequence
    from h3edge.mapping.engine import MapEngine
    from h3edge.mapping.onnx_decoders import DecoderRuntime
    from h3edge.sim.make import PRESETS, ensure_scene

    prof = load_profile(profile_name)
    settings = prof.map_settings()
    settings = dataclasses.replace(settings, mapper=dataclasses.replace(settings.mapper, device=device))
    if device == "cpu" and settings.field.backend == "torch":
        settings = dataclasses.replace(settings, field=dataclasses.replace(settings.field, backend="auto"))
    seq = ReplicaSequence(ensure_scene(work / "scene_tiny", PRESETS["tiny"]))
    m = MapEngine(settings)
    times = []
    for i in range(min(frames, len(seq))):
        f = seq[i]
        t0 = time.perf_counter()
        m.process(f)
        if m.device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    held = seq.heldout
    runtime = DecoderRuntime(prof.inference, cache_dir=work / "trt_cache")
    view = m.view().frozen(runtime)
    t0 = time.perf_counter()
    mesh = view.mesh(settings.mapper.mesh_resolution)
    mesh_s = time.perf_counter() - t0
    inside = [j for j in range(len(held)) if held.timestamps[j] <= seq.timestamps[len(times) - 1]]
    f = held[inside[len(inside) // 2] if inside else 0]  # a held-out view within the mapped stretch
    t0 = time.perf_counter()
    rgb, depth = view.render(f.intrinsics, f.pose)
    render_s = time.perf_counter() - t0
    return {
        "device": str(m.device),
        "frames": len(times),
        "frame_ms_median": 1e3 * float(np.median(times[2:] or times)),
        "mesh_faces": int(len(mesh.faces)),
        "mesh_s": mesh_s,
        "render_s": render_s,
        "heldout_psnr_db": float(psnr(rgb, f.color)),
        "heldout_depth_l1_cm": 100 * float(depth_l1(depth, f.depth)[0]),
        "inference": runtime.describe(),
        "peak_cuda_mb": (torch.cuda.max_memory_allocated() / 2**20 if m.device.type == "cuda" else None),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="orin-agx")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--cpu-frames", type=int, default=10, help="frames mapped on CPU as the reference")
    ap.add_argument("--out", default="out/cuda_check")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not torch.cuda.is_available():
        print("error: CUDA is not available to torch here (nothing to check)", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res = {"torch": torch.__version__, "cuda": torch.version.cuda, "gpu": torch.cuda.get_device_name(0),
           "encoding_parity": encoding_parity()}
    res["cuda_run"] = map_and_query(args.profile, "cuda", args.frames, out)
    res["cpu_run"] = map_and_query(args.profile, "cpu", args.cpu_frames, out)
    c = res["cuda_run"]
    quality_ok = c["mesh_faces"] > 1000 and c["heldout_depth_l1_cm"] < 10 and c["heldout_psnr_db"] > 15
    res["ok"] = bool(res["encoding_parity"]["ok"] and quality_ok)
    (out / "cuda_check.json").write_text(json.dumps(res, indent=1) + "\n")
    p = res["encoding_parity"]
    print(f"GPU {res['gpu']} (torch {res['torch']}, CUDA {res['cuda']}), profile {args.profile}")
    print(f"encodings CPU vs CUDA: forward {p['forward_max_abs']:.2e}, same rows {p['same_rows']}, "
          f"gradients {p['grad_max_abs']}, Adam step {p['adam_max_abs']:.2e} -> {'ok' if p['ok'] else 'FAIL'}")
    for name in ("cuda_run", "cpu_run"):
        r = res[name]
        print(f"{r['device']:>6}: {r['frames']} frames, {r['frame_ms_median']:.0f} ms/frame median, mesh "
              f"{r['mesh_faces']} faces in {r['mesh_s']:.2f} s, render {r['render_s']:.2f} s, held-out PSNR "
              f"{r['heldout_psnr_db']:.2f} dB, Depth L1 {r['heldout_depth_l1_cm']:.2f} cm, decoders on "
              f"{', '.join(r['inference']['active'])}")
    print("OK" if res["ok"] else "FAIL")
    return 0 if res["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
