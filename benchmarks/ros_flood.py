"""Benchmark: a real ``h3edge serve --ros`` flooded with oversized ROS images (issue [4/5] case 3).

The red team's case: 10 colour-only and 10 depth-only ~62 MB images and one 4096 x 4096 pair on the
ROS topics took the service from 1,046 MB to a 3,514 MB peak and left it at 2,827 MB, above
x86-cpu's deploy-plan MemoryMax. Here: the service maps ``--frames`` good frames through ROS, then
the flood arrives, then the same good frames again; the service's resident memory (VmRSS) and peak
(VmHWM, from /proc) before and after the flood, the drops by reason, whether the good frames after
the flood map, against the profile's MemoryMax from the deploy plan (budget + runtime measured here +
headroom)::

    python -m benchmarks.ros_flood --out research/bench_ros_flood

Prints a table and writes OUT.md and OUT.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np
import zenoh

from benchmarks.mapping import open_dataset
from benchmarks.service import _rss_mb
from h3edge.apps.demo import ServiceProcess, wait_drained
from h3edge.io import ros
from h3edge.io.protocol import Keys
from h3edge.io.ros import RosConfig
from h3edge.io.zenoh_session import open_session, zenoh_config
from h3edge.serving.client import query
from h3edge.sim.publish import publish_ros_sequence

log = logging.getLogger("benchmarks.ros_flood")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--dataset", default="default")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--work", default="out/bench_mapping")
    ap.add_argument("--out", default="out/bench_ros_flood")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from h3edge.deploy import plan

    limits = plan(args.profile)
    seq = open_dataset(args.dataset, Path(args.work))
    cfg = RosConfig(base_to_camera="identity")
    keys = {role: key.replace("/*", "/RIHS01_h3edge") for role, key in cfg.keys().items()}
    with tempfile.TemporaryDirectory() as tmp:
        svc = ServiceProcess(args.profile, Path(tmp), "flood", Path(tmp) / "service.log",
                             extra=["--ros", "--base-to-camera", "identity"])
        try:
            svc.wait_listening()
            mkeys = Keys.for_map("flood")
            with open_session(zenoh_config(None, "peer", [svc.endpoint], None, False)) as session:
                time.sleep(2.0)
                publish_ros_sequence(session, seq, cfg, rate=2.0, frames=args.frames)
                first = wait_drained(session, mkeys, 300)
                time.sleep(2.0)
                before = _rss_mb(svc.proc.pid)
                pubs = {r: session.declare_publisher(keys[r], congestion_control=zenoh.CongestionControl.BLOCK)
                        for r in ("color", "depth")}
                stamp = time.time_ns()
                big_color = ros.serialize(ros.color_message(np.zeros((4300, 4800, 3), np.uint8), stamp, "cam",
                                                            "bgr8"))
                big_depth = ros.serialize(ros.depth_message(np.ones((5600, 5600), np.float32), stamp, "cam"))
                t0 = time.perf_counter()
                for _ in range(10):
                    pubs["color"].put(big_color)
                for _ in range(10):
                    pubs["depth"].put(big_depth)
                pair = (ros.serialize(ros.color_message(np.zeros((4096, 4096, 3), np.uint8), stamp + 1, "cam")),
                        ros.serialize(ros.depth_message(np.ones((4096, 4096), np.float32), stamp + 1, "cam")))
                pubs["color"].put(pair[0])
                pubs["depth"].put(pair[1])
                flood_s = time.perf_counter() - t0
                sizes = {"color_mb": len(big_color) / 1e6, "depth_mb": len(big_depth) / 1e6,
                         "pair_mb": (len(pair[0]) + len(pair[1])) / 1e6}
                del big_color, big_depth, pair
                time.sleep(5.0)
                after = _rss_mb(svc.proc.pid)
                mid = json.loads(query(session, mkeys.status, timeout=10))
                publish_ros_sequence(session, seq, cfg, rate=2.0, frames=args.frames)
                last = wait_drained(session, mkeys, 300)
                end = _rss_mb(svc.proc.pid)
        finally:
            svc.stop()
    result = {"profile": args.profile, "memory_max": limits["MEMORY_MAX"], "budget_mb": limits["BUDGET_MB"],
              "runtime_mb": limits["RUNTIME_MB"], "sizes": sizes, "flood_s": flood_s,
              "rss_before_mb": before[0], "peak_before_mb": before[1], "rss_after_mb": after[0],
              "peak_after_mb": after[1], "rss_end_mb": end[0], "peak_end_mb": end[1],
              "mapped_before": first["map"]["frames_mapped"], "mapped_end": last["map"]["frames_mapped"],
              "dropped_by_flood": {k: v - first["ros"]["dropped"].get(k, 0) for k, v in mid["ros"]["dropped"].items()
                                   if v != first["ros"]["dropped"].get(k, 0)},
              "dropped_end": last["dropped"], "frames": args.frames}
    table = _table(result)
    print(table)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(table + "\n")
    out.with_suffix(".json").write_text(json.dumps(result, indent=1))
    return 0


def _table(r: dict) -> str:
    s = r["sizes"]
    rows = ["| | resident [MB] | peak so far (VmHWM) [MB] |", "|---|---|---|",
            f"| after {r['frames']} good frames through ROS | {r['rss_before_mb']:.0f} | {r['peak_before_mb']:.0f} |",
            f"| 5 s after the flood | {r['rss_after_mb']:.0f} | {r['peak_after_mb']:.0f} |",
            f"| after {r['frames']} more good frames | {r['rss_end_mb']:.0f} | {r['peak_end_mb']:.0f} |"]
    return (f"`h3edge serve --ros` ({r['profile']}; deploy plan MemoryMax {r['memory_max']}: budget {r['budget_mb']} "
            f"MB + runtime {r['runtime_mb']} MB + headroom). Flood: 10 colour-only images of {s['color_mb']:.1f} MB, "
            f"10 depth-only of {s['depth_mb']:.1f} MB, one 4096 x 4096 pair ({s['pair_mb']:.1f} MB), put in "
            f"{r['flood_s']:.1f} s.\n\n" + "\n".join(rows) +
            f"\n\nDropped by the flood: {r['dropped_by_flood']}. Good frames mapped: {r['mapped_before']} before, "
            f"{r['mapped_end']} after the flood and the second pass (drops at the end: {r['dropped_end']}).")


if __name__ == "__main__":
    raise SystemExit(main())
