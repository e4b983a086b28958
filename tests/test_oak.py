"""OAK camera source without a device: conversions against depthai's own types, the node graph,
and the command's one-line errors."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import types
from datetime import timedelta

import numpy as np
import pytest

from h3edge.geometry.camera import Intrinsics
from h3edge.geometry.poses import pose_from_tq
from h3edge.io import oak
from h3edge.io.protocol import decode_frame, encode_frame

dai = pytest.importorskip("depthai", reason="the 'oak' extra (depthai) is not installed")

K = [[1000.0, 0.0, 960.0], [0.0, 1000.0, 540.0], [0.0, 0.0, 1.0]]


def k_of(intr: Intrinsics) -> np.ndarray:
    return np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1]])


@pytest.mark.parametrize("src, out, crop", [((1920, 1080), (640, 480), (240, 0, 1440, 1080)),
                                            ((1280, 960), (640, 360), (0, 120, 1280, 720)),
                                            ((1280, 800), (640, 400), (0, 0, 1280, 800))])
def test_crop_intrinsics_match_depthai_transformation(src, out, crop):
    """Our CROP-mode intrinsics equal depthai's ImgTransformation after the same crop and scale."""
    t = dai.ImgTransformation(src[0], src[1], K)
    t.addCrop(*crop)
    t.addScale(out[0] / crop[2], out[1] / crop[3])
    assert tuple(t.getSize()) == out
    ours = oak.crop_intrinsics(np.array(K), src, out)
    assert (ours.width, ours.height) == out
    assert np.allclose(k_of(ours), np.array(t.getIntrinsicMatrix()), atol=1e-3)


def _group(bgr: np.ndarray, mm: np.ndarray, ts: timedelta, transform=None, depth_type=None):
    rgb = dai.ImgFrame()
    rgb.setCvFrame(bgr, dai.ImgFrame.Type.BGR888i)
    rgb.setTimestamp(ts)
    rgb.setSequenceNum(7)
    if transform is not None:
        rgb.setTransformation(transform)
    depth = dai.ImgFrame()
    depth.setCvFrame(mm, depth_type or dai.ImgFrame.Type.RAW16)
    depth.setTimestamp(ts)
    g = dai.MessageGroup()
    g["rgb"] = rgb
    g["depth"] = depth
    return g


def test_frame_intrinsics_prefer_the_frames_own_transformation():
    fallback = Intrinsics(64, 48, 50.0, 50.0, 32.0, 24.0)
    t = dai.ImgTransformation(1920, 1080, K)
    t.addCrop(240, 0, 1440, 1080)
    t.addScale(64 / 1440, 48 / 1080)
    g = _group(np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64), np.uint16), timedelta(seconds=1), t)
    intr = oak.frame_intrinsics(g["rgb"], fallback)
    assert np.allclose(k_of(intr), np.array(t.getIntrinsicMatrix()), atol=1e-4) and intr != fallback
    bare = _group(np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64), np.uint16), timedelta(seconds=1))
    assert oak.frame_intrinsics(bare["rgb"], fallback) == fallback  # no transformation: the calibration's


def test_host_clock_converts_depthai_time_to_unix_ns():
    clock = oak.HostClock(monotonic_ns=lambda: 100_000_000_000, unix_ns=lambda: 1_700_000_000_000_000_000)
    assert clock.to_unix_ns(timedelta(seconds=100, microseconds=500_001)) == 1_700_000_000_500_001_000
    # depthai's host timestamps are on the steady clock: now in depthai's clock is now in unix time
    real = oak.HostClock()
    assert abs(real.to_unix_ns(dai.Clock.now()) - time.time_ns()) < 50_000_000
    assert oak.timedelta_ns(timedelta(days=2, seconds=3, microseconds=4)) == (2 * 86400 + 3) * 10**9 + 4000


