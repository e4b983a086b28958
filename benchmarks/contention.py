"""Benchmark: the mapper on a busy robot CPU, against its fair share.

A robot's CPU also runs perception and planning. This maps the first ``--frames`` frames of a
dataset the paper's way (:meth:`MapEngine.process`: integration + ``iterations`` training steps a
frame, x86-cpu), alone and beside a competing load, for each mapper setup, and reports the median
frame and training-step times and their slowdown against running alone, beside the fair share
(the machine shared equally among the processes that want it: 1 + the number of competing
processes, at most the cores' worth).

Loads (each its own process, started before the mapper and stopped after it):

- ``busy``: one single-threaded busy loop (a planner spinning on one core);
- ``busy2``: two of them;
- ``torch``: a second multi-threaded torch process (matrix products on every core, its OpenMP pool
  left spinning as torch's default does: another learning process).

Setups (``--setups``; each a subprocess, so that the OpenMP environment is read at torch's load):

- ``spin``: every core, OpenMP workers spin after each parallel region (torch's default);
- ``passive``: every core, ``OMP_WAIT_POLICY=PASSIVE`` (what the service and CLI set, :mod:`h3edge.mapping.threads`);
- ``brief``: every core, workers spin for ``GOMP_SPINCOUNT=10000`` iterations, then sleep;
- ``one``: ``[mapper] threads = 1``, passive.

Rounds alternate setups and loads so that drift of the shared machine spreads over all of them::

    python -m benchmarks.contention --dataset real --frames 20 --out research/bench_contention

Prints a table and writes OUT.md and OUT.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

log = logging.getLogger("benchmarks.contention")

SETUPS = {
    "spin": ({"OMP_WAIT_POLICY": "ACTIVE"}, []),
    "passive": ({"OMP_WAIT_POLICY": "PASSIVE"}, []),
    "brief": ({"GOMP_SPINCOUNT": "10000"}, []),
    "one": ({"OMP_WAIT_POLICY": "PASSIVE"}, ["mapper.threads=1"]),
}
_OPENMP_KEYS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "KMP_BLOCKTIME")  # a setup's own values only
LOADS = {"none": [], "busy": ["busy"], "busy2": ["busy", "busy"], "torch": ["torch"]}

_BUSY = "while True:\n    pass\n"
_TORCH = ("import torch\n"
          "a = torch.randn(384, 384)\n"
          "while True:\n"
          "    for _ in range(8):\n"
          "        a = torch.tanh(a @ a * 0.01)\n")


def _environment(**openmp: str) -> dict[str, str]:
    """This environment without its OpenMP settings, plus ``openmp``."""
    return {**{k: v for k, v in os.environ.items() if k not in _OPENMP_KEYS}, **openmp}


def _start_load(kinds: list[str]) -> list[subprocess.Popen]:
    procs = []
    for kind in kinds:
        code = _BUSY if kind == "busy" else _TORCH
        procs.append(subprocess.Popen([sys.executable, "-c", code], env=_environment(),
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    time.sleep(1.5 if procs else 0.0)  # the load running (torch imported) before the mapper starts
    return procs


def _stop_load(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
    for p in procs:
        p.wait()


def worker(dataset: str, frames: int, warmup: int, overrides: list[str], work: Path) -> dict:
    """In the subprocess: map ``warmup`` + ``frames`` frames inline; the timed frames' summary."""
    from benchmarks.mapping import open_dataset
    from h3edge.config import apply_overrides, load_profile
    from h3edge.mapping.engine import MapEngine

    settings = apply_overrides(load_profile("x86-cpu").map_settings(), overrides)
    mapper = MapEngine(settings)
    seq = open_dataset(dataset, work)
    frame_ms, step_ms = [], []
    for i in range(warmup + frames):
        before = len(mapper.timings.samples.get("training", []))
        t0 = time.perf_counter()
        result = mapper.process(seq[i])
        dt = time.perf_counter() - t0
        if i >= warmup and result.mapped:
            frame_ms.append(1000 * dt)
            train = mapper.timings.samples.get("training", [])
            if len(train) > before:
                step_ms.append(1000 * train[-1] / settings.mapper.iterations)
    return {"frames": len(frame_ms), "frame_ms": frame_ms, "step_ms": step_ms}


