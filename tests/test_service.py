"""The edge service end to end: a real ``h3edge serve`` process, real zenoh on loopback, the real
publisher and query client; malformed input, error replies, SIGKILL and resume."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
import zenoh

from h3edge.apps.demo import ServiceProcess, wait_drained
from h3edge.eval.evaluate import EvalConfig, evaluate_geometry
from h3edge.eval.metrics import psnr
from h3edge.io.protocol import FrameMessage, Keys, PoseMessage, decode_frame, encode_frame, encode_pose, pose_to_json
from h3edge.io.replica import ReplicaSequence
from h3edge.io.zenoh_session import open_session
from h3edge.mapping.map_file import read_checkpoint
from h3edge.profiling.report import load_document
from h3edge.profiling.timing import read_durations
from h3edge.serving.client import RemoteError, query, wait_for_service
from h3edge.sim.publish import publish_sequence

PROFILE = Path(__file__).parent / "data" / "service-test.toml"
KEYS = Keys.for_map("test")


@pytest.fixture(scope="module")
def served(tiny_scene, tmp_path_factory):
    """A service that mapped the tiny scene streamed by the publisher (poses on their own key)."""
    state = tmp_path_factory.mktemp("state")
    svc = ServiceProcess(PROFILE, state, "test", state / "service.log")
    svc.wait_listening()
    session = open_session(svc.client_config())
    wait_for_service(session, KEYS)
    seq = ReplicaSequence(tiny_scene)
    sent = publish_sequence(session, seq, KEYS, rate=4.0, pose_rate=30.0, jitter_ms=20)
    end = time.monotonic() + 30
    while json.loads(query(session, KEYS.status))["frames"]["received"] < sent["frames"] and time.monotonic() < end:
        time.sleep(0.1)
    status = wait_drained(session, KEYS, timeout=300)
    yield svc, session, seq, sent, status, state
    session.close()
    if svc.proc.poll() is None:
        svc.stop()


def test_maps_streamed_scene(served):
    _, _, seq, sent, status, _ = served
    assert sent["frames"] == len(seq)
    f = status["frames"]
    assert f["received"] == len(seq)
    assert f["mapped"] >= 0.6 * len(seq), status  # the rest dropped by the queue policy, not lost
    assert f["mapped"] + f["dropped"] == f["received"]
    assert set(status["dropped"]) <= {"queue_full"}, status["dropped"]
    assert status["map"]["voxels"] > 100 and status["map"]["keyframes"] >= 1
    assert status["memory"]["total_bytes"] > 0 and status["memory"]["budget_bytes"] == 512 << 20
    assert status["mapper_alive"]
    tr = status["training"]  # every frame integrated; training on its own thread, none inline
    assert tr["iterations"]["frame"] == 0 and tr["iterations"]["between_frames"] > 0, tr
    assert tr["iterations_per_s"] >= 0 and (tr["between_frames_share"] is None or 0 <= tr["between_frames_share"] <= 1)
    inf = status["inference"]  # what the mapper and the query decoders run on
    assert inf["mapping_device"] == "cpu" and inf["decoders"] in ("onnx", "torch")
    if inf["decoders"] == "onnx":
        assert inf["active"] and inf["onnxruntime"].startswith("onnxruntime")


def test_status_is_fast(served):
    _, session, *_ = served
    times = []
    for _ in range(5):
        t = time.perf_counter()
        json.loads(query(session, KEYS.status))
        times.append(time.perf_counter() - t)
    assert np.median(times) < 1.0  # functional bound only; the < 20 ms target is benchmarked


def test_mesh_query_matches_ground_truth(served):
    _, session, seq, *_ = served
    data = query(session, KEYS.mesh, {"format": "ply"}, timeout=120)
    mesh = trimesh.load(trimesh.util.wrap_as_stream(data), file_type="ply", process=False)
    assert len(mesh.faces) > 500 and mesh.visual.vertex_colors is not None
    gt = trimesh.load(seq.gt_mesh_path, process=False)
    g = evaluate_geometry(mesh, gt, seq.poses, seq.intrinsics, EvalConfig(n_points=20000, cull_views=10))
    # within 1.5 cm of the protocol's sampling floor at this sample count (the GT against itself)
    assert g["accuracy_cm"] < g["sampling_floor_cm"] + 1.5 and g["completion_cm"] < g["sampling_floor_cm"] + 2.5, g
    glb = query(session, KEYS.mesh, {"format": "glb", "resolution": 2}, timeout=120)
    assert glb[:4] == b"glTF"
    part = query(session, KEYS.mesh, params="format=obj;resolution=2;aabb=-50,-50,-50,50,50,0.5", timeout=120)
    assert part.startswith(b"#") or b"\nv " in part[:2000] or part.startswith(b"v ")


def test_render_query(served):
    _, session, seq, *_ = served
    held = seq.heldout[1]
    i = held.intrinsics
    req = {"pose": pose_to_json(held.pose), "width": i.width, "height": i.height,
           "intrinsics": {"fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy}}
    msg = decode_frame(query(session, KEYS.render, req, timeout=120))
    assert msg.color.shape == held.color.shape and msg.pose is not None
    valid = (held.depth > 0) & (msg.depth > 0)
    assert valid.mean() > 0.8
    assert np.median(np.abs(msg.depth[valid] - held.depth[valid])) < 0.03
    assert psnr(msg.color, held.color) > 14.0


def test_typed_client_answers_every_query(served):
    """``h3edge.Client`` over the same session: typed answers, the service's refusals as RemoteError
    with its message, and the render equal to the raw query's."""
    from h3edge import Client

    _, session, seq, *_ = served
    client = Client("test", session=session, timeout=120)
    assert client.status()["frames"]["mapped"] > 0 and "table" in client.profile()
    held = seq.heldout[1]
    color, depth = client.render(held.pose, intrinsics=held.intrinsics)
    assert color.shape == held.color.shape and color.dtype == np.uint8 and depth.dtype == np.float32
    valid = (held.depth > 0) & (depth > 0)
    assert valid.mean() > 0.8 and np.median(np.abs(depth[valid] - held.depth[valid])) < 0.03
    assert client.mesh("glb", resolution=2)[:4] == b"glTF"
    pts = np.array([held.pose[:3, 3], held.pose[:3, 3] + [0.0, 0.0, 0.1]])
    d = client.signed_distance(pts, gradient=True)
    assert d.sdf.shape == (2,) and d.state.dtype == np.uint8 and d.gradient.shape == (2, 3)
    sl = client.slice(float(held.pose[2, 3]), (0.0, 0.0), (2.0, 1.0), 0.1)
    assert sl.occupancy.shape == (10, 20) and sl.resolution == pytest.approx(0.1)
    with pytest.raises(RemoteError, match="format must be ply, glb or obj"):
        client.mesh("stl")
    client.close()  # a session it was handed stays open
    assert json.loads(query(session, KEYS.status))["mapper_alive"]


