"""The fleet: two real services on loopback found and listed by one wildcard status query."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

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


def test_merged_distance_is_the_nearest_surface_any_map_knows():
    """merge_distances: per point the least signed distance among the maps that know it, its state
    and map; inside wins over a nearer-looking free answer; unknown where no map knows."""
    from h3edge.io.distance_types import FREE, INSIDE, NEAR, UNKNOWN
    from h3edge.serving.fleet import merge_distances

    nan = np.nan
    a = (np.array([0.30, 0.02, nan, 0.10, nan], np.float32), np.array([FREE, NEAR, UNKNOWN, FREE, UNKNOWN], np.uint8),
         np.tile(np.array([1.0, 0, 0], np.float32), (5, 1)))
    b = (np.array([0.05, 0.04, 0.07, -0.03, nan], np.float32), np.array([NEAR, NEAR, NEAR, INSIDE, UNKNOWN], np.uint8),
         np.tile(np.array([0, 1.0, 0], np.float32), (5, 1)))
    sdf, state, grad, source = merge_distances([a, b], 5)
    assert np.allclose(sdf[:4], [0.05, 0.02, 0.07, -0.03]) and np.isnan(sdf[4])
    assert state.tolist() == [NEAR, NEAR, NEAR, INSIDE, UNKNOWN] and source.tolist() == [1, 0, 1, 1, -1]
    assert np.allclose(grad[0], [0, 1, 0]) and np.allclose(grad[1], [1, 0, 0]) and np.isnan(grad[4]).all()
    sdf, state, grad, source = merge_distances([], 3)
    assert np.isnan(sdf).all() and (state == UNKNOWN).all() and grad is None and (source == -1).all()
    from h3edge.serving.fleet import fleet_sdf

    with pytest.raises(ValueError, match="finite"):
        fleet_sdf(None, np.array([[0.0, np.nan, 1.0]]), entries=[])
    # statuses whose site transform or box is malformed cost that map, named, not the query
    odd = [{"map_id": "skewed", "status": {"site_from_world": np.diag([2.0, 1, 1, 1]).tolist(), "map": {}}},
           {"map_id": "short", "status": {"site_from_world": [1, 2, 3], "map": {}}},
           {"map_id": "nan-box", "status": {"map": {"bounds": [[0, 0, 0], [np.nan, 1, 1]]}}},
           {"map_id": "empty", "status": {"map": {"bounds": None}}}]
    d = fleet_sdf(None, np.zeros((2, 3)), entries=odd)
    assert sorted(d.missing) == ["nan-box", "short", "skewed"] and d.skipped == ["empty"] and not d.maps
    assert (d.state == UNKNOWN).all()


def test_fleet_sdf_fans_out_to_the_maps_in_the_site_frame_within_its_deadline(tiny_scene, tmp_path):
    """Two real services mapped the tiny scene, robot-b's world frame 20 m along the site's x axis and
    turned 90 degrees about z (``--site-from-world``): site-frame points near each map are asked of
    that map alone, in its own frame, and come back as that map answers them directly (gradients
    turned into the site frame); points near neither are unknown; a map that answers its status but
    not its queries is named after the deadline, not waited for; the same through `h3edge fleet sdf`."""
    import threading
    import time

    from h3edge.apps.demo import wait_drained
    from h3edge.geometry.camera import backproject
    from h3edge.io.distance_types import UNKNOWN
    from h3edge.io.protocol import Keys
    from h3edge.io.replica import ReplicaSequence
    from h3edge.serving.client import Client
    from h3edge.serving.fleet import fleet_sdf
    from h3edge.sim.publish import publish_sequence

    seq = ReplicaSequence(tiny_scene)
    shift = np.array([20.0, 0.0, 0.0])
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # robot-b's world axes in the site frame
    services = [ServiceProcess(PROFILE, tmp_path / "robot-a", "robot-a", tmp_path / "a.log"),
                ServiceProcess(PROFILE, tmp_path / "robot-b", "robot-b", tmp_path / "b.log",
                               extra=["--site-from-world", "20 0 0 0 0 0.7071067811865476 0.7071067811865476"])]
    try:
        for s in services:
            s.wait_listening()
        conf = zenoh_config(None, "peer", [s.endpoint for s in services], None, False)
        with open_session(conf) as session:
            for mid in ("robot-a", "robot-b"):
                keys = Keys.for_map(mid)
                for _ in range(50):  # its queryables are declared just after it listens
                    if any(e["map_id"] == mid for e in fleet_status(session, 1.0)):
                        break
                publish_sequence(session, seq, keys, rate=4.0, frames=6, embed_pose=True)
                wait_drained(session, keys, timeout=300)
            f = seq[2]
            rng = np.random.default_rng(0)
            z = f.depth[::8, ::8]
            world = backproject(f.depth, f.intrinsics, f.pose)[::8, ::8][z > 0][:200]
            world = world + rng.normal(0, 0.05, world.shape)  # near the surface, both sides
            far = np.array([[100.0, 100.0, 100.0], [-50.0, 3.0, 0.0]])
            site = np.concatenate([world, world @ turn.T + shift, far])
            entries = fleet_status(session, 2.0)
            assert {e["map_id"] for e in entries} == {"robot-a", "robot-b"}
            assert [e["status"]["site_from_world"][0][3] for e in entries] == [0.0, 20.0]
            assert np.allclose(np.asarray(entries[1]["status"]["site_from_world"])[:3, :3], turn)
            d = fleet_sdf(session, site, timeout=10.0, gradient=True, entries=entries)
            assert sorted(d.maps) == ["robot-a", "robot-b"] and not d.missing and not d.skipped
            n = len(world)
            for k, mid in enumerate(("robot-a", "robot-b")):
                with Client(mid, conf) as client:
                    direct = client.signed_distance(world, gradient=True)
                rows = slice(k * n, (k + 1) * n)
                known = direct.state != UNKNOWN
                assert known.mean() > 0.5
                # the same answers (the maps train on between the two queries, after a snapshot's 2 s: mm)
                assert np.mean(d.state[rows] == direct.state) > 0.95
                both = known & (d.state[rows] != UNKNOWN)
                assert np.mean(np.abs(d.sdf[rows][both] - direct.sdf[both]) < 0.005) > 0.95
                assert (np.array(d.maps)[d.source[rows][both]] == mid).all()
                got, want = d.gradient[rows][both], direct.gradient[both] @ (turn.T if k else np.eye(3))
                whole = np.isfinite(want).all(1) & np.isfinite(got).all(1)  # a gradient with a NaN comes back all NaN
                assert np.isnan(got[~np.isfinite(got).all(1)]).all() and whole.mean() > 0.5
                assert np.mean(np.abs(got[whole] - want[whole]).max(1) < 0.05) > 0.95  # in the site frame
            assert (d.state[2 * n:] == UNKNOWN).all() and (d.source[2 * n:] == -1).all()
            np.save(tmp_path / "site.npy", site)
            cli = [sys.executable, "-m", "h3edge", "fleet", "sdf", "--points", str(tmp_path / "site.npy"), "--out",
                   str(tmp_path / "sdf.npz"), "--timeout", "10", "--mode", "peer", "--no-multicast"]
            for s in services:
                cli += ["--connect", s.endpoint]
            out = subprocess.run(cli, capture_output=True, text=True, timeout=120)
            assert out.returncode == 0 and f"{len(site)} points" in out.stdout, out.stderr
            got = np.load(tmp_path / "sdf.npz")
            assert sorted(got["maps"].tolist()) == sorted(d.maps) and got["sdf"].shape == (len(site),)
            assert np.mean(got["state"] == d.state) > 0.9  # the maps may have trained on meanwhile

            # a map that answers its status but never its queries: named once the deadline passes
            slow_status = dict(entries[0]["status"], map_id="slow")
            hold = threading.Event()

            def on_status(q):
                q.reply(q.key_expr, json.dumps(slow_status).encode())

            def on_sdf(q):
                hold.wait(10.0)

            qs = [session.declare_queryable("h3edge/slow/status", on_status),
                  session.declare_queryable("h3edge/slow/sdf", on_sdf)]
            try:
                t0 = time.monotonic()
                d = fleet_sdf(session, site, timeout=3.0)
                took = time.monotonic() - t0
            finally:
                hold.set()
                for q in qs:
                    q.undeclare()
            assert "slow" in d.missing and sorted(d.maps) == ["robot-a", "robot-b"] and took < 6.0, (d.missing, took)
            assert (d.state[:2 * n] != UNKNOWN).mean() > 0.5  # the two maps' answers still merged
    finally:
        for s in services:
            s.stop()
