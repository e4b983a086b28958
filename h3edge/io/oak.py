"""Luxonis OAK RGB-D camera source (depthai v3): colour and stereo depth aligned to colour,
synchronised on the device, published in the service's wire protocol (``h3edge camera oak``).

Only :func:`run_oak` touches a device; everything it relies on is testable without one:
- :func:`crop_intrinsics`: the calibration's intrinsics after ``requestOutput(..., CROP)``
  (centre crop to the output's aspect, then scale), :func:`frame_intrinsics`: a frame's own
  ``ImgTransformation`` when the device filled it in, else that;
- :class:`HostClock`: depthai stamps messages on the host's steady clock (``getTimestamp()``,
  already converted from device time by depthai; CLOCK_MONOTONIC on Linux); the protocol's
  timestamps are host unix nanoseconds, shared with the pose publishers;
- :func:`group_to_message`: a synchronised ``MessageGroup`` (``rgb``, ``depth`` uint16 mm) ->
  :class:`~h3edge.io.protocol.FrameMessage`;
- :func:`vio_pose`: BasaltVIO's IMU-body pose -> colour-camera-to-world;
- :func:`build_pipeline`: the node graph on a pipeline (RVC2: StereoDepth aligns depth to the
  colour output itself, ``inputAlignTo``; RVC4: an ``ImageAlign`` node), poses from BasaltVIO +
  IMU when asked.

Poses come either from the robot's odometry on ``h3edge/<id>/pose`` (``external``: the source
only checks that some arrive) or from depthai's BasaltVIO node (``vio``: published on the same key).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass
from datetime import timedelta

import cv2
import numpy as np

from h3edge.geometry.camera import Intrinsics
from h3edge.geometry.poses import pose_from_tq
from h3edge.io.protocol import FrameMessage

log = logging.getLogger(__name__)

STEREO_SIZE = (640, 400)  # mono sensors' output fed to StereoDepth (OV9282: 1280x800 native)


class OakUnavailable(RuntimeError):
    """The camera, depthai or the chosen pose source is not there: a one-line message for the user."""


@dataclass(frozen=True)
class OakConfig:
    width: int = 640  # colour output (depth is aligned to it, same size)
    height: int = 480
    fps: float = 15.0
    pose_source: str = "external"  # external: robot odometry on h3edge/<id>/pose | vio: depthai BasaltVIO
    pose_wait_s: float = 10.0  # external: a pose must arrive on the pose key within this (0: don't check)
    stereo_preset: str = "DEFAULT"  # dai.node.StereoDepth.PresetMode name
    vio_fps: float = 60.0  # mono outputs feeding BasaltVIO (depthai's VIO examples)
    imu_rate_hz: int = 200
    color_encoding: str = "jpeg"  # protocol colour encoding (jpeg | png | raw_rgb8)

    def __post_init__(self) -> None:
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 3072):
            raise ValueError(f"output size {self.width}x{self.height} out of range (16..4096 x 16..3072)")
        if self.width % 16:
            raise ValueError(f"width {self.width} must be a multiple of 16 (StereoDepth's aligned output)")
        if not 0 < self.fps <= 60:
            raise ValueError(f"fps {self.fps} out of range (0, 60]")
        if self.pose_source not in ("external", "vio"):
            raise ValueError(f"pose source must be external or vio, got {self.pose_source!r}")

    @property
    def sync_threshold(self) -> timedelta:
        """Colour and depth count as one frame when stamped within half a frame period."""
        return timedelta(seconds=1.0 / (2.0 * self.fps))


def require_depthai():
    """The depthai module, or a one-line error saying how to get it."""
    os.environ.setdefault("DEPTHAI_LEVEL", "error")  # depthai's own logger, else it warns on stderr at import
    try:
        import depthai
    except ImportError:
        raise OakUnavailable("depthai is not installed: pip install 'h3edge[oak]'") from None
    if not hasattr(depthai, "node") or not hasattr(depthai.node, "Camera"):
        raise OakUnavailable(f"depthai {getattr(depthai, '__version__', '?')} is too old: h3edge needs depthai v3")
    return depthai


# ----------------------------------------------------------------------------- pure conversions
def crop_intrinsics(k: np.ndarray, src_size: tuple[int, int], out_size: tuple[int, int]) -> Intrinsics:
    """Intrinsics of an ``out_size`` (w, h) output cut from a ``src_size`` image as depthai's
    ``ImgResizeMode.CROP`` does: the largest centred crop with the output's aspect, then a scale."""
    k = np.asarray(k, np.float64)
    (sw, sh), (ow, oh) = src_size, out_size
    scale = max(ow / sw, oh / sh)  # the crop keeps the whole of the tighter axis
    cw, ch = ow / scale, oh / scale
    x0, y0 = (sw - cw) / 2.0, (sh - ch) / 2.0
    return Intrinsics(ow, oh, k[0, 0] * scale, k[1, 1] * scale, (k[0, 2] - x0) * scale, (k[1, 2] - y0) * scale)


