"""Per-frame, per-component wall-clock timings (the paper's Table I components and more).

A :class:`Timings` collects durations keyed by component name for each frame (``with
timings.time("training"):``) and summarises them as median / p95 / mean / count in ms. Component
names used by the mapper, in the paper's order: ``read`` (data reading & preprocessing),
``priors`` (octree SDF priors), ``texture`` (texture pattern determination), ``keyframes``
(keyframe policy), ``training`` (map training); plus ``mesh`` and ``render`` for queries.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

PAPER_COMPONENTS = ("read", "priors", "texture", "keyframes", "training")
LABELS = {"read": "data reading & preprocessing", "priors": "octree SDF priors",
          "texture": "texture pattern determination", "keyframes": "keyframe policy",
          "training": "map training", "mesh": "mesh extraction", "render": "render at pose",
          "frame": "whole frame"}


@dataclass
class Timings:
    samples: dict[str, list[float]] = field(default_factory=dict)  # seconds

    def add(self, name: str, seconds: float) -> None:
        self.samples.setdefault(name, []).append(float(seconds))

    @contextmanager
    def time(self, name: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - t0)

    def summary(self) -> dict[str, dict[str, float]]:
        out = {}
        for name, v in self.samples.items():
            a = 1000 * np.asarray(v)
            out[name] = {"median_ms": float(np.median(a)), "p95_ms": float(np.percentile(a, 95)),
                         "mean_ms": float(a.mean()), "total_s": float(a.sum() / 1000), "count": len(a)}
        return out


def format_timings(summary: dict[str, dict[str, float]], title: str = "timings", frames: int | None = None) -> str:
    """Markdown table: the paper's components first, then the rest; 'per frame' spreads a
    component that runs on some frames only (texture every 10 frames) over all mapped frames."""
    order = [c for c in PAPER_COMPONENTS + ("frame", "mesh", "render") if c in summary]
    order += sorted(set(summary) - set(order))
    rows = [f"### {title}", "", "| component | median [ms] | p95 [ms] | count | per frame [ms] |", "|---|---|---|---|---|"]
    for c in order:
        s = summary[c]
        per = f"{1000 * s['total_s'] / frames:.1f}" if frames and c not in ("mesh", "render") else ""
        rows.append(f"| {LABELS.get(c, c)} | {s['median_ms']:.1f} | {s['p95_ms']:.1f} | {s['count']} | {per} |")
    return "\n".join(rows)
