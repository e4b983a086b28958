"""Benchmark: a fleet of h3edge services behind one zenoh router, queried as one map (issue [5/5]).

Starts ``h3edge router`` and ``--services`` real services (``h3edge serve``, ``--profile``) connected to
it on loopback, each mapping its own consecutive part of one simulated sequence in its own world
frame, placed in the shared site frame by ``--site-from-world`` (robot-a: the site frame; the others
turned and shifted, their robots' poses given in their own frames), plus ``h3edge fleet keep``. Two
more services, not on the router, map every frame (``whole``, ``whole-2``: the reference, and the
mapping's own run-to-run error). Then, on one client session through the router, medians of
``--rounds``:

- ``fleet status``: the wildcard status query over the services;
- ``fleet sdf``: signed distance at ``--points`` site-frame points drawn in the union of the maps'
  boxes, beside each map's own sdf query of the same points (moved into its frame);
- ``fleet slice``: the merged occupancy slice at three heights against the slice of the map of all
  frames, cell by cell (occupancy agreement where both know the cell, and the cells one knows and
  the other not), beside the same figures for the two maps of all frames (the mapping's own error);
- a service killed (SIGKILL) just before a fan-out: the fan-out's time against its deadline;
- robot-a's checkpoint kept by the keeper: robot-a stopped, its state directory deleted, restarted
  with ``--resume-from-fleet``; the restored file against the kept one (SHA-256) and its answers at
  the same points against those just before it stopped::

    python -m benchmarks.fleet --services 3 --frames 60 --points 100000 --out research/bench_fleet

Prints a table and writes OUT.md and OUT.json.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from benchmarks.mapping import open_dataset
from h3edge.apps.demo import ServiceProcess, free_port, wait_drained
from h3edge.io.distance_types import UNKNOWN
from h3edge.io.protocol import Keys
from h3edge.io.ros import extrinsic_matrix
from h3edge.io.zenoh_session import open_session, zenoh_config
from h3edge.serving.client import Client
from h3edge.serving.fleet import Fleet, fleet_sdf
from h3edge.sim.publish import SubSequence, publish_sequence

log = logging.getLogger("benchmarks.fleet")
def _place(k: int) -> str:
    """Where robot k's world frame lies in the site frame: robot-a the site frame, the others turned
    about z and shifted."""
    angle = [0.0, np.pi / 2, np.pi, -np.pi / 4][k % 4]
    shift = [(0, 0), (20, 0), (0, 30), (-25, -5)][k % 4]
    return f"{shift[0]} {shift[1]} 0 0 0 {np.sin(angle / 2):.15f} {np.cos(angle / 2):.15f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default="default", help="a simulated preset or a sequence directory")
    ap.add_argument("--services", type=int, default=3)
    ap.add_argument("--frames", type=int, default=60, help="frames of the sequence, split among the services")
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--rate", type=float, default=1.0, help="frames per second each robot streams (five services "
                    "share the machine's cores: faster, and frames are dropped by the queue policy)")
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--work", default="out/bench_mapping", help="where simulated scenes are made")
    ap.add_argument("--out", default="out/bench_fleet")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    seq = open_dataset(args.dataset, Path(args.work))
    n = min(args.frames, len(seq))
    ids = [f"robot-{chr(ord('a') + k)}" for k in range(args.services)]
    places = {m: _place(k) for k, m in enumerate(ids)}
    parts = np.array_split(np.arange(n), args.services)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        router_ep = f"tcp/127.0.0.1:{free_port()}"
        logs = open(tmp / "procs.log", "ab")
        procs = [subprocess.Popen([sys.executable, "-m", "h3edge", "router", "--listen", router_ep, "--no-multicast"],
                                  stdout=logs, stderr=subprocess.STDOUT),
                 subprocess.Popen([sys.executable, "-m", "h3edge", "fleet", "keep", "--dir", str(tmp / "kept"),
                                   "--mode", "client", "--connect", router_ep, "--no-multicast"],
                                  stdout=logs, stderr=subprocess.STDOUT)]

        def robot(mid: str, *extra: str) -> ServiceProcess:
            return ServiceProcess(args.profile, tmp / mid, mid, tmp / f"{mid}.log",
                                  extra=["--connect", router_ep, "--site-from-world", places[mid], *extra])

        services = {m: robot(m, *(["--fleet-checkpoints"] if m == ids[0] else [])) for m in ids}
        wholes = {m: ServiceProcess(args.profile, tmp / m, m, tmp / f"{m}.log") for m in ("whole", "whole-2")}
        try:
            for s in [*services.values(), *wholes.values()]:
                s.wait_listening()
            conf = zenoh_config(None, "client", [router_ep], None, False)
            with open_session(conf) as session:
                fleet = Fleet(session=session, timeout=30.0)
                for _ in range(100):
                    if len(fleet_status_ok(fleet)) == len(ids):
                        break
                    time.sleep(0.2)
                streams = []
                for mid, part in zip(ids, parts):
                    world_from_site = np.linalg.inv(extrinsic_matrix(places[mid], "site_from_world"))
                    streams.append((session, SubSequence(seq, part, world_from_site), mid))
                wsessions = {m: open_session(zenoh_config(None, "peer", [w.endpoint], None, False))
                             for m, w in wholes.items()}
                streams += [(wsessions[m], SubSequence(seq, np.arange(n)), m) for m in wholes]
                t0 = time.perf_counter()
                threads = [threading.Thread(target=publish_sequence, args=(ses, sub, Keys.for_map(mid)),
                                            kwargs={"rate": args.rate, "embed_pose": True})
                           for ses, sub, mid in streams]
                for t in threads:
                    t.start()
                for t in threads:
                    t.join()
                frames = {}
                for ses, _, mid in streams:
                    f = wait_drained(ses, Keys.for_map(mid), timeout=1200)["frames"]
                    frames[mid] = {"received": f["received"], "mapped": f["mapped"]}
                log.info("mapped in %.0f s", time.perf_counter() - t0)
                time.sleep(3.0)  # the last frames' steps; the maps keep training meanwhile
                result = _measure(session, fleet, wsessions, ids, args)
                result["frames_mapped"] = frames
                result["checkpoint"] = _keep_and_restore(session, fleet, services, robot, ids[0], tmp, args)
                result["killed"] = _kill_during_fan_out(session, fleet, services, ids[-1])
                for s in wsessions.values():
                    s.close()
        finally:
            for s in [*services.values(), *wholes.values()]:
                s.stop()
            for p in procs:
                p.terminate()
                p.wait(30)
            logs.close()
    result.update(dataset=args.dataset, frames=int(n), profile=args.profile, places=places, rate=args.rate)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    table = _table(result)
    print(table)
    out.with_suffix(".md").write_text(table + "\n")
    out.with_suffix(".json").write_text(json.dumps(result, indent=1))
    return 0


def fleet_status_ok(fleet: Fleet) -> list[dict]:
    return [e for e in fleet.status() if "status" in e]


def _site_box(entries: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """The site-frame box around every map's voxel box."""
    corners = []
    for e in entries:
        t = np.asarray(e["status"]["site_from_world"], np.float64)
        b = np.asarray(e["status"]["map"]["bounds"], np.float64)
        c = np.array([[b[i, 0], b[j, 1], b[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        corners.append(c @ t[:3, :3].T + t[:3, 3])
    c = np.concatenate(corners)
    return c.min(0), c.max(0)


def _slice_match(a, b) -> dict:
    """Occupancy of slice ``a`` against slice ``b`` (numpy int8 images): agreement where both know a
    cell, and the shares of cells only one knows."""
    ka, kb = a >= 0, b >= 0
    both = ka & kb
    return {"agree": float(np.mean(a[both] == b[both])) if both.any() else float("nan"),
            "known_a": float(ka.mean()), "known_b": float(kb.mean()),
            "only_a": float(np.mean(ka & ~kb)), "only_b": float(np.mean(kb & ~ka))}


def _measure(session, fleet: Fleet, wsessions: dict, ids: list[str], args) -> dict:
    entries = fleet_status_ok(fleet)
    lo, hi = _site_box(entries)
    pts = np.random.default_rng(0).uniform(lo, hi, (args.points, 3))
    status_s, fleet_s, single_s = [], [], {m: [] for m in ids}
    known_one: dict[str, float] = {}
    d = None
    for _ in range(args.rounds):
        t0 = time.perf_counter()
        entries = fleet_status_ok(fleet)
        status_s.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        d = fleet_sdf(session, pts, timeout=30.0)
        fleet_s.append(time.perf_counter() - t0)
        for e in entries:
            m = e["map_id"]
            t = np.linalg.inv(np.asarray(e["status"]["site_from_world"], np.float64))
            local = pts @ t[:3, :3].T + t[:3, 3]
            with Client(m, session=session, timeout=60.0) as c:
                t0 = time.perf_counter()
                one = c.signed_distance(local)
                single_s[m].append(time.perf_counter() - t0)
            known_one[m] = float(np.mean(one.state != UNKNOWN))
    one_median = {m: statistics.median(single_s[m]) for m in ids}
    # slices: the fleet merged vs the map of all frames; the two maps of all frames vs each other
    whole = {m: Client(m, session=s, timeout=120.0) for m, s in wsessions.items()}
    wbox = np.asarray(whole["whole"].status()["map"]["bounds"])
    slices, slice_ms = [], []
    for z in np.linspace(wbox[0, 2], wbox[1, 2], 5)[1:-1]:
        t0 = time.perf_counter()
        fs = fleet.slice(float(z), wbox[0, :2], wbox[1, :2], 0.05)
        slice_ms.append(1000 * (time.perf_counter() - t0))
        w1 = whole["whole"].slice(float(z), wbox[0, :2], wbox[1, :2], 0.05)
        w2 = whole["whole-2"].slice(float(z), wbox[0, :2], wbox[1, :2], 0.05)
        slices.append({"z": float(z), "cells": int(fs.slice.occupancy.size), "maps": fs.maps,
                       "fleet_vs_whole": _slice_match(fs.slice.occupancy, w1.occupancy),
                       "whole2_vs_whole": _slice_match(w2.occupancy, w1.occupancy)})
    return {"services": len(ids), "points": int(args.points), "rounds": int(args.rounds),
            "answered": len(entries), "fleet_status_ms": 1000 * statistics.median(status_s),
            "fleet_sdf_ms": 1000 * statistics.median(fleet_s),
            "one_map_sdf_ms": {m: 1000 * v for m, v in one_median.items()},
            "fleet_over_slowest_map": statistics.median(fleet_s) / max(one_median.values()),
            "fleet_known": float(np.mean(d.state != UNKNOWN)), "missing": d.missing,
            "one_map_known": known_one, "voxels": {e["map_id"]: e["status"]["map"]["voxels"] for e in entries},
            "slice_ms": statistics.median(slice_ms), "slices": slices}


def _keep_and_restore(session, fleet: Fleet, services: dict, robot, mid: str, tmp: Path, args) -> dict:
    c = Client(mid, session=session, timeout=120.0)
    st = c.status()
    b = np.asarray(st["map"]["bounds"], np.float64)
    probe = np.random.default_rng(1).uniform(b[0], b[1], (20_000, 3))
    before = c.signed_distance(probe)
    services[mid].stop()  # the final checkpoint is published to the keeper as it stops
    manifest = tmp / "kept" / mid / "manifest.json"
    end = time.monotonic() + 60
    while time.monotonic() < end:
        if manifest.exists() and json.loads(manifest.read_text())["frames_mapped"] == st["map"]["frames_mapped"]:
            break
        time.sleep(0.3)
    kept = json.loads(manifest.read_text())
    copy = tmp / "kept-copy.h3ckpt"
    shutil.copy(tmp / "kept" / mid / "map.h3ckpt", copy)
    shutil.rmtree(tmp / mid)  # the robot's disk is lost
    t0 = time.perf_counter()
    services[mid] = robot(mid, "--resume-from-fleet", "--fleet-timeout", "60")
    services[mid].wait_listening()
    restored = c.wait(120)
    restore_s = time.perf_counter() - t0
    sha = hashlib.sha256((tmp / mid / mid / "map.h3ckpt").read_bytes()).hexdigest()
    after = c.signed_distance(probe)
    both = (before.state != UNKNOWN) & (after.state != UNKNOWN)
    diff = np.abs(before.sdf[both] - after.sdf[both])
    from h3edge import Mapper

    local = Mapper.load(copy).signed_distance(probe)  # the kept file read here: the same map?
    same = (local.state != UNKNOWN) & (after.state != UNKNOWN)
    return {"map": mid, "kept_mb": kept["bytes"] / 1e6, "frames_kept": kept["frames_mapped"],
            "frames_restored": restored["map"]["frames_mapped"], "same_file": sha == kept["sha256"],
            "restart_s": restore_s, "state_equal": float(np.mean(before.state == after.state)),
            "sdf_diff_median_mm": 1000 * float(np.median(diff)),
            "sdf_diff_p99_mm": 1000 * float(np.quantile(diff, 0.99)),
            "kept_state_equal": float(np.mean(local.state == after.state)),
            "kept_sdf_diff_max_mm": 1000 * float(np.abs(local.sdf[same] - after.sdf[same]).max(initial=0.0)),
            "points": len(probe)}


def _kill_during_fan_out(session, fleet: Fleet, services: dict, mid: str) -> dict:
    entries = fleet_status_ok(fleet)
    box = _site_box(entries)
    pts = np.random.default_rng(2).uniform(*box, (20_000, 3))
    services[mid].proc.send_signal(signal.SIGKILL)
    services[mid].proc.wait(10)
    t0 = time.perf_counter()
    d = fleet_sdf(session, pts, timeout=3.0, entries=entries)
    return {"map": mid, "deadline_s": 3.0, "took_s": time.perf_counter() - t0, "missing": d.missing,
            "answered": d.maps}


def _table(r: dict) -> str:
    rows = ["| query | median | |", "|---|---|---|",
            f"| fleet status ({r['answered']} maps, through the router) | {r['fleet_status_ms']:.0f} ms | "
            "target < 200 ms |",
            f"| fleet sdf, {r['points']:,} points | {r['fleet_sdf_ms']:.0f} ms | "
            f"{r['fleet_over_slowest_map']:.2f}x the slowest single map (target < 3x); "
            f"known {100 * r['fleet_known']:.1f} % |"]
    for m, ms in r["one_map_sdf_ms"].items():
        rows.append(f"| {m} sdf, the same points | {ms:.0f} ms | {r['voxels'][m]} voxels; known "
                    f"{100 * r['one_map_known'][m]:.1f} % |")
    rows.append(f"| fleet slice (median of {len(r['slices'])} heights) | {r['slice_ms']:.0f} ms | |")
    rows += ["", "| slice at z | fleet vs map of all frames: agree / only fleet / only all-frames | "
             "second map of all frames vs the first (the mapping's own error) |", "|---|---|---|"]
    for s in r["slices"]:
        f, w = s["fleet_vs_whole"], s["whole2_vs_whole"]
        rows.append(f"| {s['z']:.2f} m ({s['cells']} cells) | {100 * f['agree']:.1f} % / {100 * f['only_a']:.1f} % / "
                    f"{100 * f['only_b']:.1f} % | {100 * w['agree']:.1f} % / {100 * w['only_a']:.1f} % / "
                    f"{100 * w['only_b']:.1f} % |")
    k, c = r["killed"], r["checkpoint"]
    rows += ["", f"- {k['map']} killed (SIGKILL) before a fan-out with a {k['deadline_s']:.0f} s deadline: it "
             "returned in "
             f"{k['took_s']:.2f} s, {k['map']} named missing ({', '.join(k['missing']) or 'none'}), answers from "
             f"{', '.join(k['answered'])}.",
             f"- {c['map']}'s checkpoint kept by `fleet keep` ({c['kept_mb']:.1f} MB, {c['frames_kept']} frames); its "
             f"state directory deleted, `serve --resume-from-fleet` up again in {c['restart_s']:.1f} s with "
             f"{c['frames_restored']} frames; the restored file is the kept one: {c['same_file']}; at "
             f"{c['points']:,} points its answers against those just before it stopped (it trained on until then): "
             f"state equal {100 * c['state_equal']:.2f} %, |sdf| difference median {c['sdf_diff_median_mm']:.2f} mm, "
             f"p99 {c['sdf_diff_p99_mm']:.2f} mm; against the kept file read in this process: state equal "
             f"{100 * c['kept_state_equal']:.2f} %, largest |sdf| difference {c['kept_sdf_diff_max_mm']:.3f} mm."]
    mapped = ", ".join(f"{m} {f['mapped']}/{f['received']}" for m, f in r["frames_mapped"].items())
    return (f"{r['services']} services behind one router on loopback ({r['profile']}), {r['frames']} frames of "
            f"{r['dataset']} split among them at {r['rate']:g} Hz, each in its own world frame placed in the site "
            f"frame; 2 more services map every frame (the reference); {r['rounds']} rounds; frames mapped / sent: "
            f"{mapped}\n\n" + "\n".join(rows))


if __name__ == "__main__":
    raise SystemExit(main())
