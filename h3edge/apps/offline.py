"""Map a whole sequence offline and write a run directory (``h3edge map`` and ``h3edge demo``).

DIR/mesh.ply (vertex colours), DIR/renders/ (held-out or training views: colour PNG, 16-bit depth
PNG in mm, and a GT | render strip), DIR/metrics.json + .md (:func:`h3edge.eval.evaluate.evaluate`),
DIR/timings.json + .md (per-component, per-frame), DIR/run.json (profile settings, map stats),
DIR/decoders/{sdf,color}.onnx (the trained decoders, as queries run them), DIR/profile.json (the
timing profile ``h3edge profile report`` reads) and DIR/timings.jsonl (every duration).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from h3edge.config import Profile
from h3edge.eval.evaluate import evaluate, format_table
from h3edge.io.sequence import Sequence, write_color, write_depth
from h3edge.mapping.background import BackgroundTraining
from h3edge.mapping.engine import FrameResult, MapEngine
from h3edge.mapping.onnx_decoders import export_decoders
from h3edge.profiling.progress import ProgressBar
from h3edge.profiling.timing import DurationLog, format_timings

log = logging.getLogger(__name__)


class PausableClock:
    """Seconds since creation, less the time spent inside :meth:`paused` blocks."""

    def __init__(self) -> None:
        self._t0 = time.perf_counter()
        self._paused = 0.0

    def __call__(self) -> float:
        return time.perf_counter() - self._t0 - self._paused

    @contextlib.contextmanager
    def paused(self):
        t = time.perf_counter()
        try:
            yield
        finally:
            self._paused += time.perf_counter() - t


LAST_FRAME = -1.0  # a mark's time: when the last frame has been handled


def map_sequence(seq: Sequence, mapper: MapEngine, frames: int | None = None, stride: int = 1,
                 progress_every: int = 50, camera_hz: float | None = None, settle_s: float = 0.0,
                 queue_depth: int = 2, inline: bool = False, marks: list[tuple[str, float]] = (),
                 on_mark: Callable[[str, float, list], None] | None = None) -> list:
    """Feed every ``stride``-th frame (the first ``frames`` of them) to the mapper.

    ``camera_hz`` None: every frame, one after the other, as fast as the mapper goes (the paper's
    fixed iterations per frame, :meth:`MapEngine.process`). ``camera_hz`` F: a live replay, as the
    service sees a camera: frame k arrives at k / F s of wall time; at most ``queue_depth`` arrived
    frames wait (older ones are skipped, a ``queue_full`` result, as the service's ingest queue drops
    them); each frame taken is integrated (:meth:`MapEngine.integrate`) while training runs on a thread
    of its own (:class:`~h3edge.mapping.background.BackgroundTraining`), as the service runs it.
    ``inline``: the service before that (:meth:`MapEngine.process` per frame, one keyframe step whenever
    no frame waits). ``settle_s``: after the last frame, keep training that long (the robot
    standing still). ``marks``: (label, replay seconds) at which ``on_mark(label, t, results so far)``
    is called with training paused, the map held (:meth:`MapEngine.exclusive`) and the replay clock
    stopped (an evaluation); a time of ``LAST_FRAME`` calls it when the last frame has been
    handled. Returns one
    :class:`~h3edge.mapping.engine.FrameResult` per frame, skipped ones included.
    """
    idx = list(range(0, len(seq), max(1, stride)))[:frames]
    results = []
    clock = PausableClock()
    bar_at = [0]  # frames the progress bar has counted

    bar = ProgressBar(len(idx), "map")

    def progress(n: int) -> None:
        bar.update(n - bar_at[0], voxels=len(mapper.voxels), keyframes=len(mapper.keyframes.keyframes))
        bar_at[0] = n
        if progress_every and n % progress_every == 0:
            log.info("%d/%d frames in, %d voxels, %d keyframes, %d iterations between frames, %.2f s/frame so far",
                     n, len(idx), len(mapper.voxels), len(mapper.keyframes.keyframes),
                     mapper.iterations["between_frames"], clock() / n)

    def map_one(i: int, verb) -> None:
        t0 = clock()
        frame = seq[i]
        results.append(verb(frame, read_seconds=clock() - t0))

    if camera_hz is None:
        with bar:
            for n, i in enumerate(idx):
                map_one(i, mapper.process)
                progress(n + 1)
        return results
    if camera_hz <= 0:
        raise ValueError(f"camera rate must be > 0 Hz, got {camera_hz}")
    last_arrival = (len(idx) - 1) / camera_hz
    # in time order, the last frame's at its arrival (before any timed mark from then on)
    pending = sorted(marks, key=lambda m: (last_arrival, 0) if m[1] == LAST_FRAME else (m[1], 1))

    def mark_due(last: bool = False) -> bool:
        if not pending or on_mark is None or (pending[0][1] == LAST_FRAME) != last:
            return False
        if not last and pending[0][1] > clock():
            return False
        label, _ = pending.pop(0)
        with clock.paused(), (trainer.paused() if trainer else contextlib.nullcontext()), mapper.exclusive():
            on_mark(label, clock(), results)
        return True

    trainer = None if inline else BackgroundTraining(mapper).start()
    verb = mapper.process if inline else mapper.integrate

    def idle(until: float) -> None:
        """Wait for the next event: inline trains one step, live lets its thread train."""
        if inline and mapper.train_between_frames() is not None:
            return
        time.sleep(max(0.0, min(0.01, until - clock())))

    try:
        nxt = 0  # position in idx of the oldest frame not yet mapped or skipped
        while nxt < len(idx):
            if mark_due():
                continue
            arrived = min(len(idx), int(clock() * camera_hz) + 1)
            if arrived > nxt:
                for k in range(nxt, max(nxt, arrived - queue_depth)):  # overflowed the queue
                    results.append(FrameResult(idx[k], False, "queue_full"))
                nxt = max(nxt, arrived - queue_depth)
                map_one(idx[nxt], verb)
                nxt += 1
                progress(nxt)
            else:
                idle(min(nxt / camera_hz, pending[0][1] if pending and pending[0][1] != LAST_FRAME else np.inf))
        while mark_due():  # timed marks passed while the last frames were handled
            pass
        mark_due(last=True)
        t_end = max([last_arrival + settle_s] + [t for _, t in pending])
        while clock() < t_end:
            if not mark_due():
                idle(pending[0][1] if pending else t_end)
        while mark_due():
            pass
    finally:
        bar.close()
        if trainer is not None:
            trainer.stop()
    return results


def write_view_strips(mapper: MapEngine, seq: Sequence, out: Path, views: int = 4) -> None:
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
                evaluate_map: bool = True, settings=None, reference=None, camera_hz: float | None = None,
                settle_s: float = 0.0) -> dict:
    """Map ``seq`` with ``profile`` and write the run directory; returns the run summary.
    ``reference``: a mesh to compare the map's mesh with (a TSDF of the same frames), for data
    without a GT mesh. ``camera_hz`` / ``settle_s``: a live replay (:func:`map_sequence`)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    settings = settings or profile.map_settings()
    mapper = MapEngine(settings)
    (out / "timings.jsonl").write_text("")
    durations = DurationLog(out / "timings.jsonl", max_bytes=1 << 40)  # every duration of the run
    mapper.timings.sink = durations
    t0 = time.perf_counter()
    try:
        results = map_sequence(seq, mapper, frames, stride, camera_hz=camera_hz, settle_s=settle_s)
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
    write_view_strips(mapper, held if held is not None and len(held) else seq, out / "renders")
    durations.flush()
    summary = mapper.timings.summary()
    timings_md = format_timings(summary, f"per-component timings ({profile.name}, {mapper.device})",
                                frames=mapper.frames_mapped)
    (out / "timings.json").write_text(json.dumps({"frames": mapper.frames_mapped, "components": summary,
                                                  "mapping_wall_s": map_s}, indent=1) + "\n")
    (out / "timings.md").write_text(timings_md + "\n")
    from h3edge.profiling.report import profile_document

    stats = mapper.stats()
    (out / "profile.json").write_text(json.dumps(profile_document(
        profile.name, str(mapper.device), mapper.frames_mapped, summary, stats["memory_bytes"], stats["dropped"],
        {"mapping_device": str(mapper.device), "decoders": "torch"}),  # offline renders use the eager modules
        indent=1) + "\n")
    run = {"sequence": str(seq.root), "profile": profile.name, "settings": dataclasses.asdict(settings),
           "frames_in": len(results), "stats": mapper.stats(), "mesh_vertices": len(mesh.vertices),
           "mesh_faces": len(mesh.faces), "mapping_wall_s": map_s,
           "replay": {"camera_hz": camera_hz, "settle_s": settle_s,
                      "skipped": sum(1 for r in results if r.reason == "queue_full"),
                      "iterations": dict(mapper.iterations)}}
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