def _run_worker(setup: str, args) -> dict:
    env_extra, overrides = SETUPS[setup]
    env = _environment(**env_extra)
    cmd = [sys.executable, "-m", "benchmarks.contention", "--worker", "--dataset", args.dataset,
           "--frames", str(args.frames), "--warmup", str(args.warmup), "--work", str(args.work)]
    for o in overrides:
        cmd += ["--set", o]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"worker {setup} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def fair_share(load: str, cores: int) -> float:
    """The slowdown a process-fair share gives the mapper beside ``load`` on ``cores`` cores."""
    others = len(LOADS[load])
    return float(min(1 + others, cores)) if others else 1.0


def summarise(samples: dict, cores: int) -> list[dict]:
    """Rows setup x load: medians over every round's frames and slowdowns against the setup alone."""
    rows = []
    alone_steps = [np.median(np.concatenate([r["step_ms"] for r in by["none"]]))
                   for by in samples.values() if by.get("none")]
    fastest = min(alone_steps) if alone_steps else None
    for setup, by_load in samples.items():
        alone = by_load.get("none")
        for load, runs in by_load.items():
            f = np.concatenate([r["frame_ms"] for r in runs])
            s = np.concatenate([r["step_ms"] for r in runs])
            row = {"setup": setup, "load": load, "frames": len(f), "frame_ms": float(np.median(f)),
                   "frame_p95_ms": float(np.percentile(f, 95)), "step_ms": float(np.median(s)),
                   "step_max_ms": float(s.max()), "fair_share": fair_share(load, cores)}
            if alone:
                fa = np.median(np.concatenate([r["frame_ms"] for r in alone]))
                sa = np.median(np.concatenate([r["step_ms"] for r in alone]))
                row["frame_slowdown"] = row["frame_ms"] / fa
                row["step_slowdown"] = row["step_ms"] / sa
            if fastest:
                row["step_vs_fastest_alone"] = row["step_ms"] / fastest
            rows.append(row)
    return rows


def format_table(rows: list[dict]) -> str:
    lines = ["| setup | load | frames | frame median [ms] | frame p95 [ms] | step median [ms] | step max [ms] | "
             "frame slowdown | step slowdown | step vs the fastest alone | fair share |", "|" + "---|" * 11]
    for r in rows:
        lines.append(f"| {r['setup']} | {r['load']} | {r['frames']} | {r['frame_ms']:.0f} | {r['frame_p95_ms']:.0f} | "
                     f"{r['step_ms']:.0f} | {r['step_max_ms']:.0f} | {r.get('frame_slowdown', float('nan')):.2f}x | "
                     f"{r.get('step_slowdown', float('nan')):.2f}x | "
                     f"{r.get('step_vs_fastest_alone', float('nan')):.2f}x | "
                     f"{r['fair_share']:.1f}x |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default="real", help="real, a simulated preset (default, studio, tiny) or a directory")
    ap.add_argument("--frames", type=int, default=20, help="timed frames a run")
    ap.add_argument("--warmup", type=int, default=3, help="frames mapped first, not timed")
    ap.add_argument("--setups", nargs="+", default=list(SETUPS), choices=list(SETUPS))
    ap.add_argument("--loads", nargs="+", default=["none", "busy", "torch"], choices=list(LOADS))
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--work", type=Path, default=Path("bench_work"))
    ap.add_argument("--out", type=Path, help="writes OUT.md and OUT.json")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--set", action="append", default=[], help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.dataset, args.frames, args.warmup, args.set, args.work)))
        return 0
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    cores = os.cpu_count() or 1
    samples: dict[str, dict[str, list]] = {s: {ld: [] for ld in args.loads} for s in args.setups}
    for rnd in range(args.rounds):
        for load in args.loads:
            for setup in (args.setups if rnd % 2 == 0 else args.setups[::-1]):
                procs = _start_load(LOADS[load])
                try:
                    res = _run_worker(setup, args)
                finally:
                    _stop_load(procs)
                samples[setup][load].append(res)
                log.info("round %d %s beside %s: frame median %.0f ms, step median %.0f ms", rnd, setup, load,
                         np.median(res["frame_ms"]), np.median(res["step_ms"]))
    rows = summarise(samples, cores)
    table = format_table(rows)
    print(table)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        cmd = "python -m benchmarks.contention " + " ".join(argv if argv is not None else sys.argv[1:])
        args.out.with_suffix(".md").write_text(f"<!-- {cmd} ({cores} cores) -->\n{table}\n")
        args.out.with_suffix(".json").write_text(json.dumps({"cores": cores, "rows": rows, "samples": samples},
                                                            indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