def test_query_command(served, tmp_path):
    """``h3edge query`` (the CLI on the typed client) against the running service: status, a render
    written as PNGs, signed distance from a points file, a slice saved as .npz, and a refusal as one
    line with exit status 1."""
    import subprocess
    import sys

    svc, _, seq, *_ = served

    def cli(*args):
        return subprocess.run([sys.executable, "-m", "h3edge", "query", *args, "--map-id", "test", "--connect",
                               svc.endpoint, "--no-multicast", "--timeout", "120"], capture_output=True, text=True,
                              timeout=300)

    p = cli("status")
    assert p.returncode == 0 and json.loads(p.stdout)["frames"]["mapped"] > 0, p.stderr
    t = seq.heldout[1].pose[:3, 3]
    p = cli("render", "--pose", ",".join(str(x) for x in [*t, 0, 0, 0, 1]), "--out", str(tmp_path / "r"))
    assert p.returncode == 0 and (tmp_path / "r_color.png").exists() and (tmp_path / "r_depth.png").exists(), p.stderr
    np.save(tmp_path / "pts.npy", np.array([t, t + 0.1]))
    p = cli("sdf", "--points", str(tmp_path / "pts.npy"), "--gradient")
    assert p.returncode == 0 and len(json.loads(p.stdout.splitlines()[0])["sdf"]) == 2, p.stderr
    p = cli("slice", "--z", str(t[2]), "--aabb", "0,0,2,1", "--cell", "0.1", "--out", str(tmp_path / "s.npz"))
    assert p.returncode == 0, p.stderr
    with np.load(tmp_path / "s.npz") as z:
        assert z["occupancy"].shape == (10, 20) and "meta" in z.files
    p = cli("mesh", "--resolution", "1000", "--out", str(tmp_path / "m.ply"))
    assert p.returncode == 1 and "error from the service: resolution must be" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr


