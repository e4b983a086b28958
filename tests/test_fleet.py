"""The fleet: real services on loopback, directly and behind `h3edge router`, found by one wildcard
status query and asked as one map in a shared site frame; checkpoints kept by `h3edge fleet keep`."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from h3edge.apps.demo import ServiceProcess
from h3edge.io.zenoh_session import open_session, zenoh_config
from h3edge.serving.fleet import fleet_sdf, fleet_status, format_fleet

PROFILE = Path(__file__).parent / "data" / "service-test.toml"


def test_merged_distance_is_the_nearest_surface_any_map_knows():
    """merge_distances: per point the nearest surface the maps know, its state and map: inside wins;
    near answers of one surface (within SAME_SURFACE_M of the least) are averaged, a surface farther
    behind is not; free only where no map sees a surface; unknown where no map knows."""
    from h3edge.io.distance_types import FREE, INSIDE, NEAR, UNKNOWN
    from h3edge.serving.fleet import merge_distances

    nan = np.nan
    a = (np.array([0.30, 0.02, nan, 0.10, nan], np.float32), np.array([FREE, NEAR, UNKNOWN, FREE, UNKNOWN], np.uint8),
         np.tile(np.array([1.0, 0, 0], np.float32), (5, 1)))
    b = (np.array([0.05, 0.04, 0.07, -0.03, nan], np.float32), np.array([NEAR, NEAR, NEAR, INSIDE, UNKNOWN], np.uint8),
         np.tile(np.array([0, 1.0, 0], np.float32), (5, 1)))
    sdf, state, grad, source = merge_distances([a, b], 5)
    assert np.allclose(sdf[:4], [0.05, 0.03, 0.07, -0.03]) and np.isnan(sdf[4])  # 0.02 and 0.04: one surface
    assert state.tolist() == [NEAR, NEAR, NEAR, INSIDE, UNKNOWN] and source.tolist() == [1, 0, 1, 1, -1]
    assert np.allclose(grad[0], [0, 1, 0]) and np.allclose(grad[1], [0.5, 0.5, 0]) and np.isnan(grad[4]).all()
    far = (np.array([0.09], np.float32), np.array([NEAR], np.uint8), None)  # another surface 8 cm behind
    sdf, state, grad, source = merge_distances([(np.array([0.01], np.float32), np.array([NEAR], np.uint8), None),
                                                far], 1)
    assert np.allclose(sdf, [0.01]) and source.tolist() == [0] and grad is None
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


def _wait_for(predicate, timeout: float, what: str):
    import time

    end = time.monotonic() + timeout
    while True:
        got = predicate()
        if got:
            return got
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.3)


def test_fleet_behind_a_router_answers_as_one_map_and_keeps_checkpoints(tiny_scene, tmp_path):
    """`h3edge router` on loopback; three services connected to it map a third of the tiny scene
    each, robot-c in a world frame turned 90 degrees and shifted in the site frame (its robot's poses
    in that frame); a fourth service, not on the router, maps every frame. Through the router, as one
    map: the status lists the three; the signed distance at site points is the maps' own answers
    merged (each asked in its frame, gradients turned into the site frame; the same through `h3edge
    fleet sdf`); the merged slice equals the whole map's cell by cell (as two
    maps of the same frames do: the mapping's own error), the depth-composited render sees what the
    whole map sees, the mesh has one part per map in the site frame. robot-a publishes its
    checkpoints and `h3edge fleet keep` keeps them; a checkpoint put under another map's key, or
    with a chunk changed, is not kept. robot-a's disk lost: `serve --resume-from-fleet` brings its
    map back (same frames, same answers). A service killed mid-fan-out, and a map that answers its
    status but never its queries, are named after the deadline."""
    import signal
    import threading
    import time

    import trimesh

    from h3edge.apps.demo import free_port, wait_drained
    from h3edge.geometry.camera import backproject
    from h3edge.io.distance_types import UNKNOWN
    from h3edge.io.protocol import Keys
    from h3edge.io.replica import ReplicaSequence
    from h3edge.io.ros import extrinsic_matrix
    from h3edge.serving.client import Client
    from h3edge.serving.fleet import Fleet, merge_distances
    from h3edge.serving.keeping import CHUNK_BYTES, publish_checkpoint
    from h3edge.sim.publish import SubSequence, publish_sequence

    seq = ReplicaSequence(tiny_scene)
    router_ep = f"tcp/127.0.0.1:{free_port()}"
    procs = [subprocess.Popen([sys.executable, "-m", "h3edge", "router", "--listen", router_ep, "--no-multicast"],
                              stdout=open(tmp_path / "router.log", "ab"), stderr=subprocess.STDOUT)]
    keep_dir = tmp_path / "kept"
    procs.append(subprocess.Popen([sys.executable, "-m", "h3edge", "fleet", "keep", "--dir", str(keep_dir), "--mode",
                                   "client", "--connect", router_ep, "--no-multicast"],
                                  stdout=open(tmp_path / "keep.log", "ab"), stderr=subprocess.STDOUT))
    site_c = "5 2 0 0 0 0.7071067811865476 0.7071067811865476"
    ids = ["robot-a", "robot-b", "robot-c"]

    def robot(mid: str, *extra: str) -> ServiceProcess:
        more = ["--site-from-world", site_c] if mid == "robot-c" else []
        return ServiceProcess(PROFILE, tmp_path / mid, mid, tmp_path / f"{mid}.log",
                              extra=["--connect", router_ep, *more, *extra])

    services = {m: robot(m, *(["--fleet-checkpoints"] if m == "robot-a" else [])) for m in ids}
    whole = ServiceProcess(PROFILE, tmp_path / "whole", "whole", tmp_path / "whole.log")
    try:
        for s in [*services.values(), whole]:
            s.wait_listening()
        conf = zenoh_config(None, "client", [router_ep], None, False)
        with open_session(conf) as session, open_session(zenoh_config(None, "peer", [whole.endpoint], None,
                                                                       False)) as wsession:
            fleet = Fleet(session=session, timeout=10.0)
            _wait_for(lambda: len(fleet_status(session, 2.0)) == 3, 120, "three services behind the router")
            fresh = fleet.status()
            assert all(e["status"]["last_frame_age_s"] is None and e["status"]["mapper_alive"] for e in fresh)
            assert "| robot-a | world | 0 |" in format_fleet(fresh, 0.01) and "3 map(s)" in format_fleet(fresh)
            world_from_site_c = np.linalg.inv(extrinsic_matrix(site_c, "site_from_world"))
            streams = [(session, SubSequence(seq, part, world_from_site_c if mid == "robot-c" else None), mid)
                       for mid, part in zip(ids, np.array_split(np.arange(len(seq)), 3))]
            streams.append((wsession, seq, "whole"))
            # the robots' thirds at 2 Hz (4 services share the cores; a full queue would skip a frame), as long as
            # the whole sequence at 4 Hz
            publishers = [threading.Thread(target=publish_sequence, args=(ses, sub, Keys.for_map(mid)),
                                           kwargs={"rate": 4.0 if mid == "whole" else 2.0, "embed_pose": True})
                          for ses, sub, mid in streams]
            from h3edge.apps.viewer import run_fleet_viewer

            stop_view, views = threading.Event(), {}
            viewer = threading.Thread(target=lambda: views.update(run_fleet_viewer(
                session, save=str(tmp_path / "site.rrd"), stop=stop_view, scan_every_s=2.0)))
            viewer.start()
            for t in publishers:
                t.start()
            for t in publishers:
                t.join()
            for mid in ids:
                st = wait_drained(session, Keys.for_map(mid), 300)
                assert st["frames"]["dropped"] == 0, (mid, st["dropped"])
            wait_drained(wsession, Keys.for_map("whole"), 300)
            time.sleep(2.5)  # a fresh query snapshot of every map
            entries = fleet.status()
            assert [e["map_id"] for e in entries] == ids
            stop_view.set()  # `h3edge view --fleet`: every map in one recording, each placed in the site frame
            viewer.join(60)
            assert sorted(views) == ids and all(v["frames"] >= 1 and v["meshes"] >= 1 for v in views.values()), views
            from rerun.chunk import RrdReader

            summary = RrdReader(str(tmp_path / "site.rrd")).store().summary()
            for mid in ids:
                for entity in ("mesh/", "trajectory", "camera/image"):
                    assert f"/site/{mid}/{entity}" in summary, (mid, entity, summary)
            cli = subprocess.run([sys.executable, "-m", "h3edge", "fleet", "status", "--mode", "client", "--connect",
                                  router_ep, "--no-multicast"], capture_output=True, text=True, timeout=120)
            assert cli.returncode == 0 and all(f"| {m} | world | " in cli.stdout for m in ids), cli.stderr
            assert np.allclose(np.asarray(entries[2]["status"]["site_from_world"])[:3, 3], [5, 2, 0])
            wc = Client("whole", session=wsession, timeout=60)
            box = np.asarray(wc.status()["map"]["bounds"])
            for z in (1.5,):  # mid-height: near the floor the tiny scene's free space is sparse in any map
                fs = fleet.slice(z, box[0, :2], box[1, :2], 0.05)
                ws = wc.slice(z, box[0, :2], box[1, :2], 0.05)
                assert sorted(fs.maps) == ids and not fs.missing
                both = (fs.slice.occupancy >= 0) & (ws.occupancy >= 0)
                assert np.mean((ws.occupancy >= 0) & (fs.slice.occupancy < 0)) < 0.02  # the fleet knows what it knows
                assert np.mean(fs.slice.occupancy[both] == ws.occupancy[both]) > 0.95
                assert set(np.unique(fs.source[fs.source >= 0])) == {0, 1, 2}  # every map gave cells
            f = seq.heldout[len(seq.heldout) // 2]
            r = fleet.render(f.pose, intrinsics=f.intrinsics)
            _, wd = wc.render(f.pose, intrinsics=f.intrinsics)
            assert abs(np.mean(r.depth > 0) - np.mean(wd > 0)) < 0.02
            seen = (r.depth > 0) & (wd > 0)
            assert np.median(np.abs(r.depth - wd)[seen]) < 0.02 and len(np.unique(r.source[seen])) >= 2
            m = fleet.mesh()
            assert sorted(m.meshes) == ids and not m.missing
            parts = trimesh.load(trimesh.util.wrap_as_stream(m.export("glb")), file_type="glb")
            assert sorted(parts.geometry) == ids
            wm = trimesh.load(trimesh.util.wrap_as_stream(wc.mesh("ply")), file_type="ply")
            assert np.abs(trimesh.util.concatenate(list(m.meshes.values())).bounds - wm.bounds).max() < 0.1

            # signed distance at site points: each map asked in its own frame (robot-c's turned and shifted),
            # answers as the maps give them directly, merged, gradients turned into the site frame
            f = seq[len(seq) // 2]
            near = backproject(f.depth, f.intrinsics, f.pose)[::8, ::8][f.depth[::8, ::8] > 0][:300]
            site = np.concatenate([near + np.random.default_rng(0).normal(0, 0.05, near.shape), [[100.0, 100, 100]]])
            d = fleet.signed_distance(site, gradient=True)
            assert sorted(d.maps) == ids and not d.missing
            direct = []
            for mid in d.maps:
                site_from = np.asarray(next(e for e in entries if e["map_id"] == mid)["status"]["site_from_world"])
                got = Client(mid, session=session, timeout=60).signed_distance(
                    (site - site_from[:3, 3]) @ site_from[:3, :3], gradient=True)
                direct.append((got.sdf, got.state, got.gradient @ site_from[:3, :3].T))
            sdf, state, grad, source = merge_distances(direct, len(site))
            # the same answers (the maps train on between the queries, after a snapshot's 2 s: mm)
            assert np.mean(d.state == state) > 0.95 and (d.state[-1] == UNKNOWN) and d.source[-1] == -1
            both = (d.state != UNKNOWN) & (state != UNKNOWN)
            assert both.mean() > 0.5 and np.mean(np.abs(d.sdf[both] - sdf[both]) < 0.005) > 0.95
            finite = both & np.isfinite(grad).all(1) & np.isfinite(d.gradient).all(1)
            assert finite.mean() > 0.4 and np.mean(np.abs(d.gradient[finite] - grad[finite]).max(1) < 0.05) > 0.95
            assert np.mean(d.source[both] == source[both]) > 0.9
            assert (d.source == d.maps.index("robot-c")).sum() > 10  # the turned map answered its share
            np.save(tmp_path / "site.npy", site)
            cli = [sys.executable, "-m", "h3edge", "fleet", "sdf", "--points", str(tmp_path / "site.npy"), "--out",
                   str(tmp_path / "sdf.npz"), "--timeout", "10", "--mode", "client", "--connect", router_ep,
                   "--no-multicast"]
            out = subprocess.run(cli, capture_output=True, text=True, timeout=120)
            assert out.returncode == 0 and f"{len(site)} points" in out.stdout, out.stderr
            got = np.load(tmp_path / "sdf.npz")
            assert sorted(got["maps"].tolist()) == ids and np.mean(got["state"] == d.state) > 0.9

            # robot-a's checkpoints kept on another host
            a = Client("robot-a", session=session, timeout=60)
            a.save()
            manifest = keep_dir / "robot-a" / "manifest.json"
            _wait_for(manifest.exists, 60, "the keeper to keep robot-a's checkpoint")
            kept = json.loads(manifest.read_text())
            assert kept["frames_mapped"] == a.status()["map"]["frames_mapped"]
            # not kept: robot-a's file under robot-b's key; a chunk changed
            ckpt = tmp_path / "robot-a" / "robot-a" / "map.h3ckpt"
            publish_checkpoint(session, "robot-b", ckpt)
            torn = tmp_path / "torn.h3ckpt"
            data = bytearray(ckpt.read_bytes())
            data[min(len(data) - 1, CHUNK_BYTES + 7)] ^= 0xFF
            torn.write_bytes(bytes(data))
            publish_checkpoint(session, "robot-a", torn)
            _wait_for(lambda: (tmp_path / "keep.log").read_text().count("refused (invalid)") >= 2, 60,
                      "the keeper to refuse both")  # in order: robot-b's key first, then the torn one
            assert not (keep_dir / "robot-b" / "map.h3ckpt").exists()
            assert json.loads(manifest.read_text())["sha256"] == kept["sha256"]

            probe = np.asarray(entries[0]["status"]["map"]["bounds"]).mean(0) + np.random.default_rng(1).uniform(
                -1.5, 1.5, (300, 3))
            answered = a.signed_distance(probe)  # the map trains on until it stops: compared within mm below
            assert services["robot-a"].stop() == 0  # its final checkpoint goes to the keeper too
            _wait_for(lambda: json.loads(manifest.read_text())["sha256"] != kept["sha256"]
                      or json.loads(manifest.read_text())["kept_unix"] > kept["kept_unix"], 30, "the final checkpoint")
            final = json.loads(manifest.read_text())
            import hashlib
            import shutil

            shutil.rmtree(tmp_path / "robot-a")  # the robot's disk is lost
            services["robot-a"] = robot("robot-a", "--resume-from-fleet", "--fleet-timeout", "20")
            services["robot-a"].wait_listening()
            _wait_for(lambda: any(e["map_id"] == "robot-a" for e in fleet_status(session, 2.0)), 120, "robot-a back")
            st = a.status()
            assert st["map"]["frames_mapped"] == final["frames_mapped"] == 14 and st["map"]["voxels"] > 0
            restored = (tmp_path / "robot-a" / "robot-a" / "map.h3ckpt").read_bytes()
            assert hashlib.sha256(restored).hexdigest() == final["sha256"]  # the very file it last wrote
            after = a.signed_distance(probe)
            assert np.mean(answered.state == after.state) > 0.95
            known = (answered.state != UNKNOWN) & (after.state != UNKNOWN)
            assert known.sum() > 50 and np.median(np.abs(answered.sdf[known] - after.sdf[known])) < 0.003

            # a service killed (its status a moment old), and a map that answers its status but never its
            # queries: both named in the answer once the deadline passes, not waited for
            entries = fleet.status()
            services["robot-b"].proc.send_signal(signal.SIGKILL)
            services["robot-b"].proc.wait(10)
            hold = threading.Event()
            slow = dict(entries[0]["status"], map_id="slow")
            qs = [session.declare_queryable("h3edge/slow/status",
                                            lambda q: q.reply(q.key_expr, json.dumps(slow).encode())),
                  session.declare_queryable("h3edge/slow/sdf", lambda q: hold.wait(10.0))]
            try:
                t0 = time.monotonic()
                d = fleet_sdf(session, probe, timeout=3.0, entries=[*entries, {"map_id": "slow", "status": slow}])
                took = time.monotonic() - t0
            finally:
                hold.set()
                for q in qs:
                    q.undeclare()
            assert took < 8.0 and {"robot-b", "slow"} <= set(d.missing) and "robot-a" in d.maps, (d.missing, took)
            assert (d.state != UNKNOWN).mean() > 0.3  # the answering maps' answers still merged
    finally:  # every process goes, whatever one of them does
        for s in [*services.values(), whole]:
            try:
                s.stop()
            except Exception:
                s.proc.kill()
        for p in procs:
            p.terminate()
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