def frame_intrinsics(frame, fallback: Intrinsics) -> Intrinsics:
    """The frame's own intrinsics (its ImgTransformation, which follows every crop and scale the
    device applied) when valid and of the frame's size, else ``fallback``."""
    try:
        t = frame.getTransformation()
        if t.isValid() and tuple(t.getSize()) == (frame.getWidth(), frame.getHeight()):
            k = np.asarray(t.getIntrinsicMatrix(), np.float64)
            if np.all(np.isfinite(k)) and k[0, 0] > 0 and k[1, 1] > 0:
                return Intrinsics(frame.getWidth(), frame.getHeight(), k[0, 0], k[1, 1], k[0, 2], k[1, 2])
    except (AttributeError, RuntimeError):
        pass
    return fallback


def timedelta_ns(td: timedelta) -> int:
    """Exact integer nanoseconds of a timedelta (depthai's timestamps), no float rounding."""
    return ((td.days * 86_400 + td.seconds) * 1_000_000 + td.microseconds) * 1_000


class HostClock:
    """Maps depthai host timestamps (steady clock = CLOCK_MONOTONIC) to host unix nanoseconds, the
    protocol's clock. The offset is re-read on every call, so an NTP step or slew of the wall clock
    is followed as it happens (the pose publishers use the wall clock too)."""

    def __init__(self, monotonic_ns=time.monotonic_ns, unix_ns=time.time_ns):
        self._mono, self._unix = monotonic_ns, unix_ns

    def offset_ns(self) -> int:
        a = self._mono()
        u = self._unix()
        b = self._mono()
        return u - (a + b) // 2

    def to_unix_ns(self, steady: timedelta) -> int:
        return timedelta_ns(steady) + self.offset_ns()


def group_to_message(group, frame_id: int, clock: HostClock, fallback: Intrinsics,
                     pose: np.ndarray | None = None) -> FrameMessage:
    """A synchronised group (``rgb``: colour ImgFrame, ``depth``: uint16 mm aligned to it) as a
    frame message stamped with the colour frame's capture time in host unix ns. Raises
    ValueError on a frame that cannot be used (missing part, wrong type, empty)."""
    try:
        rgb, depth = group["rgb"], group["depth"]
    except (KeyError, IndexError, RuntimeError):
        raise ValueError("message group lacks rgb or depth") from None
    if rgb is None or depth is None:
        raise ValueError("message group lacks rgb or depth")
    bgr = rgb.getCvFrame()
    if bgr is None or bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.size == 0:
        raise ValueError(f"colour frame has shape {getattr(bgr, 'shape', None)}, expected (H, W, 3)")
    mm = depth.getFrame()
    if mm is None or mm.dtype != np.uint16 or mm.ndim != 2:
        raise ValueError(
            f"depth frame is {getattr(mm, 'dtype', None)} {getattr(mm, 'shape', None)}, expected uint16 (H, W) mm"
        )
    h, w = bgr.shape[:2]
    if mm.shape != (h, w):  # aligned to colour but at another resolution: nearest keeps depth edges
        mm = cv2.resize(mm, (w, h), interpolation=cv2.INTER_NEAREST)
    intr = frame_intrinsics(rgb, fallback)
    if (intr.width, intr.height) != (w, h):
        raise ValueError(f"colour frame is {w}x{h}, the camera was set up for {intr.width}x{intr.height}")
    return FrameMessage(timestamp_ns=clock.to_unix_ns(rgb.getTimestamp()), frame_id=int(frame_id),
                        color=np.ascontiguousarray(bgr[..., ::-1]), depth=mm.astype(np.float32) / 1000.0,
                        intrinsics=intr, pose=pose, frame_name=f"oak-{rgb.getSequenceNum()}")


def transform_tq(tr) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """(translation, quaternion x, y, z, w) of a depthai TransformData."""
    t, q = tr.getTranslation(), tr.getQuaternion()
    return (t.x, t.y, t.z), (q.qx, q.qy, q.qz, q.qw)


