"""Map a whole sequence offline and write a run directory (``h3edge map`` and ``h3edge demo``).

DIR/mesh.ply (vertex colours), DIR/renders/ (held-out or training views: colour PNG, 16-bit depth
PNG in mm, and a GT | render strip), DIR/metrics.json + .md (:func:`h3edge.eval.evaluate.evaluate`),
DIR/timings.json + .md (per-component, per-frame), DIR/run.json (profile settings, map stats),
DIR/decoders/{sdf,color}.onnx (the trained decoders, as queries run them), DIR/profile.json (the
timing profile ``h3edge profile report`` reads) and DIR/timings.jsonl (every duration).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path

import numpy as np

from h3edge.config import Profile
from h3edge.eval.evaluate import evaluate, format_table
from h3edge.io.sequence import Sequence, write_color, write_depth
from h3edge.mapping.mapper import Mapper
from h3edge.mapping.onnx_decoders import export_decoders
from h3edge.mapping.timing import DurationLog, format_timings

log = logging.getLogger(__name__)


def map_sequence(seq: Sequence, mapper: Mapper, frames: int | None = None, stride: int = 1,
                 progress_every: int = 50) -> list:
    """Feed every ``stride``-th frame (the first ``frames`` of them) to the mapper."""
    idx = list(range(0, len(seq), max(1, stride)))[:frames]
    results = []
    t_start = time.perf_counter()
    for n, i in enumerate(idx):
        t0 = time.perf_counter()
        frame = seq[i]
        results.append(mapper.process(frame, read_seconds=time.perf_counter() - t0))
        if progress_every and (n + 1) % progress_every == 0:
            log.info("mapped %d/%d frames, %d voxels, %d keyframes, %.2f s/frame so far", n + 1, len(idx),
                     len(mapper.voxels), len(mapper.keyframes.keyframes), (time.perf_counter() - t_start) / (n + 1))
    return results


def write_renders(mapper: Mapper, seq: Sequence, out: Path, views: int = 4) -> None:
    out.mkdir(parents=True, exist_ok=True)
    strips = []
    for i in np.linspace(0, len(seq) - 1, min(views, len(seq))).round().astype(int):
        f = seq[int(i)]
        rgb, depth = mapper.render(f.intrinsics, f.pose)
        write_color(out / f"view_{i:04d}_color.png", rgb)
        write_depth(out / f"view_{i:04d}_depth.png", depth, 1000.0)
        strips.append(np.concatenate([f.color, rgb], 1))
    if strips:
        write_color(out / "gt_vs_render.jpg", np.concatenate(strips, 0), jpeg_quality=90)


def run_offline(seq: Sequence, profile: Profile, out: Path, frames: int | None = None, stride: int = 1,
                evaluate_map: bool = True, settings=None, reference=None) -> dict:
    """Map ``seq`` with ``profile`` and write the run directory; returns the run summary.
    ``reference``: a mesh to compare the map's mesh with (a TSDF of the same frames), for data
    without a GT mesh."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    settings = settings or profile.map_settings()
    mapper = Mapper(settings)
    (out / "timings.jsonl").write_text("")
    durations = DurationLog(out / "timings.jsonl", max_bytes=1 << 40)  # every duration of the run
    mapper.timings.sink = durations
    t0 = time.perf_counter()
    try:
        results = map_sequence(seq, mapper, frames, stride)
    except BaseException:
        durations.close()  # what was logged up to the failure stays readable
        raise
    map_s = time.perf_counter() - t0
    mesh = mapper.mesh()
    mesh.export(out / "mesh.ply")
    (out / "decoders").mkdir(exist_ok=True)
    for name, model in export_decoders(mapper.field).items():  # what queries run, for serving from DIR
        (out / "decoders" / f"{name}.onnx").write_bytes(model)
    held = getattr(seq, "heldout", None)
    write_renders(mapper, held if held is not None and len(held) else seq, out / "renders")
    durations.flush()
    summary = mapper.timings.summary()
    timings_md = format_timings(summary, f"per-component timings ({profile.name}, {mapper.device})",
                                frames=mapper.frames_mapped)
    (out / "timings.json").write_text(json.dumps({"frames": mapper.frames_mapped, "components": summary,
                                                  "mapping_wall_s": map_s}, indent=1) + "\n")
    (out / "timings.md").write_text(timings_md + "\n")
    from h3edge.serving.profile_report import profile_document

    stats = mapper.stats()
    (out / "profile.json").write_text(json.dumps(profile_document(
        profile.name, str(mapper.device), mapper.frames_mapped, summary, stats["memory_bytes"], stats["dropped"],
        {"mapping_device": str(mapper.device), "decoders": "torch"}),  # offline renders use the eager modules
        indent=1) + "\n")
    run = {"sequence": str(seq.root), "profile": profile.name, "settings": dataclasses.asdict(settings),
           "frames_in": len(results), "stats": mapper.stats(), "mesh_vertices": len(mesh.vertices),
           "mesh_faces": len(mesh.faces), "mapping_wall_s": map_s}
    metrics_md = ""
    if evaluate_map:
        res = evaluate(seq, renderer=mapper.renderer(), mesh=mesh, cfg=profile.eval, reference=reference)
        metrics_md = format_table(res, f"map of {seq.root.name} ({profile.name})")
        (out / "metrics.json").write_text(json.dumps(res, indent=1) + "\n")
        (out / "metrics.md").write_text(metrics_md + "\n")
        run["metrics"] = res
    (out / "run.json").write_text(json.dumps(run, indent=1, default=str) + "\n")
    # printed tables: the timings again, now with the evaluation's renders in them
    run["tables"] = "\n\n".join(t for t in (metrics_md, format_timings(mapper.timings.summary(),
                                f"per-component timings ({profile.name}, {mapper.device})",
                                frames=mapper.frames_mapped)) if t)
    durations.close()
    mapper.timings.sink = None
    run["mapper"] = mapper
    return run
