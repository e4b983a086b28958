"""Host transfers of the torch backend's integration and training step (issue [3/5]): the Orin
profiles' mapping (``field.backend = "torch"``) run on this machine's CPU with every tensor-to-host
call h3edge makes counted (:class:`h3edge.profiling.host_transfers.HostTransfers`), per frame's
integration and per training step, by function and by source line. On CUDA each is a stall.

    python -m benchmarks.host_transfers [--profile orin-agx] [--frames 8] [--out research/bench_host_transfers]

Prints a table and writes JSON (``<out>.json``) and markdown (``<out>.md``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import statistics
import tempfile
from pathlib import Path

from h3edge.config import load_profile
from h3edge.io import open_sequence
from h3edge.mapping.engine import MapEngine, MapSettings
from h3edge.profiling.host_transfers import HostTransfers
from h3edge.sim.make import PRESETS, make_scene


def lean_torch_settings(profile: str = "orin-agx") -> MapSettings:
    """``profile``'s mapping on the CPU with the torch backend, sized for the tiny simulated scene
    (160x120: 3 points a voxel; small tables; 1,024 rays a step)."""
    s = load_profile(profile).mapping
    return dataclasses.replace(
        s, mapper=dataclasses.replace(s.mapper, device="cpu", rays_per_iteration=1024),
        voxels=dataclasses.replace(s.voxels, min_points=3),
        field=dataclasses.replace(s.field, backend="torch", geo_log2_table=14, tex_log2_table=14))


def count_transfers(settings: MapSettings, frames: list) -> dict:
    """Integrate each frame and run two training steps after it (the second with no new frame),
    counting host transfers: the per-frame and per-step totals (after the first two frames: the
    map's first keyframe and field set-up are not the steady state), the steady steps' counts by
    function and by line, and the bytes of host arrays they made tensors (uploads), by function,
    summed over those steps."""
    m = MapEngine(settings)
    m.voxels.compact_lookup = False  # the GPU's fixed-shape lookup, not the CPU's compaction
    per_frame, per_step, step_syncs = [], [], []
    functions: dict[str, list[int]] = {}
    sync_functions: dict[str, list[int]] = {}
    lines: dict[str, int] = {}
    uploads: dict[str, int] = {}
    for i, f in enumerate(frames):
        with HostTransfers() as integ:
            m.integrate(f)
        steps = []
        for _ in range(2):
            with HostTransfers() as step:
                if m.train_once() is not None:
                    steps.append(step)
        if i < 2 or not steps:
            continue
        per_frame.append(integ.total)
        for step in steps:
            per_step.append(step.total)
            step_syncs.append(step.syncs)
            for k, v in step.by_function().items():
                functions.setdefault(k, []).append(v)
            for k, v in step.syncs_by_function().items():
                sync_functions.setdefault(k, []).append(v)
            for k, v in step.by_line().items():
                lines[k] = max(lines.get(k, 0), v)
            for k, v in step.uploads_by_function().items():
                uploads[k] = uploads.get(k, 0) + v
    if not per_step:
        raise RuntimeError("no steady training step ran: more frames needed")
    return {"frames": len(per_frame), "integration": {"max": max(per_frame), "median": statistics.median(per_frame)},
            "step": {"max": max(per_step), "median": statistics.median(per_step)},
            "step_syncs": {"max": max(step_syncs), "median": statistics.median(step_syncs)},
            "step_syncs_by_function": {k: max(v) for k, v in
                                       sorted(sync_functions.items(), key=lambda kv: -max(kv[1]))},
            "step_by_function": {k: max(v) for k, v in sorted(functions.items(), key=lambda kv: -max(kv[1]))},
            "step_by_line": dict(sorted(lines.items(), key=lambda kv: -kv[1])),
            "steps": len(per_step), "frame_pixels": int(frames[0].depth.size),
            "step_uploads_by_function": dict(sorted(uploads.items(), key=lambda kv: -kv[1]))}


def _markdown(result: dict, profile: str) -> str:
    out = [f"Host transfers, {profile} mapping on the torch backend (CPU), {result['frames']} steady frames: "
           f"integration {result['integration']['max']} a frame, training step {result['step']['max']} "
           f"(median {result['step']['median']}).", "", "| step: function | transfers |", "|---|---|"]
    out += [f"| `{k}` | {v} |" for k, v in result["step_by_function"].items()]
    out += ["", "| step: line | transfers |", "|---|---|"]
    out += [f"| `{k}` | {v} |" for k, v in result["step_by_line"].items()]
    out += ["", f"Data-dependent shapes in a step (on CUDA the host waits for the device to learn a size; no copy "
                f"of the data): {result['step_syncs']['max']} (median {result['step_syncs']['median']}).", "",
            "| step: function | syncs |", "|---|---|"]
    out += [f"| `{k}` | {v} |" for k, v in result["step_syncs_by_function"].items()]
    out += ["", f"Host arrays made tensors in those {result['steps']} steps, {result['frame_pixels']} pixels a frame "
                f"(on CUDA copies up; on this CPU views: `cell_votes.py:on_device` is a view of all the votes here, "
                f"on CUDA it sends the rows marked since the last step; `voxels.py:device_index` goes up when "
                f"voxels were added; `device_frames.py:_tensor`: a frame's images for the ray draw, once):", "",
            "| step: function | bytes |", "|---|---|"]
    out += [f"| `{k}` | {v} |" for k, v in result["step_uploads_by_function"].items()]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--profile", default="orin-agx", help="profile whose mapping settings run (torch backend, CPU)")
    ap.add_argument("--frames", type=int, default=8, help="frames of the tiny simulated scene")
    ap.add_argument("--out", default="", help="write <out>.json and <out>.md")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "scene"
        make_scene(scene, dataclasses.replace(PRESETS["tiny"], frames=max(args.frames, 4)))
        frames = [f for _, f in zip(range(args.frames), open_sequence(scene))]
        result = count_transfers(lean_torch_settings(args.profile), frames)
    text = _markdown(result, args.profile)
    print(text)
    if args.out:
        Path(args.out).with_suffix(".json").write_text(json.dumps(result, indent=1) + "\n")
        Path(args.out).with_suffix(".md").write_text(f"<!-- python -m benchmarks.host_transfers --profile "
                                                     f"{args.profile} --frames {args.frames} --out {args.out} -->\n"
                                                     + text)
    return result


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING)
    main()