def vio_pose(t, q, imu_to_camera: np.ndarray) -> np.ndarray:
    """Colour-camera-to-world from BasaltVIO's IMU-body-to-world (t metres, q x, y, z, w) and the
    calibration's IMU -> colour camera extrinsics (4x4, translation already in metres):
    T_world_cam = T_world_imu @ inv(T_cam_imu)."""
    if not np.all(np.isfinite(np.asarray(t, np.float64))):
        raise ValueError(f"translation {t} is not finite")
    n = float(np.linalg.norm(np.asarray(q, np.float64)))
    if not np.isfinite(n) or abs(n - 1.0) > 1e-3:  # VIO sends unit quaternions: anything else is corrupt
        raise ValueError(f"quaternion norm {n} is not 1")
    return pose_from_tq(np.asarray(t, np.float64), q) @ np.linalg.inv(np.asarray(imu_to_camera, np.float64))


# ------------------------------------------------------------------------------ the node graph
@dataclass
class OakStreams:
    frames: object  # output queue of synchronised rgb + depth groups
    poses: object | None  # output queue of BasaltVIO TransformData, when pose_source is vio


def build_pipeline(dai, pipeline, cfg: OakConfig, platform) -> OakStreams:
    """Colour (CAM_A) at ``cfg.width x cfg.height``, CROP-resized and undistorted; stereo depth
    from CAM_B / CAM_C aligned to that colour output; both into a Sync node (``rgb``, ``depth``);
    with ``pose_source == "vio"`` also IMU + mono outputs into BasaltVIO."""
    cam = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
    rgb = cam.requestOutput((cfg.width, cfg.height), dai.ImgFrame.Type.RGB888i, dai.ImgResizeMode.CROP, cfg.fps, True)
    left = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
    right = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C)
    try:
        preset = getattr(dai.node.StereoDepth.PresetMode, cfg.stereo_preset)
    except AttributeError:
        raise OakUnavailable(f"unknown stereo preset {cfg.stereo_preset!r}") from None
    stereo = pipeline.create(dai.node.StereoDepth).build(left.requestOutput(STEREO_SIZE, fps=cfg.fps),
                                                         right.requestOutput(STEREO_SIZE, fps=cfg.fps), preset)
    sync = pipeline.create(dai.node.Sync)
    sync.setSyncThreshold(cfg.sync_threshold)
    rgb.link(sync.inputs["rgb"])
    if platform == dai.Platform.RVC4:
        align = pipeline.create(dai.node.ImageAlign)
        stereo.depth.link(align.input)
        rgb.link(align.inputAlignTo)
        align.outputAligned.link(sync.inputs["depth"])
    else:  # RVC2: StereoDepth resamples depth onto the linked colour output
        rgb.link(stereo.inputAlignTo)
        stereo.depth.link(sync.inputs["depth"])
    frames = sync.out.createOutputQueue(maxSize=4, blocking=False)
    poses = None
    if cfg.pose_source == "vio":
        if not hasattr(dai.node, "BasaltVIO"):
            raise OakUnavailable(f"depthai {getattr(dai, '__version__', '?')} has no BasaltVIO node: "
                                 "use --pose-source external (robot odometry on the pose key)")
        imu = pipeline.create(dai.node.IMU)
        imu.enableIMUSensor([dai.IMUSensor.ACCELEROMETER_RAW, dai.IMUSensor.GYROSCOPE_RAW], cfg.imu_rate_hz)
        imu.setBatchReportThreshold(1)
        imu.setMaxBatchReports(10)
        vio = pipeline.create(dai.node.BasaltVIO)
        left.requestOutput(STEREO_SIZE, fps=cfg.vio_fps).link(vio.left)
        right.requestOutput(STEREO_SIZE, fps=cfg.vio_fps).link(vio.right)
        imu.out.link(vio.imu)
        poses = vio.transform.createOutputQueue(maxSize=64, blocking=False)
    return OakStreams(frames, poses)


# ------------------------------------------------------------------------------ device-facing
def open_device(dai):
    """The first OAK found, or a one-line error."""
    try:
        found = dai.Device.getAllAvailableDevices()
    except RuntimeError as e:
        raise OakUnavailable(f"cannot search for OAK devices: {e}") from None
    if not found:
        raise OakUnavailable("no OAK device found (USB: check the cable and the udev rule "
                             "deploy/80-movidius.rules; PoE: check the network)")
    try:
        return dai.Device()
    except RuntimeError as e:
        raise OakUnavailable(f"cannot open the OAK device: {e}") from None