@pytest.mark.parametrize("request_, match", [
    ({"pose": {"t": [0, 0, 0], "q": [0, 0, 0, 1]}, "width": 5000, "height": 5000}, "exceeds"),
    ({"pose": {"t": [0, 0, 0], "q": [0, 0, 0, 1]}, "width": 1228800, "height": 1}, "1..16384"),  # at the pixel cap
    ({"width": 64, "height": 48}, "needs"),
    ({"pose": {"t": [0, 0, 0], "q": [0, 0, 0, 2]}}, "unit quaternion"),
    ({"pose": {"t": [0, 0, 0], "q": [0, 0, 0, 1]}, "colour": 1}, "unknown"),
])
def test_bad_render_requests_get_error_replies(served, request_, match):
    _, session, *_ = served
    t = time.perf_counter()
    with pytest.raises(RemoteError, match=match):
        query(session, KEYS.render, request_, timeout=30)
    assert time.perf_counter() - t < 10


def test_bad_mesh_request_gets_error_reply(served):
    _, session, *_ = served
    with pytest.raises(RemoteError, match="format"):
        query(session, KEYS.mesh, {"format": "stl"})
    with pytest.raises(RemoteError, match="resolution"):
        query(session, KEYS.mesh, {"resolution": 1000})


def test_profile_query(served):
    from h3edge.profiling.report import load_document, report

    svc, session, *_ = served
    p = json.loads(query(session, KEYS.profile))
    from h3edge.serving.client import Client

    # what `h3edge profile report zenoh:test` reads
    live = load_document("zenoh:test", lambda mid: Client(mid, svc.client_config(), timeout=10.0).profile())
    assert live["profile"] == "service-test" and "pose association" in report(live)
    assert live["inference"]["mapping_device"] == "cpu"
    if live["inference"]["decoders"] == "onnx":
        assert "query decoders on CPUExecutionProvider" in report(live)
    assert {"read", "priors", "keyframes", "integration", "idle_training", "ingest", "queue_wait", "association",
            "frame_delay"} <= set(p["components"])  # every frame integrated, training on its own thread
    assert "frame integration" in p["table"] and "training step" in p["table"]


def _frame(seq, i, ts_ns, pose=True):
    f = seq[i]
    return FrameMessage(ts_ns, i, f.color, f.depth, f.intrinsics, f.pose if pose else None)


