"""Per-frame, per-component wall-clock timings (the paper's Table I components and more).

A :class:`Timings` collects durations keyed by component name for each frame (``with
timings.time("training"):``) and summarises them as median / p95 / mean / count in ms. Component
names used by the mapper, in the paper's order: ``read`` (data reading & preprocessing),
``priors`` (octree SDF priors), ``texture`` (texture pattern determination), ``keyframes``
(keyframe policy), ``training`` (map training); plus ``mesh`` and ``render`` for queries.

A :class:`DurationLog` attached as a ``Timings`` sink writes every duration as a JSON line
(``{"unix", "component", "ms"}``) to a run's ``timings.jsonl``, rotated past a size cap.
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

PAPER_COMPONENTS = ("read", "priors", "texture", "keyframes", "training")
LABELS = {"read": "data reading & preprocessing", "priors": "octree SDF priors",
          "texture": "texture pattern determination", "keyframes": "keyframe policy",
          "training": "map training", "idle_training": "training step (its own thread)", "mesh": "mesh extraction",
          "render": "render at pose",
          "frame": "whole frame", "ingest": "ingest (zenoh callback)", "queue_wait": "queue wait",
          "integration": "frame integration (no training)", "color_base": "colour base fusion",
          "integration_wait": "integration's wait for the map",
          "association": "pose association", "frame_delay": "frame age when mapped", "checkpoint": "checkpoint write",
          "free_space": "free space", "cell_votes": "cell votes",
          "residual_check": "colour residual check (training thread)"}


@dataclass
class Timings:
    """Durations per component: the last ``window`` of each for median / p95, all of them in
    count / total (a long-running service keeps bounded memory)."""

    window: int = 10_000
    samples: dict[str, collections.deque] = field(default_factory=dict)  # seconds
    counts: dict[str, int] = field(default_factory=dict)
    totals: dict[str, float] = field(default_factory=dict)
    sink: Callable[[str, float], None] | None = None  # also called with every duration (a DurationLog)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def __getstate__(self) -> dict:  # a copy takes the durations, not the lock
        return {k: v for k, v in self.__dict__.items() if k != "_lock"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    def add(self, name: str, seconds: float) -> None:
        with self._lock:  # integration and training add from their own threads
            self._add(name, seconds)

    def _add(self, name: str, seconds: float) -> None:
        if name not in self.samples:
            self.samples[name] = collections.deque(maxlen=self.window)
            self.counts[name], self.totals[name] = 0, 0.0
        self.samples[name].append(float(seconds))
        self.counts[name] += 1
        self.totals[name] += float(seconds)
        if self.sink is not None:
            self.sink(name, float(seconds))

    @contextmanager
    def time(self, name: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - t0)

    def summary(self) -> dict[str, dict[str, float]]:
        out = {}
        for name, v in list(self.samples.items()):  # may be called from another thread than add()
            a = 1000 * np.asarray(list(v))
            if len(a) == 0:
                continue
            count, total = self.counts.get(name, len(a)), self.totals.get(name, a.sum() / 1000)
            out[name] = {"median_ms": float(np.median(a)), "p95_ms": float(np.percentile(a, 95)),
                         "mean_ms": float(1000 * total / max(count, 1)), "total_s": float(total), "count": count}
        return out


log = logging.getLogger(__name__)


class DurationLog:
    """Appends ``{"unix", "component", "ms"}`` JSON lines to ``path`` (thread-safe, buffered).
    Past ``max_bytes`` the file moves to ``<path>.1`` (replacing the previous one) and a new one
    starts, so a service that runs for months keeps at most 2x ``max_bytes`` on disk. A write
    error (disk full) is logged once and stops the log; it never reaches the caller."""

    def __init__(self, path: str | Path, max_bytes: int = 64 << 20):
        self.path, self.max_bytes = Path(path), max_bytes
        self._lock = threading.Lock()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._size = self.path.stat().st_size if self.path.exists() else 0
        self._f = open(self.path, "a", buffering=1 << 16)

    def __call__(self, name: str, seconds: float) -> None:
        line = json.dumps({"unix": round(time.time(), 3), "component": name, "ms": round(1000 * seconds, 3)}) + "\n"
        with self._lock:
            if self._f is None:
                return
            try:
                if self._size + len(line) > self.max_bytes:
                    self._f.close()
                    self.path.replace(self.path.with_name(self.path.name + ".1"))
                    self._f, self._size = open(self.path, "a", buffering=1 << 16), 0
                self._f.write(line)
                self._size += len(line)
            except OSError as e:
                log.error("timing log %s stopped: %s", self.path, e)
                self._f = None

    def flush(self) -> None:
        with self._lock:
            if self._f is not None:
                try:
                    self._f.flush()
                except OSError as e:
                    log.error("timing log %s stopped: %s", self.path, e)
                    self._f = None

    def close(self) -> None:
        self.flush()
        with self._lock:
            if self._f is not None:
                self._f.close()
                self._f = None


def read_durations(path: str | Path) -> dict[str, list[float]]:
    """{component: [ms, ...]} from a :class:`DurationLog` file (and its rotated ``.1`` first)."""
    out: dict[str, list[float]] = {}
    p = Path(path)
    for f in (p.with_name(p.name + ".1"), p):
        if f.exists():
            for line in f.read_text().splitlines():
                try:
                    rec = json.loads(line)
                    out.setdefault(rec["component"], []).append(float(rec["ms"]))
                except (ValueError, KeyError):
                    continue  # a line cut short by a crash
    return out


def format_timings(summary: dict[str, dict[str, float]], title: str = "timings", frames: int | None = None) -> str:
    """Markdown table: the paper's components first, then the rest; 'per frame' spreads a
    component that runs on some frames only (texture every 10 frames) over all mapped frames."""
    per_frame = PAPER_COMPONENTS + ("cell_votes", "free_space", "color_base", "integration", "frame")
    order = [c for c in PAPER_COMPONENTS + ("integration", "idle_training", "frame", "mesh", "render") if c in summary]
    order += sorted(set(summary) - set(order))
    rows = [
        f"### {title}",
        "",
        "| component | median [ms] | p95 [ms] | count | per frame [ms] |",
        "|---|---|---|---|---|",
    ]
    for c in order:
        s = summary[c]
        per = f"{1000 * s['total_s'] / frames:.1f}" if frames and c in per_frame else ""
        rows.append(f"| {LABELS.get(c, c)} | {s['median_ms']:.1f} | {s['p95_ms']:.1f} | {s['count']} | {per} |")
    return "\n".join(rows)