def calibration_intrinsics(dai, device, cfg: OakConfig) -> tuple[Intrinsics, np.ndarray | None]:
    """(colour intrinsics for the output size from the device calibration, IMU -> colour camera
    extrinsics in metres or None when the calibration has none)."""
    calib = device.readCalibration()
    k, w, h = calib.getDefaultIntrinsics(dai.CameraBoardSocket.CAM_A)
    intr = crop_intrinsics(np.asarray(k), (int(w), int(h)), (cfg.width, cfg.height))
    imu_cam = None
    try:
        imu_cam = np.asarray(calib.getImuToCameraExtrinsics(dai.CameraBoardSocket.CAM_A, False), np.float64)
        imu_cam[:3, 3] /= 100.0  # depthai extrinsics are in centimetres
    except RuntimeError:
        pass
    return intr, imu_cam


def wait_for_pose(session, key: str, timeout: float) -> bool:
    """True when a message arrives on ``key`` within ``timeout`` seconds."""
    got = threading.Event()
    sub = session.declare_subscriber(key, lambda _sample: got.set())
    try:
        return got.wait(timeout)
    finally:
        sub.undeclare()


def run_oak(cfg: OakConfig, session, keys, device, dai, stop: threading.Event | None = None,
            frames: int | None = None) -> dict:
    """Stream an opened OAK ``device`` (:func:`open_device`) to ``keys.frame`` (and VIO poses to
    ``keys.pose``) until ``stop`` is set, the device stops or ``frames`` were sent; returns counts.
    Raises :class:`OakUnavailable` when the chosen pose source is not there."""
    import zenoh

    stop = stop or threading.Event()
    fallback, imu_cam = calibration_intrinsics(dai, device, cfg)
    if cfg.pose_source == "vio" and imu_cam is None:
        raise OakUnavailable("the device calibration has no IMU extrinsics: --pose-source vio needs them")
    if cfg.pose_source == "external" and cfg.pose_wait_s > 0:
        log.info("waiting up to %.0f s for poses on %s", cfg.pose_wait_s, keys.pose)
        if not wait_for_pose(session, keys.pose, cfg.pose_wait_s):
            raise OakUnavailable(f"no pose on {keys.pose} within {cfg.pose_wait_s:.0f} s: start the robot's odometry "
                                 "publisher, or use --pose-source vio")
    clock = HostClock()
    counts = {"frames": 0, "poses": 0, "dropped": 0}
    pub_f = session.declare_publisher(keys.frame, congestion_control=zenoh.CongestionControl.DROP)
    pub_p = session.declare_publisher(keys.pose, congestion_control=zenoh.CongestionControl.DROP)
    try:
        _stream(cfg, dai, device, keys, pub_f, pub_p, clock, fallback, imu_cam, stop, frames, counts)
    except RuntimeError as e:  # XLink errors: the device was unplugged or crashed
        raise OakUnavailable(f"the OAK stream stopped after {counts['frames']} frames: {e}") from None
    return counts


def _stream(cfg, dai, device, keys, pub_f, pub_p, clock, fallback, imu_cam, stop, frames, counts) -> None:
    from h3edge.io.protocol import PoseMessage, encode_frame, encode_pose

    with dai.Pipeline(device) as pipeline:
        streams = build_pipeline(dai, pipeline, cfg, device.getPlatform())
        pipeline.start()
        log.info("OAK streaming %dx%d at %.0f fps (%s), intrinsics %s, poses: %s", cfg.width, cfg.height, cfg.fps,
                 device.getPlatform().name, fallback, cfg.pose_source)
        while pipeline.isRunning() and not stop.is_set() and (frames is None or counts["frames"] < frames):
            if streams.poses is not None:
                for tr in streams.poses.tryGetAll():
                    try:
                        pose = vio_pose(*transform_tq(tr), imu_cam)
                    except ValueError as e:
                        log.warning("VIO pose dropped: %s", e)
                        continue
                    pub_p.put(encode_pose(PoseMessage(clock.to_unix_ns(tr.getTimestamp()), pose)))
                    counts["poses"] += 1
            group = streams.frames.tryGet()
            if group is None:
                time.sleep(0.002)
                continue
            try:
                msg = group_to_message(group, counts["frames"] + counts["dropped"], clock, fallback)
            except ValueError as e:
                counts["dropped"] += 1
                log.warning("OAK frame dropped: %s", e)
                continue
            pub_f.put(encode_frame(msg, cfg.color_encoding))
            counts["frames"] += 1
