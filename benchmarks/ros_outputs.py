"""Benchmark: the ROS 2 path and the outputs for planners and viewers, against their targets.

1. ROS ingest: the per-message cost of turning CDR colour + depth + camera info + odometry into
   a queued frame (:class:`~h3edge.serving.ros_ingest.RosIngest`, median over frames), and a real
   ``h3edge serve --ros`` fed 640x480 colour + depth at ``--ros-hz`` for ``--ros-seconds`` over
   loopback zenoh: how many pairs the ROS ingest assembled and queued, against what was published
   (the mapper maps what it can; the queue drops the oldest, as for any input).
2. Live mesh updates: a map built frame by frame; after each frame, the blocks that frame changed
   are meshed (as :class:`~h3edge.serving.live.LivePublisher` does) and compared with the whole
   map's mesh at that point: bytes and build time (medians over frames, and the ratio).
3. Signed distance of ``--points`` random points in the map's bounding box (with and without the
   gradient), and a 10 x 10 m slice at 5 cm, on a frozen map copy (medians of ``--repeats``).

Usage: ``python -m benchmarks.ros_outputs [--dataset default] [--frames 40]``; writes
``research/bench_ros_outputs.{md,json}`` by default.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from benchmarks.mapping import open_dataset
from benchmarks.tables import median_time, write_table
from h3edge.config import load_profile
from h3edge.io import ros
from h3edge.io.ros import RosConfig
from h3edge.mapping.distance import distance_slice, signed_distance
from h3edge.mapping.engine import MapEngine
from h3edge.mapping.voxels import unpack
from h3edge.serving.ros_ingest import RosIngest

log = logging.getLogger("benchmarks.ros_outputs")


def _encoded_frames(seq, n: int, cfg: RosConfig) -> list[tuple[bytes, bytes, bytes]]:
    out = []
    for i in range(min(n, len(seq))):
        f = seq[i]
        out.append((ros.serialize(ros.color_message(f.color, 0, "cam", "bgr8")),
                    ros.serialize(ros.depth_message(f.depth, 0, "cam", depth_scale=cfg.depth_scale)),
                    ros.serialize(ros.camera_info_message(f.intrinsics, 0, "cam"))))
    return out


def ingest_cost(seq, repeats: int) -> dict:
    """Median ms to take one colour + depth + camera info + odometry through RosIngest."""
    from h3edge.sim.publish import restamp

    cfg = RosConfig(base_to_camera="identity")
    frames = _encoded_frames(seq, 8, cfg)
    queued: list[bytes] = []
    ing = RosIngest(cfg, queued.append, lambda t, p: None, lambda c, m: None)
    h = {r: ing.handler(r) for r in ("color", "depth", "camera_info", "pose")}
    odom = ros.serialize(ros.odometry_message(np.eye(4), 0, "odom", "base_link"))
    times = []
    for k in range(repeats):
        color, depth, info = frames[k % len(frames)]
        ts = 1_000_000_000 + k * 33_333_333
        t0 = time.perf_counter()
        h["pose"](restamp(odom, ts))
        h["camera_info"](restamp(info, ts))
        h["color"](restamp(color, ts))
        h["depth"](restamp(depth, ts))
        times.append(time.perf_counter() - t0)
    assert len(queued) == repeats, ing.status()
    ms = 1e3 * float(np.median(times))
    return {"ingest_ms": ms, "max_hz": 1e3 / ms, "bytes_per_frame": sum(len(x) for x in frames[0])}


def ingest_live(seq, hz: float, seconds: float, profile: str, work: Path) -> dict:
    """A real ``h3edge serve --ros`` fed at ``hz``: frames published, paired by the ROS ingest, mapped."""
    from h3edge.apps.demo import ServiceProcess, wait_drained
    from h3edge.io.protocol import Keys
    from h3edge.io.zenoh_session import open_session
    from h3edge.serving.client import query, wait_for_service
    from h3edge.sim.publish import publish_ros_sequence

    cfg = RosConfig(base_to_camera="identity")
    state = work / "ros_live"
    svc = ServiceProcess(profile, state, "rosbench", state / "service.log", extra=["--ros", "--base-to-camera",
                                                                                   "identity"])
    try:
        svc.wait_listening()
        keys = Keys.for_map("rosbench")
        with open_session(svc.client_config()) as session:
            wait_for_service(session, keys, timeout=120)
            n = int(hz * seconds)
            encoded = _encoded_frames(seq, 16, cfg)
            t0 = time.perf_counter()
            sent = publish_ros_sequence(session, seq, cfg, rate=hz, pose_rate=2 * hz, frames=n, encoded=encoded)
            pub_s = time.perf_counter() - t0
            time.sleep(1.0)
            st = json.loads(query(session, keys.status, timeout=30))
            wait_drained(session, keys, timeout=120)
    finally:
        svc.stop()
    return {"published": sent["frames"], "publish_hz": sent["frames"] / pub_s, "paired": st["ros"]["frames"],
            "ros_dropped": sum(st["ros"]["dropped"].values()), "received": st["frames"]["received"],
            "queue_full": st["dropped"].get("queue_full", 0), "mapped": st["frames"]["mapped"]}


def mesh_updates(m: MapEngine, seq, frames: int, block_voxels: int, interval_s: float, refresh_s: float) -> dict:
    """Per frame: the changed blocks' meshes against the whole mesh (bytes, seconds), and with the
    refresh share a live update adds (``interval_s / refresh_s`` of the map's blocks, measured on
    the stalest-first blocks of that size: here a random sample of them)."""
    step = max(1, len(seq) // frames)
    rows = []
    for n, i in enumerate(range(0, len(seq), step)[:frames]):
        m.process(seq[i])
        changed = m.take_changed_keys()
        if n < frames // 2 or not len(changed):  # measure once the map has grown
            continue
        view = m.view().frozen()
        t0 = time.perf_counter()
        full = view.mesh().export(file_type="ply")
        t_full = time.perf_counter() - t0
        blocks = np.unique(np.floor_divide(unpack(changed), block_voxels), axis=0)
        t0 = time.perf_counter()
        part = sum(len(mh.export(file_type="ply")) for mh in view.block_meshes(blocks, block_voxels) if len(mh.faces))
        t_part = time.perf_counter() - t0
        every = np.unique(np.floor_divide(unpack(view.voxels.voxel_keys), block_voxels), axis=0)
        k = int(np.ceil(len(every) * interval_s / refresh_s))
        t0 = time.perf_counter()
        stale = every[np.random.default_rng(n).choice(len(every), k, replace=False)]
        refresh = sum(len(mh.export(file_type="ply")) for mh in view.block_meshes(stale, block_voxels) if len(mh.faces))
        t_refresh = time.perf_counter() - t0
        rows.append((part / len(full), t_part / t_full, len(blocks), len(full), t_full,
                     (part + refresh) / len(full), (t_part + t_refresh) / t_full))
    r = np.array(rows)
    return {"frames_measured": len(rows), "bytes_ratio": float(np.median(r[:, 0])),
            "time_ratio": float(np.median(r[:, 1])),
            "bytes_ratio_max": float(r[:, 0].max()), "blocks": float(np.median(r[:, 2])),
            "full_mesh_mb": float(np.median(r[:, 3])) / 1e6, "full_mesh_s": float(np.median(r[:, 4])),
            "bytes_ratio_with_refresh": float(np.median(r[:, 5])), "time_ratio_with_refresh": float(np.median(r[:, 6]))}


def planner_queries(m: MapEngine, points: int, repeats: int) -> dict:
    view = m.view().frozen()
    c = (unpack(view.voxels.voxel_keys) + 0.5) * view.voxel_size
    lo, hi = c.min(0), c.max(0)
    pts = lo + np.random.default_rng(0).random((points, 3)) * (hi - lo)
    z = float(np.median(c[:, 2]))
    sl = distance_slice(view, z, (lo[0], lo[1]), (lo[0] + 10, lo[1] + 10), 0.05)
    states = np.bincount(signed_distance(view, pts).state, minlength=4)
    return {"sdf_ms": 1e3 * median_time(lambda: signed_distance(view, pts), repeats),
            "sdf_grad_ms": 1e3 * median_time(lambda: signed_distance(view, pts, gradient=True), repeats),
            "slice_ms": 1e3 * median_time(lambda: distance_slice(view, z, (lo[0], lo[1]), (lo[0] + 10, lo[1] + 10),
                                                                  0.05), repeats),
            "slice_cells": int(sl.occupancy.size), "known_share": float(1 - states[0] / points),
            "slice_known_share": float((sl.occupancy >= 0).mean())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", default="default", help="a simulated preset, 'real', or a sequence directory")
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--frames", type=int, default=40, help="frames mapped for the mesh and query measurements")
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--ros-hz", type=float, default=30.0)
    ap.add_argument("--ros-seconds", type=float, default=10.0)
    ap.add_argument("--service-profile", default=str(Path(__file__).resolve().parents[1] / "tests" / "data" /
                                                     "service-test.toml"),
                    help="profile of the live ROS service (mapping is not what this measures)")
    ap.add_argument("--work", type=Path, default=Path("runs/bench_mapping"))
    ap.add_argument("--out", default="research/bench_ros_outputs")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    seq = open_dataset(args.dataset, args.work)
    cost = ingest_cost(seq, 60)
    log.info("ingest %s", cost)
    live = ingest_live(seq, args.ros_hz, args.ros_seconds, args.service_profile, args.work)
    log.info("live %s", live)
    m = MapEngine(load_profile(args.profile).mapping)
    upd = mesh_updates(m, seq, args.frames, 8, 1.0, 60.0)
    log.info("mesh updates %s", upd)
    q = planner_queries(m, args.points, args.repeats)
    log.info("queries %s", q)
    w, h = seq.intrinsics.width, seq.intrinsics.height
    rows = [
        {"what": f"ROS ingest, one {w}x{h} colour + depth + info + odometry", "value": cost["ingest_ms"], "unit": "ms",
         "target": "keeps up with 30 Hz (33 ms)", "met": cost["ingest_ms"] < 33.3},
        {"what": f"live service fed {args.ros_hz:g} Hz for {args.ros_seconds:g} s: pairs queued / published",
         "value": live["paired"] / max(live["published"], 1), "unit": f"{live['paired']}/{live['published']}",
         "target": "every pair reaches the queue", "met": live["paired"] >= 0.98 * live["published"]},
        {"what": "  of those, mapped / dropped by the queue (queue_full)", "value": live["mapped"],
         "unit": f"mapped; {live['queue_full']} queue_full", "target": "excess dropped by the policy", "met": True},
        {"what": "mesh update of one frame's changed blocks / whole mesh, bytes", "value": upd["bytes_ratio"],
         "unit": "ratio", "target": "< 0.10", "met": upd["bytes_ratio"] < 0.10},
        {"what": "  the same, build time", "value": upd["time_ratio"], "unit": "ratio",
         "target": "< 0.10", "met": upd["time_ratio"] < 0.10},
        {"what": "  with the refresh share (1/60 of the blocks: live_interval_s 1, live_refresh_s 60), bytes",
         "value": upd["bytes_ratio_with_refresh"], "unit": "ratio", "target": "< 0.10",
         "met": upd["bytes_ratio_with_refresh"] < 0.10},
        {"what": "  with the refresh share, build time", "value": upd["time_ratio_with_refresh"], "unit": "ratio",
         "target": "< 0.10", "met": upd["time_ratio_with_refresh"] < 0.10},
        {"what": f"signed distance of {args.points} points", "value": q["sdf_ms"], "unit": "ms", "target": "< 100",
         "met": q["sdf_ms"] < 100},
        {"what": f"signed distance + gradient of {args.points} points", "value": q["sdf_grad_ms"], "unit": "ms",
         "target": "(no target)", "met": True},
        {"what": f"slice 10 x 10 m at 5 cm ({q['slice_cells']} cells)", "value": q["slice_ms"], "unit": "ms",
         "target": "< 200", "met": q["slice_ms"] < 200},
    ]
    title = (f"ROS path and map outputs ({args.dataset}, {args.frames} frames, profile {args.profile}; whole mesh "
             f"{upd['full_mesh_mb']:.1f} MB in {upd['full_mesh_s']:.2f} s, {upd['blocks']:.0f} blocks changed per "
             f"frame, max bytes ratio {upd['bytes_ratio_max']:.3f}; {q['known_share']:.0%} of the box known)")
    write_table(args.out, title, [("measurement", lambda r: r["what"], None), ("value", lambda r: r["value"], 3),
                                  ("unit", lambda r: r["unit"], None), ("target", lambda r: r["target"], None),
                                  ("met", lambda r: "yes" if r["met"] else "NO", None)], rows)
    Path(args.out).with_suffix(".json").write_text(json.dumps({"title": title, "rows": rows, "ingest": cost,
                                                               "live": live, "mesh_updates": upd, "queries": q},
                                                              indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
