"""Service benchmark: a real ``h3edge serve`` process fed at 30 Hz over loopback zenoh.

Part 1 (default scene, 640x480): stream the scene at ``--rate`` (30 Hz), and while it maps measure
status query latency, mesh query at 2 cm (resolution 5) and 320x240 render latency; ingest
figures (received vs sent, drops by policy, queue depth) and the service's peak RSS.
Part 2 (soak, ``--soak-frames`` at 160x120, looping the tiny scene's trajectory forward in time):
peak RSS against the profile's memory budget plus the runtime's fixed cost (RSS right after
start-up, before the first frame).

Writes research/bench_service.md and .json; prints the tables.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time
from pathlib import Path

import numpy as np

from h3edge.apps.demo import ServiceProcess, wait_drained
from h3edge.io.protocol import Keys, pose_to_json
from h3edge.io.replica import ReplicaSequence
from h3edge.io.zenoh_session import open_session
from h3edge.serving.client import query, wait_for_service
from h3edge.sim.make import PRESETS, ensure_scene
from h3edge.sim.publish import publish_sequence

log = logging.getLogger(__name__)


def _rss_mb(pid: int) -> tuple[float, float]:
    """(current RSS, peak RSS) in MB of a process, from /proc."""
    cur = peak = 0.0
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            cur = int(line.split()[1]) / 1024
        elif line.startswith("VmHWM:"):
            peak = int(line.split()[1]) / 1024
    return cur, peak


def _table(title: str, headers: list[str], rows: list[list[str]]) -> str:
    out = [f"### {title}", "", "| " + " | ".join(headers) + " |", "|---" * len(headers) + "|"]
    return "\n".join(out + ["| " + " | ".join(r) + " |" for r in rows])


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def run_live(seq, profile: str, work: Path, rate: float, map_id: str = "bench") -> dict:
    keys = Keys.for_map(map_id)
    svc = ServiceProcess(profile, work / "state_live", map_id, work / "service_live.log")
    try:
        svc.wait_listening()
        with open_session(svc.client_config()) as s:
            wait_for_service(s, keys, timeout=120)
            base_rss = _rss_mb(svc.proc.pid)[0]
            sent: dict = {}
            pub = threading.Thread(target=lambda: sent.update(publish_sequence(s, seq, keys, rate)), daemon=True)
            t0 = time.perf_counter()
            pub.start()
            time.sleep(4.0)
            while pub.is_alive() and json.loads(query(s, keys.status))["frames"]["mapped"] < 3:
                time.sleep(0.5)
            status_ms = [1000 * _timed(lambda: query(s, keys.status)) for _ in range(30)]
            f = seq[len(seq) // 3]
            req = {"pose": pose_to_json(f.pose), "width": 320, "height": 240}
            render_s = [_timed(lambda: query(s, keys.render, req, timeout=120)) for _ in range(3)]
            mesh_s = [_timed(lambda: query(s, keys.mesh, {"resolution": 5}, timeout=300))]
            pub.join()
            stream_s = time.perf_counter() - t0
            st = wait_drained(s, keys)
            status_idle = [1000 * _timed(lambda: query(s, keys.status)) for _ in range(30)]
            mesh_idle = [_timed(lambda: query(s, keys.mesh, {"resolution": 5}, timeout=300)) for _ in range(2)]
            render_idle = [_timed(lambda: query(s, keys.render, req, timeout=120)) for _ in range(3)]
            prof = json.loads(query(s, keys.profile))
            peak = _rss_mb(svc.proc.pid)[1]
        svc.stop()
    finally:
        if svc.proc.poll() is None:
            svc.kill()
    fr = st["frames"]
    return {"sent": sent.get("frames"), "received": fr["received"], "mapped": fr["mapped"], "dropped": st["dropped"],
            "stream_s": stream_s, "rate_hz": rate, "received_hz": fr["received"] / stream_s,
            "status_ms_mapping": float(np.median(status_ms)), "status_ms_idle": float(np.median(status_idle)),
            "mesh_s_mapping": float(np.median(mesh_s)), "mesh_s_idle": float(np.median(mesh_idle)),
            "render_s_mapping": float(np.median(render_s)), "render_s_idle": float(np.median(render_idle)),
            "frame_ms_median": prof["components"]["frame"]["median_ms"], "rss_start_mb": base_rss,
            "rss_peak_mb": peak, "memory_parts": st["memory"]["parts_bytes"], "keyframes": st["map"]["keyframes"]}


class _Looped:
    """A sequence repeated ``n`` times (for the soak: the publisher stamps fresh times anyway)."""

    def __init__(self, seq, n_frames: int):
        self.seq, self.n = seq, n_frames
        self.root = seq.root
        self.poses = np.stack([seq.poses[i % len(seq)] for i in range(n_frames)])

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int):
        return self.seq[i % len(self.seq)]


def run_soak(profile: str, work: Path, frames: int, rate: float, budget_mb: int) -> dict:
    scene = ensure_scene(work / "scene_tiny", PRESETS["tiny"])
    seq = _Looped(ReplicaSequence(scene), frames)
    keys = Keys.for_map("soak")
    prof_path = work / "soak.toml"
    src = (
        Path(profile) if Path(profile).suffix else Path(__file__).resolve().parents[1] / "profiles" / f"{profile}.toml"
    )
    text = src.read_text()
    lines = [ln for ln in text.splitlines() if not ln.startswith("min_points")]  # 160x120: 3 points per voxel
    text = "\n".join(lines).replace("[voxels]", "[voxels]\nmin_points = 3", 1)
    prof_path.write_text(text + f"\n[service]\nmemory_budget_mb = {budget_mb}\ncheckpoint_interval_s = 30.0\n")
    svc = ServiceProcess(prof_path, work / "state_soak", "soak", work / "service_soak.log")
    samples = []
    try:
        svc.wait_listening()
        with open_session(svc.client_config()) as s:
            wait_for_service(s, keys, timeout=120)
            base = _rss_mb(svc.proc.pid)[0]
            pub = threading.Thread(target=publish_sequence, args=(s, seq, keys, rate), kwargs={"color_encoding": "png"},
                                   daemon=True)
            pub.start()
            while pub.is_alive():
                samples.append(_rss_mb(svc.proc.pid)[0])
                time.sleep(2.0)
            st = wait_drained(s, keys)
            peak = _rss_mb(svc.proc.pid)[1]
        svc.stop()
    finally:
        if svc.proc.poll() is None:
            svc.kill()
    return {"frames_sent": frames, "received": st["frames"]["received"], "mapped": st["frames"]["mapped"],
            "dropped": st["dropped"], "budget_mb": budget_mb, "rss_start_mb": base, "rss_peak_mb": peak,
            "rss_last_quarter_mb": float(np.max(samples[-max(1, len(samples) // 4):])) if samples else None,
            "map_bytes": st["memory"]["total_bytes"], "keyframes": st["map"]["keyframes"],
            "keyframes_evicted": st["map"]["keyframes_evicted"], "voxels": st["map"]["voxels"],
            "within_budget": peak <= budget_mb + base}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--frames", type=int, default=400, help="frames of the default scene to stream")
    ap.add_argument("--soak-frames", type=int, default=3000)
    ap.add_argument("--soak-budget-mb", type=int, default=512)
    ap.add_argument("--skip", nargs="*", default=[], choices=["live", "soak"])
    ap.add_argument("--work", default="out/bench_service")
    ap.add_argument("--out", default="research/bench_service")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    res: dict = {}
    md = []
    if "live" not in args.skip:
        scene = ensure_scene(work / "scene_default", PRESETS["default"])
        seq = ReplicaSequence(scene)
        r = run_live(seq, args.profile, work, args.rate)
        res["live"] = r
        md.append(
            _table(
                f"live: default scene 640x480 streamed at {args.rate:g} Hz ({args.profile})",
                ["measure", "value", "target"],
                [
                    [
                        "frames sent / received / mapped",
                        f"{r['sent']} / {r['received']} / {r['mapped']}",
                        "received = sent",
                    ],
                    ["received rate [Hz]", f"{r['received_hz']:.1f}", "30"],
                    ["dropped (by reason)", json.dumps(r["dropped"]), "queue_full only"],
                    [
                        "status query median [ms] (mapping / idle)",
                        f"{r['status_ms_mapping']:.1f} / {r['status_ms_idle']:.1f}",
                        "< 20",
                    ],
                    [
                        "mesh query 2 cm [s] (mapping / idle)",
                        f"{r['mesh_s_mapping']:.2f} / {r['mesh_s_idle']:.2f}",
                        "< 2",
                    ],
                    [
                        "render 320x240 [s] (mapping / idle)",
                        f"{r['render_s_mapping']:.2f} / {r['render_s_idle']:.2f}",
                        "< 1",
                    ],
                    ["mapper frame median [ms]", f"{r['frame_ms_median']:.0f}", ""],
                    ["RSS after start / peak [MB]", f"{r['rss_start_mb']:.0f} / {r['rss_peak_mb']:.0f}", ""],
                ],
            )
        )
    if "soak" not in args.skip:
        r = run_soak(args.profile, work, args.soak_frames, args.rate, args.soak_budget_mb)
        res["soak"] = r
        md.append(_table(
            f"soak: {args.soak_frames} frames at 160x120, {args.rate:g} Hz, budget {args.soak_budget_mb} MB",
            ["measure", "value"],
            [["frames received / mapped", f"{r['received']} / {r['mapped']}"],
             ["dropped (by reason)", json.dumps(r["dropped"])],
             ["RSS after start (runtime fixed cost) [MB]", f"{r['rss_start_mb']:.0f}"],
             ["RSS peak [MB]", f"{r['rss_peak_mb']:.0f}"],
             ["RSS max over the last quarter [MB]", f"{r['rss_last_quarter_mb']:.0f}"],
             ["map bytes at the end (status) [MB]", f"{r['map_bytes'] / 1e6:.1f}"],
             ["keyframes kept / evicted", f"{r['keyframes']} / {r['keyframes_evicted']}"],
             ["peak <= budget + fixed cost", str(r["within_budget"])]]))
    text = "\n\n".join(md)
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    Path(f"{out}.md").write_text(
        text + f"\n\n`python -m benchmarks.service` ({time.strftime('%Y-%m-%d')}, 2-core CPU)\n"
    )
    Path(f"{out}.json").write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
