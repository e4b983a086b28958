"""Benchmark: map quality against wall-clock time, h3edge beside TSDF fusion, both fed at the
camera's rate (the anytime benchmark).

Each dataset's frames (preloaded, so disk reads time neither method) arrive at ``--hz`` (frame k at
k / hz s) with the service's queue semantics: at most ``--queue`` frames wait and older ones are
skipped (counted). Both methods are scored on the same held-out views (``--views`` of them,
evenly spread) at fixed wall-clock checkpoints: every ``--every-s`` seconds while frames arrive,
at the last frame, and ``--still-s`` seconds after the last frame arrived (the robot standing
still). Scores: PSNR, SSIM, Depth L1, the share of valid pixels rendered more than 5 cm in front
of / behind the sensor depth, the TSDF surface farther than 5 cm from h3edge's mesh (holes,
against the TSDF's mesh at the same checkpoint) and each method's mesh farther than 5 cm from the
scene's own mesh where it has one (the simulated scenes' ``gt_mesh.ply``), else h3edge's farther
than 5 cm from the TSDF's (stray surface).

Datasets (``--datasets``): ``sim`` and ``studio`` (the simulated scenes, trajectories faster than
a hand-held camera's), ``loft`` (the photographic scene at a hand-held pace), ``replica`` (Replica
office0's GT mesh ray-cast along every ``--replica-stride``-th real pose, 1200x680, fed at
hz / stride, the rate those poses were taken at), ``real`` (7-Scenes redkitchen dev), ``tiny``, or
a sequence directory. The shared data are read in place and skipped when absent.

h3edge modes (``--modes``):
- ``live``: what the service runs: every frame that arrives is integrated on the replay thread
  (:meth:`MapEngine.integrate`) while training runs on a thread of its own
  (:class:`~h3edge.mapping.background.BackgroundTraining`);
- ``inline``: the service before that change: :meth:`MapEngine.process` per frame (``iterations``
  training steps inline), training on keyframes only when no frame waits.
h3edge runs in real time; the clock stops while a checkpoint is scored (training held off).
The TSDF peer (Open3D ``VoxelBlockGrid``, ``--tsdf-voxel``) is single-threaded, so its replay is
computed from its measured per-frame integration times (the same queue rule), scored at the same
checkpoints.

Output: OUT.md (one table per dataset: a row per checkpoint and method) and OUT.json, a plot per
dataset (OUT_<dataset>.png: PSNR, SSIM and pixels off against time, both methods) and the held-out
renders at the last frame of the profile's live run (OUT_<dataset>_views.png: sensor | h3edge |
TSDF | h3edge depth error | TSDF depth error; red = > 5 cm in front, blue = > 5 cm behind).

``--render-variant``: the profile's live map scored again at each checkpoint with other render
settings (``render.*``: the same map, so the comparison carries no replay noise), a row each.

    python -m benchmarks.anytime [--datasets sim studio loft replica real] [--hz 30] [--modes live inline]
        [--variant 'base:color_base.cell=0.01'] [--render-variant 'field only:render.base_surface=0']
        [--out research/bench_anytime]
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from benchmarks.mapping import REAL, REPLICA, open_dataset, render_replica, write_comparison
from benchmarks.tables import markdown_table
from h3edge.apps.offline import LAST_FRAME, map_sequence
from h3edge.config import apply_overrides, load_profile, parse_override, parse_variant
from h3edge.eval.evaluate import MeshRenderer, evaluate_views
from h3edge.eval.metrics import far_share_from, mesh_to_mesh
from h3edge.eval.tsdf import TIMED_BLOCKS, TsdfFusion
from h3edge.io.replica import ReplicaSequence
from h3edge.mapping.engine import MapEngine
from h3edge.mapping.raymarch import RenderConfig

log = logging.getLogger("benchmarks.anytime")
MESH_POINTS = 50_000  # surface samples per mesh for the holes share


@dataclass(frozen=True)
class Checkpoint:
    label: str  # "5 s", "last frame", "still 10 s"
    t: float  # s of replay time; the last frame's is when its frame was handled


def checkpoints(n_frames: int, hz: float, every_s: float, still_s: list[float]) -> list[Checkpoint]:
    """The scoring times of a replay of ``n_frames`` at ``hz`` (the last frame's is a placeholder at
    its arrival: each method scores it when it has handled its last frame)."""
    last = (n_frames - 1) / hz
    marks = [Checkpoint(f"{t:g} s", t) for t in np.arange(every_s, last, every_s)]
    marks.append(Checkpoint("last frame", last))
    marks += [Checkpoint(f"still {s:g} s", last + s) for s in still_s]
    return marks


def pick_views(held: list, n: int) -> list:
    idx = np.linspace(0, len(held) - 1, min(n, len(held))).round().astype(int)
    return [held[int(i)] for i in np.unique(idx)]


def score(renderer, views: list, threshold: float, mesh=None, reference=None, truth=None) -> dict:
    """Held-out view scores of ``renderer``; with ``mesh`` and ``reference``, the share of the
    reference surface farther than ``threshold`` from ``mesh`` (holes) and of ``mesh`` farther than
    ``threshold`` from the scene's own mesh where ``truth`` scores it (``far_share_from`` that
    mesh), else from the reference (stray surface)."""
    v = evaluate_views(renderer, views, 1, len(views), threshold)
    out = {"psnr_db": v["psnr_db"], "ssim": v["ssim"], "depth_l1_cm": v["depth_l1_cm"],
           "front_pct": 100 * v["front_share"], "behind_pct": 100 * v["behind_share"]}
    if mesh is not None and reference is not None and len(reference.faces):
        if len(mesh.faces) == 0:
            out["holes_pct"], out["stray_pct"] = 100.0, 0.0
        else:
            d = mesh_to_mesh(mesh, reference, MESH_POINTS, threshold)
            out["holes_pct"] = 100 * d["b_to_a_far_share"]
            out["stray_pct"] = 100 * (d["a_to_b_far_share"] if truth is None else truth(mesh))
    elif mesh is not None and truth is not None and len(mesh.faces):
        out["stray_pct"] = 100 * truth(mesh)
    return out


def replay_tsdf(frames: list, hz: float, queue: int, marks: list[Checkpoint], views: list, threshold: float,
                voxel: float, truth=None, blocks: int = TIMED_BLOCKS) -> tuple[list[dict], dict]:
    """The TSDF peer's replay, timed by its measured integrations; rows per checkpoint, and a
    summary with the meshes at each checkpoint label. ``truth``: scores the stray surface against
    the scene's own mesh (:func:`score`); ``blocks``: the voxel blocks it allocates up front
    (:class:`~h3edge.eval.tsdf.TsdfFusion`)."""
    fusion = TsdfFusion(frames[0].intrinsics, voxel, block_count=blocks)
    rows, meshes, pending = [], {}, list(marks)
    free_at, k, skipped, times = 0.0, 0, 0, []

    def score_until(t: float, last: bool = False) -> None:
        """Score the checkpoints due by ``t``; the last frame's only when ``last`` (its time is
        ``t``); standing still scores what the last frame left (nothing changes)."""
        while pending and (pending[0].label == "last frame") == last and (last or pending[0].t <= t):
            mark = pending.pop(0)
            if mark.label.startswith("still"):
                rows.append({**rows[-1], "checkpoint": mark.label, "t_s": mark.t})
                meshes[mark.label] = meshes["last frame"]
                continue
            mesh = fusion.mesh()
            meshes[mark.label] = mesh
            scores = score(MeshRenderer(mesh), views, threshold, mesh, truth=truth) if len(mesh.faces) else {}
            rows.append({"checkpoint": mark.label, "t_s": t if last else mark.t, "frames_integrated": fusion.frames,
                         "skipped": skipped, **scores})
            last = False

    while k < len(frames):
        start = max(free_at, k / hz)
        arrived = min(len(frames), int(start * hz) + 1)
        if arrived - k > queue:
            skipped += arrived - queue - k
            k = arrived - queue
        score_until(start)
        f = frames[k]
        d = fusion.integrate(f.color, f.depth, f.pose)
        times.append(d)
        free_at = start + d
        k += 1
    score_until(free_at, last=True)
    score_until(float("inf"))
    summary = {"integration_ms_median": 1000 * float(np.median(times)), "frames_integrated": fusion.frames,
               "skipped": skipped}
    return rows, {"meshes": meshes, **summary}


def warm_up(frames: list, settings) -> None:
    """Compile and load every kernel on a throwaway map (as the service does before it maps), so
    that neither the first frames nor the first checkpoint of a replay pay for it."""
    m = MapEngine(settings)
    for f in frames[:3]:
        m.process(f)
    if m.field is not None:
        m.render(frames[0].intrinsics, frames[0].pose)
        m.mesh()


def replay_h3edge(frames: list, settings, hz: float, queue: int, marks: list[Checkpoint], views: list,
                  threshold: float, references: dict, mode: str, picture: tuple | None = None,
                  renders: dict | None = None, truth=None) -> tuple[list[dict], dict, MapEngine]:
    """h3edge's replay in real time through :func:`~h3edge.apps.offline.map_sequence` (``mode``
    live or inline, as the module says); rows per checkpoint, a summary, and the mapper at the end.
    ``picture``: (sequence, path) of the held-out renders beside the TSDF's at the last frame.
    ``renders``: label -> :class:`~h3edge.mapping.raymarch.RenderConfig` the same map is also
    scored with at each checkpoint; their rows go to ``renders_rows[label]`` in the summary."""
    warm_up(frames, settings)
    mapper = MapEngine(settings)
    rows: list[dict] = []
    render_rows: dict[str, list[dict]] = {label: [] for label in renders or {}}

    def score_now(label: str, t: float, results: list) -> None:
        skipped = sum(r.reason == "queue_full" for r in results)
        row = {"checkpoint": label, "t_s": t, "frames_integrated": mapper.frames_mapped, "skipped": skipped,
               "training_steps": sum(mapper.iterations.values())}
        for name, cfg in (renders or {}).items():
            other = dict(row)
            if mapper.field is not None:
                view = mapper.view()
                view.render_cfg = cfg
                other.update(score(view, views, threshold, view.mesh(), references.get(label), truth))
            render_rows[name].append(other)
        if mapper.field is not None:
            row.update(score(mapper, views, threshold, mapper.mesh(), references.get(label), truth))
            if label == "last frame" and picture is not None:
                write_comparison(picture[0], [mapper], MeshRenderer(references[label]), picture[1], threshold)
        rows.append(row)
        log.info("%s %s at %.1f s: %s", mode, label, t, {k: round(v, 3) for k, v in row.items()
                                                          if isinstance(v, float)})

    timed = [(m.label, LAST_FRAME if m.label == "last frame" else m.t) for m in marks]
    results = map_sequence(frames, mapper, progress_every=0, camera_hz=hz, queue_depth=queue,
                              inline=mode == "inline", marks=timed, on_mark=score_now)
    tm = mapper.timings.summary()
    key = "integration" if mode == "live" else "frame"
    summary = {"mode": mode, "frames_integrated": mapper.frames_mapped,
               "skipped": sum(r.reason == "queue_full" for r in results),
               "dropped": sum(not r.mapped and r.reason != "queue_full" for r in results),
               "integration_ms_median": tm.get(key, {}).get("median_ms"),
               "integration_ms_p95": tm.get(key, {}).get("p95_ms"),
               "integration_wait_ms_median": tm.get("integration_wait", {}).get("median_ms"),
               "training_steps": dict(mapper.iterations), "residual_gain": mapper.stats()["residual_gain"],
               "components": tm, "renders_rows": render_rows}
    return rows, summary, mapper


COLUMNS = [("checkpoint", lambda r: r["checkpoint"], None), ("method", lambda r: r["method"], None),
           ("t [s]", lambda r: r.get("t_s"), 1), ("frames", lambda r: r.get("frames_integrated"), None),
           ("skipped", lambda r: r.get("skipped"), None), ("steps", lambda r: r.get("training_steps"), None),
           ("PSNR [dB]", lambda r: r.get("psnr_db"), 2), ("SSIM", lambda r: r.get("ssim"), 3),
           ("Depth L1 [cm]", lambda r: r.get("depth_l1_cm"), 2),
           ("off in front [%]", lambda r: r.get("front_pct"), 2), ("off behind [%]", lambda r: r.get("behind_pct"), 2),
           ("holes [%]", lambda r: r.get("holes_pct"), 1), ("stray [%]", lambda r: r.get("stray_pct"), 1)]


def plot(result: dict, path: Path) -> None:
    """PSNR, SSIM and pixels off (in front + behind) against replay time, one line per method
    (matplotlib: the ``bench`` extra; without it the plot is left out with a warning)."""
    try:
        import matplotlib
    except ImportError:
        log.warning("no plot %s: matplotlib is not installed (pip install 'h3edge[bench]')", path)
        return

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for method, rows in result["runs"].items():
        rows = [r for r in rows if r.get("psnr_db") is not None]
        t = [r["t_s"] for r in rows]
        for ax, key in zip(axes, ("psnr_db", "ssim", "off_pct")):
            ax.plot(t, [r["front_pct"] + r["behind_pct"] if key == "off_pct" else r[key] for r in rows],
                    marker="o", label=method)
    for ax, name in zip(axes, ("held-out PSNR [dB]", "held-out SSIM", "pixels > 5 cm off [%]")):
        ax.set_xlabel("wall-clock time [s]")
        ax.set_title(name)
        ax.axvline(result["last_arrival_s"], color="grey", lw=0.8, ls="--")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{result['title']}: fed at {result['hz']:g} Hz (dashed: last frame arrives)", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def bench_dataset(name: str, seq, settings, variants: dict, args, title: str, threshold: float, out: Path,
                  hz: float, renders: dict | None = None) -> dict:
    """One dataset's replays at ``hz`` (TSDF, then each h3edge run), its plot and its result."""
    frames = [seq[i] for i in range(len(seq) if args.frames is None else min(args.frames, len(seq)))]
    held = getattr(seq, "heldout", None)
    held = [held[i] for i in range(len(held))] if held is not None and len(held) else frames[::10]
    views = pick_views(held, args.views)
    marks = checkpoints(len(frames), hz, args.every_s, args.still_s)
    log.info("%s: %d frames at %g Hz, %d views, checkpoints %s", name, len(frames), hz, len(views),
             [m.label for m in marks])
    gt = Path(getattr(seq, "root", "")) / "gt_mesh.ply"  # the simulated scenes' own mesh
    truth = (far_share_from(trimesh.load(gt, process=False), MESH_POINTS, threshold)
             if getattr(seq, "root", None) is not None and gt.is_file() else None)
    tsdf_rows, tsdf = replay_tsdf(frames, hz, args.queue, marks, views, threshold, args.tsdf_voxel, truth,
                                  args.tsdf_blocks)
    tsdf_label = f"TSDF ({1000 * args.tsdf_voxel:.0f} mm)"
    runs = {tsdf_label: tsdf_rows}
    summaries = {tsdf_label: {k: v for k, v in tsdf.items() if k != "meshes"}}
    runs_h3 = [(f"h3edge {mode}", settings, mode) for mode in args.modes]
    runs_h3 += [(f"h3edge live {label}", st, "live") for label, st in variants.items()]
    picture = out.parent / f"{out.name}_{name}_views.png"
    for label, st, mode in runs_h3:
        shown = mode == "live" and st is settings  # the profile's own live run
        rows, summary = replay_h3edge(frames, st, hz, args.queue, marks, views, threshold, tsdf["meshes"], mode,
                                      (seq, picture) if shown else None, renders if shown else None, truth)[:2]
        gc.collect()  # the run's map goes before the next run starts (held, the next run measured slower: D53-18)
        if not args.components:
            del summary["components"]
        runs[label], summaries[label] = rows, summary
        for r_label, r_rows in summary.pop("renders_rows").items():  # the same map, rendered otherwise
            runs[f"{label}, rendered {r_label}"] = r_rows
            summaries[f"{label}, rendered {r_label}"] = {"mode": mode, "same map as": label}
    result = {"dataset": name, "title": title, "hz": hz, "frames": len(frames), "views": len(views),
              "last_arrival_s": (len(frames) - 1) / hz, "runs": runs, "summaries": summaries}
    plot(result, out.parent / f"{out.name}_{name}.png")
    return result


