"""Benchmark: the mapper's frame time on a sequence, for the checkout on ``PYTHONPATH``.

Maps every frame of a sequence directory with a profile (no evaluation) and prints a one-row
table, appended as a JSON line to ``--out``: the median and mean of the mapper's per-frame times
and the wall time. It imports only what the issue-15 filing code (``fc74dcc``) also has, so two
checkouts can be compared head to head on the same data, alternating, one process each (run it by
path so that the checkout under test is the ``h3edge`` imported)::

    for round in 1 2; do for c in /path/to/old /path/to/new; do
      PYTHONPATH=$c python benchmarks/frame_time.py ../shared/data/7scenes_redkitchen_dev --label $c
    done; done

Medians and ratios measured side by side are the figures to report (the machines are shared).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from h3edge.config import load_profile
from h3edge.io.replica import ReplicaSequence

try:
    from h3edge.mapping.engine import MapEngine
except ImportError:  # checkouts from before the library façade (issue [2/5])
    from h3edge.mapping.mapper import Mapper as MapEngine  # type: ignore[no-redef]

try:
    from h3edge.apps.offline import map_sequence
except ImportError:  # the layout of the issue-15 filing code
    from h3edge.mapping.offline import map_sequence  # type: ignore[no-redef]


def frame_times(sequence: str, profile: str, overrides: list[str]) -> dict:
    """Map every frame of ``sequence``; the frame time summary (ms) and the wall time (s)."""
    settings = load_profile(profile).map_settings()
    if overrides:
        try:
            from h3edge.config import apply_overrides
        except ImportError as exc:  # the filing code maps its profile as it is
            raise SystemExit(f"--set needs a checkout with h3edge.config.apply_overrides: {exc}") from exc
        settings = apply_overrides(settings, overrides)
    mapper = MapEngine(settings)
    t0 = time.perf_counter()
    map_sequence(ReplicaSequence(sequence), mapper, progress_every=10**9)
    ms = 1000 * np.asarray(mapper.timings.samples["frame"], np.float64)
    return {"frames": len(ms), "median_ms": float(np.median(ms)), "mean_ms": float(ms.mean()),
            "wall_s": time.perf_counter() - t0}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", help="a sequence directory (h3edge's dataset format)")
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--label", default="", help="a name for the row (the checkout)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="change the profile's setting")
    ap.add_argument("--out", help="append the row to this JSON-lines file")
    args = ap.parse_args(argv)
    row = {"label": args.label, "sequence": args.sequence, "profile": args.profile, "set": args.set,
           **frame_times(args.sequence, args.profile, args.set)}
    sys.stdout.write("| label | frames | frame median [ms] | frame mean [ms] | wall [s] |\n|---|---|---|---|---|\n"
                     f"| {row['label']} | {row['frames']} | {row['median_ms']:.0f} | {row['mean_ms']:.0f} | "
                     f"{row['wall_s']:.1f} |\n")
    if args.out:
        with open(args.out, "a") as f:
            f.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
