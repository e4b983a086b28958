"""The fleet: two real services on loopback found and listed by one wildcard status query."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from h3edge.apps.demo import ServiceProcess
from h3edge.io.zenoh_session import open_session, zenoh_config
from h3edge.serving.fleet import fleet_status, format_fleet

PROFILE = Path(__file__).parent / "data" / "service-test.toml"


def test_fleet_status_lists_every_service(tmp_path):
    services = [ServiceProcess(PROFILE, tmp_path / m, m, tmp_path / f"{m}.log") for m in ("robot-a", "robot-b")]
    try:
        for s in services:
            s.wait_listening()
        endpoints = [s.endpoint for s in services]
        with open_session(zenoh_config(None, "peer", endpoints, None, False)) as session:
            entries = []
            for _ in range(50):  # the services' queryables are declared just after they listen
                entries = fleet_status(session, timeout=2.0)
                if len(entries) == 2:
                    break
        assert [e["map_id"] for e in entries] == ["robot-a", "robot-b"], entries
        for e in entries:
            st = e["status"]
            assert st["map_id"] == e["map_id"] and st["world_frame"] == "world"
            assert st["frames"]["mapped"] == 0 and st["last_frame_age_s"] is None and st["mapper_alive"]
        table = format_fleet(entries, 0.01)
        assert "| robot-a | world | 0 |" in table and "2 map(s)" in table
        cli = [sys.executable, "-m", "h3edge", "fleet", "status", "--mode", "peer", "--no-multicast"]
        for ep in endpoints:
            cli += ["--connect", ep]
        out = subprocess.run(cli, capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        assert "robot-a" in out.stdout and "robot-b" in out.stdout
    finally:
        for s in services:
            s.stop()