def format_result(r: dict) -> str:
    rows = []
    for mark in dict.fromkeys(row["checkpoint"] for rs in r["runs"].values() for row in rs):
        for method, rs in r["runs"].items():
            rows += [{**row, "method": method} for row in rs if row["checkpoint"] == mark]
    lines = [markdown_table(f"{r['title']}, fed at {r['hz']:g} Hz ({r['frames']} frames, {r['views']} held-out views)",
                            COLUMNS, rows), ""]
    for method, s in r["summaries"].items():
        if "same map as" in s:
            lines.append(f"- {method}: the map of {s['same map as']}, rendered with other settings")
            continue
        lines.append(f"- {method}: {s['frames_integrated']} frames integrated, {s['skipped']} skipped, "
                     f"integration median {s['integration_ms_median']:.1f} ms"
                     + (f" (p95 {s['integration_ms_p95']:.1f} ms, waiting for a step: median "
                        f"{s['integration_wait_ms_median'] or 0:.1f} ms); training steps {s['training_steps']}"
                        + (f"; colour residual gain at the end {s['residual_gain']:g}"
                           if s.get("residual_gain") is not None else "")
                        if "training_steps" in s else ""))
    return "\n".join(lines)


def render_variant(spec: str, base: RenderConfig) -> tuple[str, RenderConfig]:
    """``'LABEL:render.KEY=VALUE;...'`` -> (label, ``base`` with those render settings, each parsed by
    :func:`~h3edge.config.parse_override`). Not checked against the rest of the settings as a profile
    is: a render setting a profile refuses can still be scored on a map, to show what it did (D53-7)."""
    label, _, sets = spec.partition(":")
    changes = {}
    for item in filter(None, sets.split(";")):
        section, name, value = parse_override(item)
        if section != "render":
            raise SystemExit(f"--render-variant {spec!r}: only render.* settings, got {item!r}")
        changes[name] = value
    return label, dataclasses.replace(base, **changes)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", nargs="+", default=["sim", "studio", "loft", "replica", "real"],
                    help="sim, studio, loft, replica, real, tiny, or a sequence directory")
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--modes", nargs="*", default=["live"], choices=["live", "inline"])
    ap.add_argument("--variant", action="append", default=[], metavar="LABEL:SECTION.KEY=VALUE[;...]",
                    help="one more live h3edge run with these settings changed")
    ap.add_argument("--render-variant", action="append", default=[], metavar="LABEL:render.KEY=VALUE[;...]",
                    help="the profile's live map also scored with these render settings at each checkpoint")
    ap.add_argument("--hz", type=float, default=30.0, help="camera rate the frames arrive at")
    ap.add_argument("--replica-stride", type=int, default=5,
                    help="replica: every n-th of the 2000 poses, fed at hz / n (the rate they were taken at)")
    ap.add_argument("--queue", type=int, default=2, help="frames that may wait; older ones are skipped")
    ap.add_argument("--every-s", type=float, default=5.0)
    ap.add_argument("--still-s", type=float, nargs="*", default=[10.0, 30.0])
    ap.add_argument("--views", type=int, default=8, help="held-out views scored at each checkpoint")
    ap.add_argument("--frames", type=int, help="limit frames per dataset (smoke runs)")
    ap.add_argument("--tsdf-voxel", type=float, default=0.01)
    ap.add_argument("--tsdf-blocks", type=int, default=TIMED_BLOCKS,
                    help="voxel blocks the TSDF peer allocates up front (it grows past them, slowly)")
    ap.add_argument("--components", action="store_true", help="keep h3edge's timing components in the JSON")
    ap.add_argument("--work", default="out/bench_mapping", help="where the simulated scenes are cached")
    ap.add_argument("--out", default="research/bench_anytime", help="writes OUT.md, OUT.json and the pictures")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    profile = load_profile(args.profile)
    settings = apply_overrides(profile.map_settings(), args.set)
    variants = dict(parse_variant(v, settings) for v in args.variant)
    renders = dict(render_variant(v, settings.render) for v in args.render_variant)
    out = Path(args.out)
    titles = {"sim": "default simulated scene", "studio": "studio simulated scene",
              "loft": "photographic simulated scene (loft, hand-held pace)",
              "replica": f"Replica office0 GT mesh along every {args.replica_stride}th real pose (1200x680)",
              "real": "real Kinect v1, 7-Scenes redkitchen dev", "tiny": "tiny simulated scene (160x120)"}
    results = []
    for ds in args.datasets:
        if (ds == "real" and not REAL.is_dir()) or (ds == "replica" and not REPLICA.is_dir()):
            log.warning("%s skipped: %s not present", ds, REAL if ds == "real" else REPLICA)
            continue
        hz, threshold = args.hz, profile.eval.depth_error_threshold
        if ds == "replica":  # the rendered frames are every n-th of a 30 Hz trajectory
            seq = ReplicaSequence(render_replica(REPLICA, Path(args.work) / "replica_office0", args.replica_stride))
            hz = args.hz / args.replica_stride
        else:
            seq = open_dataset({"sim": "default"}.get(ds, ds), Path(args.work))
        name = ds if ds in titles else Path(ds).name  # a preset, or a sequence directory
        r = bench_dataset(name, seq, settings, variants, args, titles.get(ds, ds), threshold, out, hz, renders)
        results.append(r)
        print(format_result(r), flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(results, indent=1, default=str) + "\n")
    out.with_suffix(".md").write_text("\n\n".join(format_result(r) for r in results) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
