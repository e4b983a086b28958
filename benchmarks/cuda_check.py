"""End-to-end check of the CUDA path, for a machine with a GPU (a Jetson, or a lent CUDA box).

    python -m benchmarks.cuda_check [--profile orin-agx] [--frames 40] [--anytime] [--out out/cuda_check]
    deploy/check-cuda.sh OUT_DIR     # this, then the mapping tests with the device forced to CUDA

In one process, a few minutes (``--anytime``: about ten more):
1. parity of the hash encodings on CPU and CUDA (torch backend, the same table and points):
   forward values, the touched rows and their gradients, one sparse Adam step
   (:func:`h3edge.apps.doctor.encoding_parity`, which ``h3edge doctor`` runs too);
2. the tiny simulated scene mapped with the profile's settings on CUDA (default orin-agx), then a
   mesh and a render at a held-out pose, both evaluated against the scene's ground truth, with
   the per-frame time, the per-component timings, the host transfers and syncs of the training
   steps (:class:`h3edge.profiling.host_transfers.HostTransfers`) and the peak GPU memory against
   the profile's memory plan; the same on CPU for the first frames as a reference;
3. query decoders through onnxruntime with the profile's providers (which ones ran is reported);
4. with ``--anytime``: issue [1/5]'s anytime benchmark on the real dev set at 30 Hz on CUDA
   (:mod:`benchmarks.anytime`; its table and JSON under OUT).
Prints a table and writes OUT/cuda_check.json; exit 1 when a bound fails (parity, quality, more
than one host transfer a step, peak GPU memory over the plan), 2 when CUDA is not available
(nothing to check). ``--device cpu`` runs the same checks with CPU in CUDA's place (the suite's
check that this script works where no GPU is).
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


def map_and_query(profile_name: str, device: str, frames: int, work: Path, reference: bool = False,
                  overrides: tuple[str, ...] = ()) -> dict:
    """Map the tiny scene on ``device`` with the profile's settings (``overrides``: ``section.key=value``
    changes); mesh + render + metrics. ``reference``: the CPU reference run, on the CPU's own backend
    (numba) rather than torch."""
    from h3edge.config import apply_overrides, load_profile
    from h3edge.eval.metrics import depth_l1, psnr
    from h3edge.io.replica import ReplicaSequence
    from h3edge.mapping.engine import MapEngine
    from h3edge.mapping.onnx_decoders import DecoderRuntime
    from h3edge.sim.make import PRESETS, ensure_scene

    prof = load_profile(profile_name)
    settings = apply_overrides(prof.map_settings(), list(overrides))
    settings = dataclasses.replace(settings, mapper=dataclasses.replace(settings.mapper, device=device))
    if reference and settings.field.backend == "torch":
        settings = dataclasses.replace(settings, field=dataclasses.replace(settings.field, backend="auto"))
    seq = ReplicaSequence(ensure_scene(work / "scene_tiny", PRESETS["tiny"]))
    from h3edge.mapping.memory_plan import memory_plan
    from h3edge.profiling.host_transfers import HostTransfers

    m = MapEngine(settings)
    if m.device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    times, transfers, syncs = [], [], []
    for i in range(min(frames, len(seq))):
        f = seq[i]
        t0 = time.perf_counter()
        m.integrate(f)
        with HostTransfers() as ht:
            for _ in range(settings.mapper.iterations):
                m.train_once()
        if m.device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
        if i >= 2:  # past the first keyframe and the field's set-up
            transfers.append(ht.total / max(1, settings.mapper.iterations))
            syncs.append(ht.syncs / max(1, settings.mapper.iterations))
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
        "plan_mb": memory_plan(settings, prof.service.memory_budget_mb, 0)["budget"] / 2**20,
        "step_host_transfers_max": max(transfers, default=0.0),
        "step_syncs_median": float(np.median(syncs)) if syncs else 0.0,
        "timings_ms": {k: round(v["median_ms"], 2) for k, v in m.timings.summary().items() if "median_ms" in v},
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="orin-agx")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--cpu-frames", type=int, default=10, help="frames mapped on CPU as the reference")
    ap.add_argument("--anytime", action="store_true", help="also the anytime benchmark on the real dev set at 30 Hz")
    ap.add_argument("--device", default="cuda", choices=["cuda", "cpu"],
                    help="cpu: the same checks with CPU in CUDA's place (this script's own test)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="change a mapping setting of the profile (both runs)")
    ap.add_argument("--out", default="out/cuda_check")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.device == "cuda" and not torch.cuda.is_available():
        print("error: CUDA is not available to torch here (nothing to check)", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    on_gpu = args.device == "cuda"
    res = {"torch": torch.__version__, "cuda": torch.version.cuda,
           "gpu": torch.cuda.get_device_name(0) if on_gpu else "none (--device cpu)",
           "encoding_parity": encoding_parity() if on_gpu else {"ok": True, "skipped": "no GPU"}}
    res["cuda_run"] = map_and_query(args.profile, args.device, args.frames, out, overrides=tuple(args.set))
    res["cpu_run"] = (map_and_query(args.profile, "cpu", args.cpu_frames, out, reference=True,
                                    overrides=tuple(args.set)) if args.cpu_frames else None)
    c = res["cuda_run"]
    quality_ok = c["mesh_faces"] > 1000 and c["heldout_depth_l1_cm"] < 10 and c["heldout_psnr_db"] > 15
    transfers_ok = c["step_host_transfers_max"] <= 1
    memory_ok = c["peak_cuda_mb"] is None or c["peak_cuda_mb"] <= c["plan_mb"]
    res["bounds"] = {"parity": bool(res["encoding_parity"]["ok"]), "quality": bool(quality_ok),
                     "one_host_transfer_a_step": bool(transfers_ok), "peak_memory_within_plan": bool(memory_ok)}
    if args.anytime:
        from benchmarks import anytime

        anytime.main(["--datasets", "real", "--profile", args.profile, "--set", f"mapper.device={args.device}",
                      "--hz", "30", "--components", "--out", str(out / "anytime_real")])
        res["anytime"] = json.loads((out / "anytime_real.json").read_text())
    res["ok"] = all(res["bounds"].values())
    (out / "cuda_check.json").write_text(json.dumps(res, indent=1) + "\n")
    p = res["encoding_parity"]
    print(f"GPU {res['gpu']} (torch {res['torch']}, CUDA {res['cuda']}), profile {args.profile}")
    if "skipped" in p:
        print(f"encodings CPU vs CUDA: skipped ({p['skipped']})")
    else:
        print(f"encodings CPU vs CUDA: forward {p['forward_max_abs']:.2e}, same rows {p['same_rows']}, "
              f"gradients {p['grad_max_abs']}, Adam step {p['adam_max_abs']:.2e} -> {'ok' if p['ok'] else 'FAIL'}")
    for name in ("cuda_run", "cpu_run"):
        r = res[name]
        if r is None:
            continue
        print(f"{r['device']:>6}: {r['frames']} frames, {r['frame_ms_median']:.0f} ms/frame median, mesh "
              f"{r['mesh_faces']} faces in {r['mesh_s']:.2f} s, render {r['render_s']:.2f} s, held-out PSNR "
              f"{r['heldout_psnr_db']:.2f} dB, Depth L1 {r['heldout_depth_l1_cm']:.2f} cm, decoders on "
              f"{', '.join(r['inference']['active'])}; a step: {r['step_host_transfers_max']:.0f} host transfers, "
              f"{r['step_syncs_median']:.0f} syncs; peak GPU memory {r['peak_cuda_mb']} MB "
              f"(plan {r['plan_mb']:.0f} MB)")
        print("        timings [ms, median]: " + ", ".join(f"{k} {v}" for k, v in r["timings_ms"].items()))
    print("bounds: " + ", ".join(f"{k} {'ok' if v else 'FAIL'}" for k, v in res["bounds"].items()))
    print("OK" if res["ok"] else "FAIL")
    return 0 if res["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