def test_malformed_messages_are_counted_and_dropped(served):
    """Truncated, wrong sizes, NaN / non-rigid poses, stale and duplicate timestamps, unknown
    fields: each is counted under its reason, nothing crashes, and a good frame still maps."""
    svc, session, seq, _, before, _ = served
    block = zenoh.CongestionControl.BLOCK  # the default (DROP) may shed a message on a loaded host
    pub_f = session.declare_publisher(KEYS.frame, congestion_control=block)
    pub_p = session.declare_publisher(KEYS.pose, congestion_control=block)
    now = time.time_ns()
    good = encode_frame(_frame(seq, 3, now))
    bad = [good[:len(good) // 2],  # truncated
           b"not a frame at all",
           good.replace(b'"width": 160', b'"width": 161', 1),  # wrong size
           good.replace(b'"frame_id"', b'"frame_idx"', 1),  # unknown field
           encode_frame(_frame(seq, 4, 1000))]  # far older than the last mapped frame
    nan_pose = json.dumps({"v": 1, "timestamp_ns": now, "t": [float("nan"), 0, 0], "q": [0, 0, 0, 1]}).encode()
    skew = np.eye(4)
    skew[0, 1] = 0.5
    nonrigid = json.dumps({"v": 1, "timestamp_ns": now + 1, "matrix": skew.reshape(-1).tolist()}).encode()
    for b in bad:
        pub_f.put(b)
        time.sleep(0.3)  # one at a time: the ingest queue keeps 2, the policy would drop the rest
    pub_p.put(nan_pose)
    pub_p.put(nonrigid)
    ok = encode_pose(PoseMessage(now + 5, seq[5].pose))
    pub_p.put(ok)
    pub_p.put(ok)  # duplicate timestamp
    time.sleep(0.5)
    pub_f.put(encode_frame(_frame(seq, 5, now + 5, pose=False)))  # good: pose from the pose stream
    time.sleep(0.5)
    pub_f.put(encode_frame(_frame(seq, 5, now + 5, pose=False)))  # the same frame again: duplicate
    end = time.monotonic() + 30  # every message has arrived, then every frame is mapped or dropped
    while json.loads(query(session, KEYS.status))["frames"]["received"] < before["frames"]["received"] + 7:
        assert time.monotonic() < end
        time.sleep(0.1)
    s = wait_drained(session, KEYS, timeout=60)
    d, d0 = s["dropped"], before["dropped"]
    grew = lambda k: d.get(k, 0) - d0.get(k, 0)  # noqa: E731
    assert grew("malformed") == 4, d
    assert grew("stale_timestamp") == 2, d  # the old frame and the duplicate
    assert grew("malformed_pose") == 2 and grew("duplicate_pose") == 1, d  # NaN, non-rigid; the repeat
    # poses refused are counted as poses, not as frames: mapped + dropped frames == received frames
    assert s["poses"]["dropped"] - before["poses"].get("dropped", 0) == 3
    assert s["frames"]["mapped"] + s["frames"]["dropped"] == s["frames"]["received"]
    assert s["frames"]["mapped"] == before["frames"]["mapped"] + 1
    assert s["last_error"] is not None and s["mapper_alive"]
    pub_f.undeclare()
    pub_p.undeclare()


def test_kill_and_resume(served, tmp_path):
    """Save, SIGKILL, restart with --resume: the map is back (frames, voxels, mesh) and mapping goes on."""
    svc, session, seq, _, _, state = served
    info = json.loads(query(session, KEYS.save, timeout=120))
    header, _ = read_checkpoint(Path(info["path"]))
    assert header["frames_mapped"] == info["frames_mapped"] > 0 and header["map_id"] == "test"
    # the map's state directory is a run directory: profile.json with each checkpoint, every duration logged
    doc = load_document(str(state / "test"))
    assert doc["frames"] == info["frames_mapped"] and doc["profile"] == "service-test"
    durations = read_durations(state / "test" / "timings.jsonl")
    assert {"ingest", "queue_wait", "association", "frame_delay", "integration"} <= set(durations)
    assert len(durations["integration"]) == doc["components"]["integration"]["count"] > 0
    before = json.loads(query(session, KEYS.status))
    svc.kill()  # no chance to write anything more
    time.sleep(0.5)
    svc2 = ServiceProcess(PROFILE, state, "test", tmp_path / "service2.log", resume=True)
    try:
        svc2.wait_listening()
        with open_session(svc2.client_config()) as s2:
            st = wait_for_service(s2, KEYS)
            assert st["resumed_from"]["frames_mapped"] == info["frames_mapped"]
            assert st["map"]["frames_mapped"] == info["frames_mapped"]
            assert st["frames"]["mapped"] == 0  # this process's frames: none yet
            assert st["map"]["voxels"] == before["map"]["voxels"]
            mesh = query(s2, KEYS.mesh, {"resolution": 2}, timeout=120)
            assert len(mesh) > 1000
            # it goes on mapping: newer frames (host timestamps after the checkpoint's) are mapped
            publish_sequence(s2, seq, KEYS, rate=4.0, frames=6, embed_pose=True)
            st2 = wait_drained(s2, KEYS, timeout=120)
            assert st2["map"]["frames_mapped"] > info["frames_mapped"] and st2["frames"]["mapped"] > 0
            assert st2["frames"]["mapped"] + st2["frames"]["dropped"] == st2["frames"]["received"]
        assert svc2.stop() == 0
    finally:
        if svc2.proc.poll() is None:
            svc2.kill()
