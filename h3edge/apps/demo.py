"""The whole system on one machine (``h3edge demo``), and the helpers the integration tests share.

``run_demo``: start ``h3edge serve`` as a real process on a loopback zenoh endpoint, stream the
scene through the publisher, query status, a mesh and a render while it maps, wait for the
mapper to drain, query the final mesh and renders at the evaluation views, evaluate them against
the scene's ground truth, print the metrics, the service's status and its timing table, then stop
the service with SIGTERM (it writes its final checkpoint) and check it exited cleanly.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import trimesh

from h3edge.io.protocol import decode_frame, pose_to_json

log = logging.getLogger(__name__)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServiceProcess:
    """``h3edge serve`` in a child process listening on ``tcp/127.0.0.1:<port>``, no multicast."""

    def __init__(self, profile: str, state_dir: Path, map_id: str, log_path: Path, port: int | None = None,
                 resume: bool = False, extra: list[str] | None = None, env: dict | None = None):
        self.port = port or free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        cmd = [sys.executable, "-m", "h3edge", "serve", "--profile", str(profile), "--map-id", map_id,
               "--state-dir", str(state_dir), "--listen", self.endpoint, "--no-multicast", *(extra or [])]
        if resume:
            cmd.append("--resume")
        log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(log_path, "ab")
        self.proc = subprocess.Popen(cmd, stdout=self._log, stderr=subprocess.STDOUT, env={**os.environ, **(env or {})})

    def wait_listening(self, timeout: float = 120.0) -> None:
        """Until the service's zenoh endpoint accepts connections (it opens after the map is loaded)."""
        end = time.monotonic() + timeout
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"h3edge serve exited with code {self.proc.returncode} (see its log)")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=1.0):
                    return
            except OSError:
                if time.monotonic() > end:
                    raise TimeoutError(
                        f"h3edge serve did not listen on {self.endpoint} within {timeout:.0f} s"
                    ) from None
                time.sleep(0.2)

    def client_config(self):
        from h3edge.io.zenoh_session import zenoh_config

        return zenoh_config(None, "client", [self.endpoint], None, False)

    def stop(self, timeout: float = 120.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout)
        finally:
            self._log.close()

    def kill(self) -> int:
        self.proc.kill()
        rc = self.proc.wait(30)
        self._log.close()
        return rc


class RemoteRenderer:
    """The evaluation's renderer interface answered by the service's render query."""

    def __init__(self, session, keys, timeout: float = 120.0):
        self.session, self.keys, self.timeout = session, keys, timeout

    def render(self, intr, c2w) -> tuple[np.ndarray, np.ndarray]:
        from h3edge.serving.client import query

        req = {"pose": pose_to_json(c2w), "width": intr.width, "height": intr.height,
               "intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy}, "raw": True}
        msg = decode_frame(query(self.session, self.keys.render, req, timeout=self.timeout))
        return msg.color, msg.depth


def wait_drained(session, keys, timeout: float = 600.0) -> dict:
    """Wait until every received frame was mapped or dropped; returns the last status."""
    from h3edge.serving.client import query

    end = time.monotonic() + timeout
    while True:
        s = json.loads(query(session, keys.status, timeout=10))
        f = s["frames"]
        if f["queued"] == 0 and f["mapped"] + f["dropped"] >= f["received"] or time.monotonic() > end:
            return s
        time.sleep(0.5)


def run_demo(seq, profile: str, out: Path, rate: float = 2.0, map_id: str = "demo") -> int:
    from h3edge.config import load_profile
    from h3edge.eval.evaluate import evaluate, format_table
    from h3edge.io.protocol import Keys
    from h3edge.io.zenoh_session import open_session
    from h3edge.profiling.timing import format_timings
    from h3edge.serving.client import query, save_render_reply, wait_for_service
    from h3edge.sim.publish import publish_sequence

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    prof = load_profile(profile)
    keys = Keys.for_map(map_id)
    svc = ServiceProcess(profile, out / "state", map_id, out / "service.log")
    print(f"service: h3edge serve --profile {profile} on {svc.endpoint} (log {out / 'service.log'})")
    rc = 1
    try:
        svc.wait_listening()
        with open_session(svc.client_config()) as session:
            wait_for_service(session, keys, timeout=120)
            mid = len(seq) // 2
            mid_done = threading.Event()

            def on_frame(i: int, n: int) -> None:
                if i == mid:
                    mid_done.set()

            t0 = time.perf_counter()
            pub = threading.Thread(target=publish_sequence, args=(session, seq, keys, rate),
                                   kwargs={"on_frame": on_frame}, daemon=True)
            pub.start()
            print(f"publishing {len(seq)} frames at {rate:g} Hz ...")
            mid_done.wait()
            # queries while it maps
            t = time.perf_counter()
            status = json.loads(query(session, keys.status))
            t_status = time.perf_counter() - t
            t = time.perf_counter()
            (out / "mesh_midway.ply").write_bytes(query(session, keys.mesh, {"format": "ply"}, timeout=120))
            t_mesh = time.perf_counter() - t
            f = seq[mid]
            t = time.perf_counter()
            save_render_reply(query(session, keys.render, {"pose": pose_to_json(f.pose), "width": 320, "height": 240},
                               timeout=120), out / "render_midway")
            t_render = time.perf_counter() - t
            print(f"while mapping (frame {mid} sent, {status['frames']['mapped']} mapped): status "
                  f"{1000 * t_status:.0f} ms, mesh {t_mesh:.1f} s, render 320x240 {t_render:.2f} s "
                  f"-> {out}/mesh_midway.ply, {out}/render_midway_*.png")
            pub.join()
            status = wait_drained(session, keys)
            map_s = time.perf_counter() - t0
            (out / "mesh.ply").write_bytes(query(session, keys.mesh, {"format": "ply"}, timeout=300))
            mesh = trimesh.load(out / "mesh.ply", process=False)
            cfg = dataclasses.replace(prof.eval, max_views=min(prof.eval.max_views, 10))
            res = evaluate(seq, renderer=RemoteRenderer(session, keys), mesh=mesh, cfg=cfg)
            (out / "metrics.json").write_text(json.dumps(res, indent=1) + "\n")
            prof_reply = json.loads(query(session, keys.profile))
            (out / "profile.json").write_text(json.dumps(prof_reply, indent=1) + "\n")
            (out / "status.json").write_text(json.dumps(status, indent=1) + "\n")
            print()
            print(format_table(res, f"live map of {seq.root.name} ({prof.name}, over zenoh)"))
            print()
            print(format_timings(prof_reply["components"], f"service timings ({prof.name}, {prof_reply['device']})",
                                 frames=prof_reply["frames"]))
            fr = status["frames"]
            print(f"\n{fr['received']} frames received, {fr['mapped']} mapped, {fr['dropped']} dropped "
                  f"{status['dropped']} in {map_s:.0f} s; {status['map']['voxels']} voxels, "
                  f"{status['map']['keyframes']} keyframes; outputs in {out}/")
        rc = svc.stop()
        ckpt = out / "state" / map_id / "map.h3ckpt"
        print(f"service stopped with exit code {rc}; checkpoint {ckpt} ({ckpt.stat().st_size / 1e6:.1f} MB)"
              if ckpt.exists() else f"service stopped with exit code {rc}; no checkpoint written")
        return 0 if rc == 0 else 1
    finally:
        if svc.proc.poll() is None:
            svc.kill()