def test_group_becomes_a_protocol_frame():
    h, w = 48, 64
    bgr = np.zeros((h, w, 3), np.uint8)
    bgr[..., 0], bgr[..., 2] = 30, 200  # blue 30, red 200
    mm = np.full((h, w), 1500, np.uint16)
    mm[0, 0] = 0  # invalid stays 0
    fallback = Intrinsics(w, h, 50.0, 50.0, 32.0, 24.0)
    clock = oak.HostClock(monotonic_ns=lambda: 0, unix_ns=lambda: 10**18)
    msg = oak.group_to_message(_group(bgr, mm, timedelta(seconds=2)), 3, clock, fallback)
    assert msg.timestamp_ns == 10**18 + 2 * 10**9 and msg.frame_id == 3 and msg.pose is None
    assert msg.color.shape == (h, w, 3) and tuple(msg.color[5, 5]) == (200, 0, 30)  # RGB order
    assert msg.depth.dtype == np.float32 and msg.depth[1, 1] == pytest.approx(1.5) and msg.depth[0, 0] == 0
    assert msg.intrinsics == fallback
    back = decode_frame(encode_frame(msg, "png"))  # the wire protocol the service decodes
    assert np.array_equal(back.color, msg.color) and np.allclose(back.depth, msg.depth, atol=1e-3)
    assert back.timestamp_ns == msg.timestamp_ns
    # depth aligned at another resolution is resampled onto the colour grid (nearest)
    half = oak.group_to_message(_group(bgr, mm[::2, ::2].copy(), timedelta(seconds=2)), 4, clock, fallback)
    assert half.depth.shape == (h, w) and half.depth[10, 10] == pytest.approx(1.5)


def test_unusable_groups_raise_value_error():
    fallback = Intrinsics(64, 48, 50.0, 50.0, 32.0, 24.0)
    clock = oak.HostClock()
    g = dai.MessageGroup()
    rgb = dai.ImgFrame()
    rgb.setCvFrame(np.zeros((48, 64, 3), np.uint8), dai.ImgFrame.Type.BGR888i)
    g["rgb"] = rgb
    with pytest.raises(ValueError, match="rgb or depth"):
        oak.group_to_message(g, 0, clock, fallback)
    with pytest.raises(ValueError, match="the camera was set up for"):
        oak.group_to_message(_group(np.zeros((40, 64, 3), np.uint8), np.zeros((40, 64), np.uint16),
                                    timedelta(0)), 0, clock, fallback)


def test_vio_pose_composes_the_imu_extrinsics():
    imu_to_cam = np.eye(4)
    imu_to_cam[:3, 3] = [0.05, 0.0, 0.0]  # p_cam = p_imu + 5 cm x: the camera sits 5 cm along -x of the IMU
    q90z = (0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4))
    c2w = oak.vio_pose((1.0, 2.0, 3.0), q90z, imu_to_cam)
    # the camera origin in IMU coordinates is (-0.05, 0, 0); rotated 90 deg about z -> (0, -0.05, 0)
    assert np.allclose(c2w[:3, 3], [1.0, 1.95, 3.0]) and np.allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3))
    tr = dai.TransformData(1.0, 2.0, 3.0, *q90z)
    assert np.allclose(oak.vio_pose(*oak.transform_tq(tr), np.eye(4)), pose_from_tq((1, 2, 3), q90z))
    with pytest.raises(ValueError, match="norm"):
        oak.vio_pose((0, 0, 0), (0.0, 0.0, 0.0, 2.0), np.eye(4))


class _Rec:
    """Stand-in for a depthai node or port that records every call and link; device nodes cannot be
    created without a device ("Pipeline is host only, cannot create device node")."""

    def __init__(self, log, label):
        self._log, self._label = log, label

    def __getattr__(self, name):
        return _Rec(self._log, f"{self._label}.{name}")

    def __getitem__(self, key):
        return _Rec(self._log, f"{self._label}[{key}]")

    def __call__(self, *args, **kwargs):
        self._log.append(("call", self._label, args, kwargs))
        if self._label.endswith(".build"):
            return _Rec(self._log, self._label.rsplit(".", 1)[0])
        return _Rec(self._log, f"{self._label}()#{len(self._log)}")

    def link(self, other):
        self._log.append(("link", self._label, other._label))


class _Pipeline:
    def __init__(self):
        self.log, self.n = [], 0

    def create(self, node_type):
        self.n += 1
        return _Rec(self.log, f"{node_type.__name__}{self.n}")


def _links(log):
    return {(a.split("#")[0], b) for kind, a, b, *_ in [e for e in log if e[0] == "link"]}


