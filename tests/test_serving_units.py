"""Wire protocol codec, pose association, checkpoint files, sd_notify, memory plan: unit level."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from h3edge.config import load_profile
from h3edge.geometry.camera import Intrinsics, look_at
from h3edge.geometry.poses import interpolate_pose
from h3edge.io.protocol import (
    FrameMessage,
    PoseMessage,
    ProtocolError,
    decode_frame,
    decode_pose,
    encode_frame,
    encode_pose,
)
from h3edge.mapping.map_file import CheckpointError, read_checkpoint, write_checkpoint
from h3edge.mapping.memory_plan import keyframe_bytes, memory_plan
from h3edge.serving.association import PoseBuffer
from h3edge.serving.systemd import Notifier

INTR = Intrinsics(32, 24, 30.0, 30.0, 16.0, 12.0)


def _map_inline(mapper, frame) -> None:
    """Map ``frame`` (an io.sequence.Frame) the paper's way through the library's verbs."""
    assert mapper.add_frame(frame.color, frame.depth, frame.pose, frame.intrinsics, frame.timestamp,
                            train=True, frame_id=frame.index).mapped
POSE = look_at(np.array([1.0, 2.0, 1.5]), np.array([0.0, 0.0, 1.0]))


def _msg(pose=POSE) -> FrameMessage:
    rng = np.random.default_rng(0)
    color = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 4.0, (24, 32)).astype(np.float32)
    depth[0, :5] = 0
    return FrameMessage(123_456_789, 7, color, depth, INTR, pose, "cam")


@pytest.mark.parametrize("cenc, denc, tol", [("png", "png16", 0.0006), ("raw_rgb8", "raw_u16", 0.0006),
                                             ("png", "raw_f32", 0.0), ("jpeg", "png16", 0.0006)])
def test_frame_round_trip(cenc, denc, tol):
    m = _msg()
    out = decode_frame(encode_frame(m, cenc, denc, 1000.0))
    assert (out.timestamp_ns, out.frame_id, out.intrinsics, out.frame_name) == (m.timestamp_ns, 7, INTR, "cam")
    assert np.abs(out.depth - m.depth).max() <= tol and (out.depth[0, :5] == 0).all()
    if cenc != "jpeg":
        assert np.array_equal(out.color, m.color)
    assert np.allclose(out.pose, POSE, atol=1e-9)
    assert decode_frame(encode_frame(_msg(None))).pose is None


def _header_edit(data: bytes, fn) -> bytes:
    n = int.from_bytes(data[4:8], "little")
    h = json.loads(data[8:8 + n])
    fn(h)
    hb = json.dumps(h).encode()
    return data[:4] + len(hb).to_bytes(4, "little") + hb + data[8 + n:]


@pytest.mark.parametrize("edit, match", [
    (lambda h: h.update(extra=1), "unknown field"),
    (lambda h: h.update(v=2), "version"),
    (lambda h: h.update(width=33), "header says|needs"),
    (lambda h: h["intrinsics"].update(fx=float("nan")), "finite"),
    (lambda h: h.update(depth_scale=0), "positive"),
    (lambda h: h["color"].update(encoding="bmp"), "encoding"),
    (lambda h: h["pose"].update(q=[0, 0, 0, 3]), "unit quaternion"),
    (lambda h: h.update(pose={"matrix": [1, 0, 0, 0, 0, 2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}), "rigid"),
    (lambda h: h.update(timestamp_ns=-1), "outside"),
    (lambda h: h.update(width=100000), "outside|limit"),
])
def test_frame_decode_rejects(edit, match):
    data = _header_edit(encode_frame(_msg(), "png", "raw_u16"), edit)
    with pytest.raises(ProtocolError, match=match):
        decode_frame(data)


def test_frame_decode_rejects_truncation_and_garbage():
    data = encode_frame(_msg())
    for bad in (data[:-1], data + b"x", data[:6], b"H3FR" + (10 ** 6).to_bytes(4, "little"), b""):
        with pytest.raises(ProtocolError):
            decode_frame(bad)


def test_pose_round_trip_and_rejects():
    p = decode_pose(encode_pose(PoseMessage(5, POSE, "odom")))
    assert p.timestamp_ns == 5 and p.frame_name == "odom" and np.allclose(p.pose, POSE, atol=1e-9)
    m = json.dumps({"v": 1, "timestamp_ns": 9, "matrix": POSE.reshape(-1).tolist()}).encode()
    assert np.allclose(decode_pose(m).pose, POSE)
    for bad in (b"{", b"[]", json.dumps({"v": 1, "timestamp_ns": 1}).encode(),
                json.dumps({"v": 1, "timestamp_ns": 1, "t": [0, 0], "q": [0, 0, 0, 1]}).encode(),
                json.dumps({"v": 1, "timestamp_ns": 1, "t": [0, 0, 0], "q": [0, 0, 0, 1], "x": 1}).encode()):
        with pytest.raises(ProtocolError):
            decode_pose(bad)


def test_pose_buffer_interpolates_waits_and_misses():
    b = PoseBuffer(capacity=4, max_gap_s=0.1)
    a = POSE
    c = look_at(np.array([1.5, 2.0, 1.5]), np.array([0.0, 0.5, 1.0]))
    assert b.lookup(10) == ("wait", None)
    assert b.add(100_000_000, c) == "" and b.add(50_000_000, a) == ""  # out of order is fine
    assert b.add(50_000_000, a) == "duplicate"
    bad = np.eye(4)
    bad[0, 0] = 2
    assert b.add(60_000_000, bad) == "bad_pose"
    state, pose = b.lookup(75_000_000)
    assert state == "ok" and np.allclose(pose, interpolate_pose(a, c, 0.5))
    assert b.lookup(50_000_000)[0] == "ok"
    assert b.lookup(100_000_001) == ("wait", None)  # no pose after it yet
    assert b.lookup(10)[0] == "miss"  # older than the buffer
    b.add(400_000_000, c)
    assert b.lookup(300_000_000)[0] == "miss"  # poses 300 ms apart > 100 ms
    for t in range(5):
        b.add(500_000_000 + t, c)
    assert len(b) == 4


def test_poses_stamped_ahead_neither_block_frames_nor_push_out_the_present_ones():
    """Issue [4/5] 2: one pose stamped far ahead made every frame whose own next pose came late a
    miss; a flood of them pushed the real poses out of the buffer."""
    b = PoseBuffer(capacity=50, max_gap_s=0.1)
    step = 10_000_000  # 100 Hz
    for k in range(20):
        b.add(k * step, POSE)
    b.add(3_000 * 1_000_000_000, POSE)  # 50 min ahead
    assert b.lookup(19 * step + step // 2) == ("wait", None)  # its own next pose may still come
    b.add(20 * step, POSE)
    assert b.lookup(19 * step + step // 2)[0] == "ok"
    for k in range(500):  # a flood ahead of the stream's present
        b.add(3_000 * 1_000_000_000 + (k + 1) * step, POSE)
    assert len(b) == 50
    for k in range(21, 30):  # the stream goes on: its poses stay and its frames associate
        b.add(k * step, POSE)
        assert b.lookup(k * step - step // 2)[0] == "ok", k


def test_an_outlier_pose_refuses_only_the_frames_beside_it():
    """A pose 100 m off between good ones: frames interpolated across it are misses (implausible
    speed), frames between good poses still associate, and the buffer keeps its order (issue 16,
    item 3)."""
    b = PoseBuffer(capacity=100, max_gap_s=0.1)
    far = POSE.copy()
    far[:3, 3] += 100.0
    for k in range(10):
        assert b.add(k * 33_000_000, far if k == 5 else POSE) == ""
    for t in (150_000_000, 180_000_000):  # between poses 4 and 5, and 5 and 6
        state, why = b.lookup(t)
        assert state == "miss" and "outlier" in why
    assert b.lookup(100_000_000)[0] == "ok" and b.lookup(250_000_000)[0] == "ok"


def test_checkpoint_atomic_and_checked(tmp_path):
    p = tmp_path / "m" / "map.h3ckpt"
    arrays = {"a": np.arange(10.0), "b/c": np.ones((3, 2), np.uint8)}
    size = write_checkpoint(p, {"map_id": "x", "frames_mapped": 3}, arrays)
    assert p.stat().st_size == size and not (p.parent / "map.h3ckpt.tmp").exists()
    h, got = read_checkpoint(p)
    assert h["map_id"] == "x" and h["format_version"] == 1 and np.array_equal(got["b/c"], arrays["b/c"])
    raw = bytearray(p.read_bytes())
    raw[-20] ^= 0xFF  # flip a payload byte
    p.write_bytes(bytes(raw))
    with pytest.raises(CheckpointError, match="checksum"):
        read_checkpoint(p)
    p.write_bytes(bytes(raw[:100]))
    with pytest.raises(CheckpointError):
        read_checkpoint(p)
    p.write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="magic"):
        read_checkpoint(p)


def test_notifier_sends_datagrams(tmp_path):
    addr = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(addr)
    srv.settimeout(2)
    n = Notifier({"NOTIFY_SOCKET": addr, "WATCHDOG_USEC": "30000000"})
    assert n.enabled and n.watchdog_interval() == 15.0
    assert n.ready("mapping")
    assert srv.recv(100) == b"READY=1\nSTATUS=mapping"
    assert n.watchdog() and srv.recv(100) == b"WATCHDOG=1"
    srv.close()
    off = Notifier({})
    assert not off.enabled and off.watchdog_interval() is None and not off.ready()


def test_memory_plan_sets_keyframe_cap():
    s = load_profile("x86-cpu").map_settings()
    kb = keyframe_bytes(s)
    big, small = memory_plan(s, 4096, kb), memory_plan(s, 300, kb)
    assert big["max_keyframes"] > small["max_keyframes"] >= 8
    assert big["hash_tables"] == small["hash_tables"] > 0
    parts = ("hash_tables", "voxels_at_cap", "query_snapshot", "query_working_set", "checkpoint_capture",
             "frame_buffers", "free_space", "cell_votes", "color_base", "keyframes")
    assert sum(big[k] for k in parts) == big["budget"]
    # the largest admitted frame's buffers are planned for: a larger cap leaves fewer keyframes
    hd, uhd = memory_plan(s, 4096, kb, 1920 * 1080), memory_plan(s, 4096, kb, 4096 * 3072)
    assert uhd["frame_buffers"] > 6 * hd["frame_buffers"] > 0 and uhd["max_keyframes"] < hd["max_keyframes"]


def test_deploy_files():
    from pathlib import Path

    import zenoh

    root = Path(__file__).resolve().parents[1]
    for f in ("zenoh-peer.json5", "zenoh-tls-acl.json5"):
        zenoh.Config.from_file(str(root / "deploy" / f))  # parses with this zenoh
    unit = (root / "systemd" / "h3edge.service").read_text()
    for line in ("Type=notify", "WatchdogSec=", "Restart=on-failure", "StateDirectory=h3edge",
                 "RestartPreventExitStatus=2", "--resume"):
        assert line in unit
    directives = [ln.split("=")[0] for ln in unit.splitlines() if ln and not ln.startswith("#")]
    assert "PrivateDevices" not in directives and "MemoryDenyWriteExecute" not in directives
    assert "MemoryMax" not in directives  # sized per device by the install script's drop-in
    script = (root / "deploy" / "install-jetson.sh").read_text()
    assert "/bin/h3edge\" deploy plan" in script and "MemoryMax=$MEMORY_MAX" in script and "x86-cpu" not in script
    assert subprocess.run(["bash", "-n", str(root / "deploy" / "install-jetson.sh")]).returncode == 0
    oak_unit = (root / "systemd" / "h3edge-oak.service").read_text()
    for line in ("h3edge camera oak", "Restart=always", "SupplementaryGroups=plugdev"):
        assert line in oak_unit
    assert "PrivateDevices" not in [ln.split("=")[0] for ln in oak_unit.splitlines() if ln and not ln.startswith("#")]
    assert 'ATTRS{idVendor}=="03e7"' in (root / "deploy" / "80-movidius.rules").read_text()


def test_duration_log_rotates_and_survives_write_errors(tmp_path, monkeypatch):
    from h3edge.profiling.timing import DurationLog, Timings, read_durations

    path = tmp_path / "run" / "timings.jsonl"
    log_ = DurationLog(path, max_bytes=2000)
    t = Timings(window=5, sink=log_)
    for i in range(100):
        t.add("training", 0.001 * i)
    log_.flush()
    assert path.exists() and path.with_name("timings.jsonl.1").exists()
    assert path.stat().st_size <= 2000 and path.with_name("timings.jsonl.1").stat().st_size <= 2000
    kept = read_durations(path)["training"]
    assert 20 < len(kept) < 100 and kept[-1] == pytest.approx(99.0)  # the newest survive rotation
    assert t.counts["training"] == 100 and len(t.samples["training"]) == 5  # bounded memory
    with open(path, "a") as f:
        f.write('{"unix": 1, "compo')  # a line cut short by a crash is skipped
    assert read_durations(path)["training"] == kept

    def full(*_):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(log_._f, "write", full)
    t.add("training", 0.5)  # logged once, never raised
    t.add("training", 0.5)
    assert log_._f is None and t.counts["training"] == 102
    log_.close()


@pytest.mark.parametrize("model, profile", [
    ("NVIDIA Jetson AGX Orin Developer Kit\x00", "orin-agx"),
    ("NVIDIA Jetson AGX Orin 64GB", "orin-agx"),
    ("NVIDIA Jetson Orin NX Engineering Reference Developer Kit", "orin-nx"),
    ("NVIDIA Jetson Orin Nano Developer Kit", "orin-nano"),
    ("NVIDIA Jetson Orin Nano Engineering Reference Developer Kit Super", "orin-nano"),
    ("Raspberry Pi 5 Model B Rev 1.0", None),
])
def test_jetson_model_picks_its_profile(model, profile):
    from h3edge.config import load_profile
    from h3edge.deploy import profile_for_model

    assert profile_for_model(model) == profile
    if profile:
        assert load_profile(profile).mapping.mapper.device == "cuda"


def test_deploy_plan_sizes_the_unit_and_refuses_what_does_not_fit(tmp_path):
    from h3edge.deploy import memory_limits, plan
    from h3edge.errors import InputError

    model, meminfo = tmp_path / "model", tmp_path / "meminfo"
    model.write_bytes(b"NVIDIA Jetson Orin Nano Developer Kit\x00")
    meminfo.write_text("MemTotal:        7620000 kB\nMemFree: 1 kB\n")
    v = plan(None, model, meminfo, runtime_mb=1500)
    assert v["PROFILE"] == "orin-nano" and Path(v["PROFILE_FILE"]).is_file()
    hi, mx = int(v["MEMORY_HIGH"][:-1]), int(v["MEMORY_MAX"][:-1])
    assert 2048 + 1500 < hi < mx <= 7620000 / 1024 - 1024 and mx % 256 == 0
    with pytest.raises(InputError, match="does not fit"):
        plan("orin-agx", model, meminfo, runtime_mb=1500)  # an 8 GB budget on an 8 GB module
    with pytest.raises(InputError, match="not a known Jetson"):
        plan(None, tmp_path / "missing", meminfo, runtime_mb=1500)
    lim = memory_limits(8192, 1200)
    assert lim.max_mb >= 8192 + 1200 + 0.15 * 8192 and lim.high_mb < lim.max_mb


def test_unwritable_state_directory_is_a_one_line_error(tmp_path):
    from h3edge.mapping.map_file import CheckpointError, check_writable

    check_writable(tmp_path / "a" / "b")  # created
    (tmp_path / "file").write_text("x")
    with pytest.raises(CheckpointError, match="not writable.*--state-dir"):
        check_writable(tmp_path / "file" / "map")
    r = subprocess.run([sys.executable, "-m", "h3edge", "serve", "--state-dir", str(tmp_path / "file"),
                        "--no-multicast"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.strip().startswith("error: state directory") and "Traceback" not in r.stderr


def test_far_future_stamps_are_refused_and_later_frames_map(tmp_path):
    """One frame and one pose stamped 2^63-1 ns are refused (their own drop reasons) before they
    reach the mapper or the pose buffer; a pose stamped 10^400 is malformed; valid frames after
    them still map (issue 16, item 1)."""
    import time

    from h3edge.mapping.engine import MapperConfig, MapSettings
    from h3edge.mapping.field import FieldConfig
    from h3edge.mapping.voxels import VoxelConfig
    from h3edge.serving.service import MapService, ServiceConfig

    settings = MapSettings(mapper=MapperConfig(device="cpu", rays_per_iteration=128, extent=8.0),
                           voxels=VoxelConfig(min_points=1),
                           field=FieldConfig(sdf_layers=1, geo_log2_table=12, tex_log2_table=12))
    svc = MapService(settings, ServiceConfig(state_dir=str(tmp_path), checkpoint_interval_s=0.0, memory_budget_mb=256))
    big = (1 << 63) - 1
    svc.submit_pose(encode_pose(PoseMessage(big, POSE)))
    svc.submit_pose(json.dumps({"v": 1, "timestamp_ns": 10 ** 400, "matrix": POSE.tolist()}).encode())
    assert len(svc.poses) == 0
    bogus = _msg()
    bogus.timestamp_ns = big
    svc.start()
    try:
        svc.submit_frame(encode_frame(bogus, "png", "png16"))
        now = time.time_ns()
        for k in range(2):
            good = _msg()
            good.timestamp_ns, good.frame_id = now + k * 10 ** 8, k
            good.depth[:] = 2.0  # a wall: voxels with enough points
            time.sleep(0.3)
            svc.submit_frame(encode_frame(good, "png", "png16"))
        end = time.monotonic() + 60
        while svc.status()["frames"]["mapped"] + svc.status()["frames"]["dropped"] < 3 and time.monotonic() < end:
            time.sleep(0.1)
        st = svc.status()
    finally:
        svc.stop(checkpoint=False)
    assert st["dropped"].get("future_timestamp") == 1 and st["dropped"].get("future_pose") == 1
    assert st["dropped"].get("malformed_pose") == 1
    assert st["frames"]["mapped"] == 2, st
    assert svc.mapper.last_timestamp < big * 1e-9


@pytest.mark.parametrize("bad", ["..", "", "a/b", "h3edge/**", "*", "x" * 65, ".hidden", "a b"])
def test_unsafe_map_ids_are_refused(bad, tmp_path):
    """A map id is one file name under the state directory and one zenoh key chunk: '..' would
    write outside the state directory, '*' would be a wildcard (issue 16, item 8)."""
    from h3edge.errors import InputError
    from h3edge.io.protocol import Keys
    from h3edge.mapping.engine import MapSettings
    from h3edge.serving.service import MapService, ServiceConfig

    with pytest.raises(InputError, match="map id"):
        Keys.for_map(bad)
    with pytest.raises(InputError, match="map id"):
        MapService(MapSettings(), ServiceConfig(map_id=bad, state_dir=str(tmp_path)))
    assert not any(tmp_path.iterdir()) and Keys.for_map("robot-1.kitchen_2").base == "h3edge/robot-1.kitchen_2"


def test_checkpoint_fallback_leftovers_and_failed_final_checkpoint(tmp_path, tiny_scene):
    """The previous checkpoint is kept and --resume falls back to it when the newest is corrupt
    (and says so); scratch files of a killed write are removed at start; a final checkpoint that
    fails makes stop() report it (the daemon then exits non-zero) (issue 16, item 7)."""
    from h3edge.io.replica import ReplicaSequence
    from h3edge.mapping.engine import MapperConfig, MapSettings
    from h3edge.mapping.field import FieldConfig
    from h3edge.mapping.map_file import previous_path
    from h3edge.mapping.voxels import VoxelConfig
    from h3edge.serving.service import MapService, ServiceConfig

    settings = MapSettings(mapper=MapperConfig(device="cpu", rays_per_iteration=128),
                           voxels=VoxelConfig(min_points=3),
                           field=FieldConfig(sdf_layers=1, geo_log2_table=12, tex_log2_table=12))
    cfg = ServiceConfig(map_id="m", state_dir=str(tmp_path), checkpoint_interval_s=0.0, memory_budget_mb=256)
    seq = ReplicaSequence(tiny_scene)
    svc = MapService(settings, cfg)
    for i in range(2):
        _map_inline(svc.mapper, seq[i])
        svc.checkpoints.write(svc.checkpoints.capture(svc.mapper))
    ckpt = svc.checkpoints.path
    assert (
        read_checkpoint(previous_path(ckpt))[0]["frames_mapped"] == 1 and read_checkpoint(ckpt)[0]["frames_mapped"] == 2
    )
    ckpt.write_bytes(ckpt.read_bytes()[:1000])  # the newest truncated
    (ckpt.parent / "map.h3ckpt.tmp").write_bytes(b"x" * 100)
    for folder in ("maps", "exports"):  # a named save or an export killed midway (issue [4/5] 11)
        (ckpt.parent / folder).mkdir(exist_ok=True)
        (ckpt.parent / folder / "named.h3ckpt.tmp").write_bytes(b"x" * 100)
    again = MapService(settings, cfg, resume=True)
    assert again.resumed_from["fallback"] and again.mapper.frames_mapped == 1
    assert again.status()["last_error"]["code"] == "checkpoint_fallback"
    assert not (ckpt.parent / "map.h3ckpt.tmp").exists()
    assert not list(ckpt.parent.glob("*/*.tmp"))
    previous_path(ckpt).write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="cannot resume"):
        MapService(settings, cfg, resume=True)
    ok = MapService(settings, cfg)
    _map_inline(ok.mapper, seq[0])
    assert ok.stop() is True
    bad = MapService(settings, cfg)
    _map_inline(bad.mapper, seq[0])
    bad.checkpoints.path = tmp_path / "not-a-dir" / "x" / "map.h3ckpt"
    (tmp_path / "not-a-dir").write_text("a file where a directory should be")
    assert bad.stop() is False and bad.last_error["code"] == "checkpoint"


@pytest.mark.parametrize("kind", ["jpeg", "png", "png16"])
def test_image_bombs_are_refused_from_their_header(kind):
    """A small image that declares a huge size is refused from its header bytes, before decoding
    (issue 16, item 4): the colour PNG / JPEG and the 16-bit depth PNG."""
    import cv2

    from h3edge.io.protocol import encoded_image_size

    big = np.zeros((3000, 2500, 3 if kind != "png16" else 1), np.uint16 if kind == "png16" else np.uint8)
    ok, buf = cv2.imencode(".jpg" if kind == "jpeg" else ".png", big)
    assert ok and len(buf) < 2_000_000 and encoded_image_size(buf.tobytes())[:2] == (2500, 3000)
    msg = _msg()
    good = encode_frame(msg, "jpeg" if kind == "jpeg" else "png", "png16")
    d = decode_frame(good)
    assert d.color.shape == (24, 32, 3)
    # splice the big image in place of the frame's own colour (or depth) image
    n = int.from_bytes(good[4:8], "little")
    header = json.loads(good[8:8 + n])
    part = "depth" if kind == "png16" else "color"
    start = 8 + n + (header["color"]["size"] if part == "depth" else 0)
    body = good[start:start + header[part]["size"]]
    header[part]["size"] = len(buf)
    hb = json.dumps(header).encode()
    rest = good[8 + n:start] + buf.tobytes() + good[start + len(body):]
    bomb = good[:4] + len(hb).to_bytes(4, "little") + hb + rest
    with pytest.raises(ProtocolError, match="header says 2500x3000, frame header says 32x24"):
        decode_frame(bomb)
    with pytest.raises(ProtocolError):
        encoded_image_size(b"GIF89a....")


class _ScriptedSession:
    """A zenoh session stand-in whose gets answer from a script: None = the network ends the query at
    once with no reply, bytes = one ok reply."""

    def __init__(self, answers):
        self.answers, self.asked = list(answers), 0

    def get(self, selector, payload=None, encoding=None, timeout=None):
        self.asked += 1
        answer = self.answers.pop(0) if self.answers else None
        if answer is None:
            return iter(())

        class Ok:
            payload = type("P", (), {"to_bytes": staticmethod(lambda: answer)})()

        return iter([type("Reply", (), {"ok": Ok, "err": None})()])


def test_a_query_ended_at_once_is_asked_again_before_nobody_is_said(monkeypatch):
    """A client session's view of the network's queryables can lag for a moment (zenoh#2767): an
    at-once empty answer is asked again with growing pauses, and only a run of them says 'no service
    serves this key, or an access-control rule denies it' (what CI met in the site ACL test)."""
    from h3edge.serving import client

    monkeypatch.setattr(client, "_EMPTY_ANSWER_RETRY_S", (0.01, 0.02, 0.04))
    late = _ScriptedSession([None, None, b"status"])
    assert client.query(late, "h3edge/m/status", timeout=5.0) == b"status" and late.asked == 3
    nobody = _ScriptedSession([])
    with pytest.raises(TimeoutError, match="ended at once with no answer, asked 4 times in .*access-control rule"):
        client.query(nobody, "h3edge/m/status", timeout=5.0)
    assert nobody.asked == 4
    short = _ScriptedSession([])  # the pauses stay within half the caller's timeout
    with pytest.raises(TimeoutError, match="asked once"):
        client.query(short, "h3edge/m/status", timeout=0.015)


def test_overloaded_queries_get_a_busy_error_reply():
    """A query that finds its queue full is answered with an error saying busy / retry, not an
    empty reply the client reads as 'is the service running?' (issue 16, item 5)."""
    from h3edge.serving.server import ZenohServer

    class FakeQuery:
        key_expr = "h3edge/m/render"

        def __init__(self):
            self.errors, self.closed = [], False

        def reply_err(self, text):
            self.errors.append(text)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.closed = True

    server = ZenohServer(service=None, session=None, map_id="m")
    cb = server._enqueue(server._heavy, lambda q: (b"", None), "h3edge/m/render")
    queries = [FakeQuery() for _ in range(server._heavy.maxsize + 3)]
    for q in queries:
        cb(q)
    refused = [q for q in queries if q.errors]
    assert len(refused) == 3 and all(q.closed and "busy" in q.errors[0] and "retry" in q.errors[0] for q in refused)
    assert server._heavy.qsize() == server._heavy.maxsize


def test_heavy_queries_past_their_deadline_get_an_error_reply():
    """A heavy query that waited in the queue past the deadline is answered with a deadline
    error, not worked on after its client gave up (issue 16, item 5)."""
    import time as time_

    from h3edge.serving.server import ZenohServer

    class FakeQuery:
        key_expr = "h3edge/m/mesh"

        def __init__(self):
            self.errors, self.replies = [], []

        def reply_err(self, text):
            self.errors.append(text)

        def reply(self, key, payload, encoding=None):
            self.replies.append(payload)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

    server = ZenohServer(service=None, session=None, map_id="m", heavy_deadline_s=0.2)
    calls = []
    late, fresh = FakeQuery(), FakeQuery()
    server._heavy.put((late, lambda q: calls.append(q) or (b"mesh", None), time_.monotonic() - 1.0, "h3edge/m/mesh"))
    server._heavy.put((fresh, lambda q: calls.append(q) or (b"mesh", None), time_.monotonic(), "h3edge/m/mesh"))
    worker = threading.Thread(target=server._work, args=(server._heavy,), daemon=True)
    worker.start()
    end = time_.monotonic() + 5
    while not fresh.replies and time_.monotonic() < end:
        time_.sleep(0.01)
    server._closing.set()
    worker.join(2)
    assert late.errors and "deadline" in late.errors[0] and "retry" in late.errors[0] and not late.replies
    assert fresh.replies == [b"mesh"] and calls == [fresh]


def test_save_is_rate_limited_and_needs_its_exact_key(tmp_path, tiny_scene):
    """At most one save per save_min_interval_s; a wildcard query reaching the save queryable writes
    nothing (issue 16, item 6)."""
    from h3edge.errors import QueryError
    from h3edge.io.replica import ReplicaSequence
    from h3edge.mapping.engine import MapperConfig, MapSettings
    from h3edge.mapping.field import FieldConfig
    from h3edge.mapping.voxels import VoxelConfig
    from h3edge.serving.server import ZenohServer
    from h3edge.serving.service import MapService, ServiceConfig

    settings = MapSettings(mapper=MapperConfig(device="cpu", rays_per_iteration=128), voxels=VoxelConfig(min_points=3),
                           field=FieldConfig(sdf_layers=1, geo_log2_table=12, tex_log2_table=12))
    svc = MapService(settings, ServiceConfig(map_id="m", state_dir=str(tmp_path), checkpoint_interval_s=0.0,
                                             memory_budget_mb=256, save_min_interval_s=30.0))
    _map_inline(svc.mapper, ReplicaSequence(tiny_scene)[0])
    assert svc.save()["frames_mapped"] == 1
    with pytest.raises(QueryError, match="save refused.*at most one per 30 s"):
        svc.save()

    class WildcardQuery:
        key_expr = "h3edge/m/**"

    server = ZenohServer(svc, session=None, map_id="m")
    before = svc.checkpoints.path.stat().st_mtime_ns
    with pytest.raises(QueryError, match="exact key h3edge/m/save"):
        server._save(WildcardQuery())
    assert svc.checkpoints.path.stat().st_mtime_ns == before


@pytest.mark.parametrize("payload", [b"[" * 100_000 + b"]" * 100_000,
                                     b'{"v": 1, "timestamp_ns": ' + b"9" * 5000 + b', "matrix": []}'])
def test_hostile_json_is_malformed_not_an_internal_error(payload):
    """Deeply nested JSON and 5000-digit integers are protocol errors (the pose key counted them
    nowhere, raising inside the zenoh callback) (issue 16, item 8)."""
    with pytest.raises(ProtocolError, match="not JSON"):
        decode_pose(payload)
    frame = b"H3FR" + len(payload).to_bytes(4, "little") + payload
    with pytest.raises(ProtocolError):  # too long a header, or not JSON
        decode_frame(frame)


@pytest.mark.parametrize("request_, match", [
    ({"format": "stl"}, "format"), ({"resolution": "Infinity"}, "mesh request"), ({"resolution": 0}, "1..10"),
    ({"aabb": "1,2,3"}, "6 numbers"), ({"aabb": [[0, 0, 0], [0, 1, 1]]}, "min < max"), ({"size": 3}, "unknown"),
    ("not an object", "JSON object"),
])
def test_mesh_requests_are_parsed_and_bounded_at_the_edge(request_, match):
    from h3edge.errors import QueryError
    from h3edge.serving.queries import MeshRequest

    with pytest.raises(QueryError, match=match):
        MeshRequest.parse(request_, 5, 10)
    ok = MeshRequest.parse({"format": "glb", "resolution": "4", "aabb": "0,0,0,1,2,3"}, 5, 10)
    assert ok.format == "glb" and ok.resolution == 4 and ok.aabb.tolist() == [[0, 0, 0], [1, 2, 3]]
    assert MeshRequest.parse({}, 5, 10).resolution == 5


def test_render_requests_are_parsed_and_bounded_at_the_edge():
    from h3edge.errors import QueryError
    from h3edge.serving.queries import RenderRequest

    pose = {"t": [0, 0, 0], "q": [0, 0, 0, 1]}
    r = RenderRequest.parse({"pose": pose, "width": 64, "height": 48, "fov_deg": 90}, 10_000)
    assert (r.intrinsics.width, r.intrinsics.height) == (64, 48) and r.intrinsics.fx == pytest.approx(32)
    for bad, match in (({"pose": pose, "width": 1228800, "height": 1}, "1..16384"),
                       ({"pose": pose, "width": 200, "height": 100}, "cap"), ({"width": 8, "height": 8}, "needs"),
                       ({"pose": pose, "width": 8, "height": 8, "fov_deg": 179}, "fov_deg"),
                       ({"pose": pose, "extra": 1}, "unknown")):
        with pytest.raises(QueryError, match=match):
            RenderRequest.parse(bad, 10_000)
