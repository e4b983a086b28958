"""Benchmark: a fleet of h3edge services queried as one map (issue [5/5]).

Starts ``--services`` real services (``h3edge serve``, ``--profile``) on loopback, each mapping its
own consecutive part of one simulated sequence (the same world frame: one site), then measures on
one client session, ``--rounds`` times each, medians reported:

- ``fleet status``: the wildcard status query over every service;
- ``fleet sdf``: signed distance at ``--points`` site-frame points drawn in the union of the maps'
  boxes (:func:`h3edge.serving.fleet.fleet_sdf`: status query, fan-out, merge), beside one map's own
  sdf query of the same points (the client's ``signed_distance``), and the share of the points the
  fleet knows against the best single map::

    python -m benchmarks.fleet --services 3 --points 100000 --out research/bench_fleet

Prints a table and writes OUT.md and OUT.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.mapping import open_dataset
from h3edge.apps.demo import ServiceProcess, wait_drained
from h3edge.io.distance_types import UNKNOWN
from h3edge.io.protocol import Keys
from h3edge.io.zenoh_session import open_session, zenoh_config
from h3edge.serving.client import Client
from h3edge.serving.fleet import fleet_sdf, fleet_status
from h3edge.sim.publish import publish_sequence

log = logging.getLogger("benchmarks.fleet")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default="default", help="a simulated preset or a sequence directory")
    ap.add_argument("--services", type=int, default=3)
    ap.add_argument("--frames", type=int, default=60, help="frames of the sequence, split among the services")
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--work", default="out/bench_mapping", help="where simulated scenes are made")
    ap.add_argument("--out", default="out/bench_fleet")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    seq = open_dataset(args.dataset, Path(args.work))
    n = min(args.frames, len(seq))
    ids = [f"robot-{chr(ord('a') + k)}" for k in range(args.services)]
    parts = np.array_split(np.arange(n), args.services)
    with tempfile.TemporaryDirectory() as tmp:
        services = [ServiceProcess(args.profile, Path(tmp) / m, m, Path(tmp) / f"{m}.log") for m in ids]
        try:
            for s in services:
                s.wait_listening()
            conf = zenoh_config(None, "peer", [s.endpoint for s in services], None, False)
            with open_session(conf) as session:
                for _ in range(50):
                    if len(fleet_status(session, 1.0)) == len(ids):
                        break
                for mid, part in zip(ids, parts):
                    sub = _Frames(seq, part)
                    publish_sequence(session, sub, Keys.for_map(mid), rate=4.0, embed_pose=True)
                    wait_drained(session, Keys.for_map(mid), timeout=600)
                time.sleep(3.0)  # the last frames' steps; the maps keep training meanwhile
                result = _measure(session, conf, ids, args)
        finally:
            for s in services:
                s.stop()
    result.update(dataset=args.dataset, frames=int(n), profile=args.profile)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    table = _table(result)
    print(table)
    out.with_suffix(".md").write_text(table + "\n")
    out.with_suffix(".json").write_text(json.dumps(result, indent=1))
    return 0


class _Frames:
    """The frames ``idx`` of ``seq`` as a sequence of their own (what a publisher streams)."""

    def __init__(self, seq, idx):
        self.seq, self.idx = seq, [int(i) for i in idx]
        self.intrinsics = seq.intrinsics
        self.poses = np.asarray(seq.poses)[self.idx]

    def __len__(self) -> int:
        return len(self.idx)

    def __getitem__(self, k: int):
        return self.seq[self.idx[k]]


def _measure(session, conf, ids: list[str], args) -> dict:
    entries = fleet_status(session, 2.0)
    boxes = np.array([e["status"]["map"]["bounds"] for e in entries], np.float64)
    lo, hi = boxes[:, 0].min(0), boxes[:, 1].max(0)
    pts = np.random.default_rng(0).uniform(lo, hi, (args.points, 3))
    status_s, fleet_s, single_s = [], [], {m: [] for m in ids}
    d = None
    for _ in range(args.rounds):
        t0 = time.perf_counter()
        entries = fleet_status(session, 2.0)
        status_s.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        d = fleet_sdf(session, pts, timeout=30.0)
        fleet_s.append(time.perf_counter() - t0)
        for m in ids:
            with Client(m, conf, timeout=60.0) as c:
                t0 = time.perf_counter()
                one = c.signed_distance(pts)
                single_s[m].append(time.perf_counter() - t0)
                single_known = float(np.mean(one.state != UNKNOWN))
                single_s.setdefault(f"{m}_known", []).append(single_known)
    one_median = {m: statistics.median(single_s[m]) for m in ids}
    return {"services": len(ids), "points": int(args.points), "rounds": int(args.rounds),
            "answered": len(entries), "fleet_status_ms": 1000 * statistics.median(status_s),
            "fleet_sdf_ms": 1000 * statistics.median(fleet_s),
            "one_map_sdf_ms": {m: 1000 * v for m, v in one_median.items()},
            "fleet_over_slowest_map": statistics.median(fleet_s) / max(one_median.values()),
            "fleet_known": float(np.mean(d.state != UNKNOWN)), "missing": d.missing,
            "one_map_known": {m: statistics.median(single_s[f"{m}_known"]) for m in ids},
            "voxels": {e["map_id"]: e["status"]["map"]["voxels"] for e in entries}}


def _table(r: dict) -> str:
    rows = ["| query | median | |", "|---|---|---|",
            f"| fleet status ({r['answered']} maps) | {r['fleet_status_ms']:.0f} ms | target < 200 ms |",
            f"| fleet sdf, {r['points']:,} points | {r['fleet_sdf_ms']:.0f} ms | "
            f"{r['fleet_over_slowest_map']:.2f}x the slowest single map (target < 3x); "
            f"known {100 * r['fleet_known']:.1f} % |"]
    for m, ms in r["one_map_sdf_ms"].items():
        rows.append(f"| {m} sdf, the same points | {ms:.0f} ms | {r['voxels'][m]} voxels; known "
                    f"{100 * r['one_map_known'][m]:.1f} % |")
    return (f"{r['services']} services on loopback ({r['profile']}), {r['frames']} frames of {r['dataset']} split "
            f"among them, {r['rounds']} rounds\n\n" + "\n".join(rows))


if __name__ == "__main__":
    raise SystemExit(main())