@pytest.mark.parametrize("platform", ["RVC2", "RVC4"])
def test_pipeline_graph(platform):
    p = _Pipeline()
    cfg = oak.OakConfig(640, 480, 20.0)
    streams = oak.build_pipeline(dai, p, cfg, getattr(dai.Platform, platform))
    calls = [e for e in p.log if e[0] == "call"]
    rgb_req = [c for c in calls if c[1] == "Camera1.requestOutput"]
    assert rgb_req[0][2] == ((640, 480), dai.ImgFrame.Type.RGB888i, dai.ImgResizeMode.CROP, 20.0, True)
    assert ("call", "Camera1.build", (dai.CameraBoardSocket.CAM_A,), {}) in calls
    sync = [c for c in calls if c[1].endswith("setSyncThreshold")]
    assert sync[0][2] == (timedelta(seconds=1 / 40),)
    links = _links(p.log)
    rgb = "Camera1.requestOutput()"
    assert (rgb, "Sync5.inputs[rgb]") in links
    if platform == "RVC2":
        assert (rgb, "StereoDepth4.inputAlignTo") in links and ("StereoDepth4.depth", "Sync5.inputs[depth]") in links
    else:
        assert ("StereoDepth4.depth", "ImageAlign6.input") in links and (rgb, "ImageAlign6.inputAlignTo") in links
        assert ("ImageAlign6.outputAligned", "Sync5.inputs[depth]") in links
    assert streams.poses is None and "Sync5.out.createOutputQueue" in [c[1] for c in calls]


def test_pipeline_with_vio_and_without_basalt():
    p = _Pipeline()
    streams = oak.build_pipeline(dai, p, oak.OakConfig(pose_source="vio"), dai.Platform.RVC2)
    links = _links(p.log)
    assert ("IMU6.out", "BasaltVIO7.imu") in links and streams.poses is not None
    assert {b for a, b in links if a.startswith("Camera2.requestOutput")} >= {"BasaltVIO7.left"}
    no_vio = types.SimpleNamespace(**{k: getattr(dai, k) for k in ("CameraBoardSocket", "ImgFrame", "ImgResizeMode",
                                                                     "Platform", "IMUSensor", "__version__")})
    no_vio.node = types.SimpleNamespace(**{k: getattr(dai.node, k) for k in ("Camera", "StereoDepth", "Sync",
                                                                            "ImageAlign", "IMU")})
    with pytest.raises(oak.OakUnavailable, match="no BasaltVIO"):
        oak.build_pipeline(no_vio, _Pipeline(), oak.OakConfig(pose_source="vio"), dai.Platform.RVC2)


def test_host_side_nodes_take_our_settings():
    """The nodes depthai lets a host-only pipeline create accept what build_pipeline gives them."""
    p = dai.Pipeline(False)
    sync = p.create(dai.node.Sync)
    sync.setSyncThreshold(oak.OakConfig(fps=30).sync_threshold)
    assert hasattr(p.create(dai.node.BasaltVIO), "transform")
    assert hasattr(p.create(dai.node.ImageAlign), "outputAligned")
    with pytest.raises(RuntimeError, match="host only"):  # why the graph test records instead
        p.create(dai.node.StereoDepth)


@pytest.mark.parametrize("args, message", [
    ([], "error: no OAK device found"),
    (["--width", "100"], "error: width 100 must be a multiple of 16"),
    (["--fps", "0"], "error: fps 0.0 out of range"),
])
def test_command_without_device_exits_with_one_line(args, message):
    env = {k: v for k, v in os.environ.items() if k != "DEPTHAI_LEVEL"}
    r = subprocess.run([sys.executable, "-m", "h3edge.cli", "camera", "oak", "--no-multicast", *args],
                       capture_output=True, text=True, timeout=120, env=env)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith(message), r.stderr


def test_calibration_intrinsics_for_the_output_size():
    """From depthai's own CalibrationHandler (as a device would hand it over) to the output's intrinsics."""
    calib = dai.CalibrationHandler()
    calib.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A, K, (1920, 1080))
    device = types.SimpleNamespace(readCalibration=lambda: calib)
    intr, imu_cam = oak.calibration_intrinsics(dai, device, oak.OakConfig(640, 480))
    assert intr == oak.crop_intrinsics(np.array(K), (1920, 1080), (640, 480))
    assert intr.fx == pytest.approx(1000 * 480 / 1080) and intr.cx == pytest.approx(320.0)
    assert imu_cam is None or imu_cam.shape == (4, 4)
