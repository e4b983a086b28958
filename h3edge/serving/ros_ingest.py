"""ROS 2 topics in: colour, depth and camera-info images paired into frames, robot poses turned
into camera poses, both handed to the service's :class:`~h3edge.serving.ingest.Ingest`.

- Colour and depth are paired by header stamp: each new image looks for the other kind within
  ``pair_tolerance_s`` among the last ``pair_buffer`` of it, of a size that goes with it (the same,
  or the depth camera's own when depth is registered); paired images become one raw frame message
  (no re-encoding) stamped with the colour image's stamp, carrying the latest camera info of that
  size. Unpaired images age out of the buffer (counted ``ros_unpaired``; ``ros_size_mismatch``, with
  the sizes, for one that met only images of another size at its stamp): an odd image never takes a
  good one with it. A pair that goes on makes the older waiting images moot (aged out); a pair that
  waits for a camera info of its size does not.
- Camera info comes on its own topic, in no fixed order with the images: a pair whose size has no
  camera info yet waits (at most ``pair_buffer`` pairs) and goes on, in stamp order, when camera info
  of its size arrives; a pair pushed out of that wait is counted ``ros_no_camera_info``.
- Poses (``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped`` or ``tf2_msgs/TFMessage``) place the
  robot's ``base_frame``; the camera pose is ``T_world_base @ T_base_optical`` with the configured
  extrinsic ``base_to_camera``. There is no default extrinsic: without one (or ``identity``, said
  explicitly) the ROS ingest does not start. A TF message's transforms other than
  ``world_frame -> base_frame`` are ignored (not drops).
- Depth from its own camera (a depth camera info on ``depth_camera_info_topic`` that differs from the
  colour camera's) is registered into the colour camera with ``depth_to_color``
  (:mod:`h3edge.geometry.registration`), or dropped as ``ros_depth_not_registered`` without it.
- Frame ids are checked: images must be in ``camera_frame`` (when set), poses must place
  ``base_frame`` in ``world_frame`` (when set); a mismatch is a counted drop with the reason, as is
  every message that cannot be decoded or used.

Runs on the transport's callback threads; never raises into them and never blocks.
"""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from h3edge.errors import InputError
from h3edge.geometry.camera import Intrinsics
from h3edge.geometry.registration import register_depth
from h3edge.io import ros
from h3edge.io.protocol import FrameMessage, encode_frame
from h3edge.io.ros import RosConfig, extrinsic_matrix

log = logging.getLogger(__name__)
IMAGE_HEADER_BYTES = 4096  # bytes of a sensor_msgs/Image besides its pixels (stamp, frame id, encoding) allowed


@dataclass(eq=False)  # an image is itself: buffers remove it by identity, never by comparing pixels
class _Image:
    stamp: int
    frame_id: str
    array: np.ndarray
    mismatch: str = ""  # why an image of the other kind at its stamp did not go with it (its drop reason)


class RosIngest:
    """ROS 2 messages -> the service's frames and poses (module docstring).

    ``submit_frame(bytes)``: a raw frame message for the queue; ``add_pose(stamp_ns, matrix)``: a
    camera pose; ``on_error(code, text)``: every refused message. ``max_pixels``: an image with more
    pixels is refused (``ros_image_too_large``) before it is decoded or buffered, from its byte
    count (4 bytes a pixel at most) and then its header."""

    def __init__(self, cfg: RosConfig, submit_frame: Callable[[bytes], None],
                 add_pose: Callable[[int, np.ndarray], None], on_error: Callable[[str, str], None],
                 max_pixels: int = 1920 * 1080):
        if not cfg.base_to_camera:
            raise InputError("ROS input needs the base -> camera extrinsic: set [ros] base_to_camera "
                             "('x y z qx qy qz qw', the camera optical frame in base_frame) or 'identity' when "
                             "the poses are the camera's own")
        self.cfg, self.max_pixels = cfg, max_pixels
        self.extrinsic = extrinsic_matrix(cfg.base_to_camera)
        # depth from its own camera is registered into the colour camera with this (None: refused)
        self.depth_to_color = extrinsic_matrix(cfg.depth_to_color, "depth_to_color") if cfg.depth_to_color else None
        self.submit_frame, self.add_pose, self.on_error = submit_frame, add_pose, on_error
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()  # frames leave in the order they were paired
        self._colors: collections.deque[_Image] = collections.deque()
        self._depths: collections.deque[_Image] = collections.deque()
        self._infos: dict[tuple[int, int], Intrinsics] = {}
        self._depth_info: Intrinsics | None = None  # the depth camera's, when its topic is published
        self._waiting: collections.deque[tuple[int, _Image, _Image]] = collections.deque()  # pairs without info
        self.received = collections.Counter()  # by role
        self.drops = collections.Counter()  # by reason
        self.frames = 0  # paired frames handed on
        self._next_id = 0

    def status(self) -> dict:
        return {"keys": self.cfg.keys(), "received": dict(self.received), "frames": self.frames,
                "dropped": dict(self.drops)}

    def handler(self, role: str) -> Callable[[bytes], None]:
        """The callback for input ``role`` (a key of :meth:`RosConfig.keys`); never raises."""
        fn = {"color": self.on_color, "depth": self.on_depth, "camera_info": self.on_camera_info,
              "depth_camera_info": self.on_depth_camera_info, "pose": self.on_pose}[role]

        def call(data: bytes) -> None:
            self.received[role] += 1
            try:
                fn(data)
            except ros.RosMessageError as e:
                self._drop(f"ros_bad_{role}", str(e))
            except Exception as e:  # noqa: BLE001 - a bug must not escape into the zenoh callback
                log.exception("ROS %s message failed", role)
                self._drop("ros_internal_error", f"{role}: {type(e).__name__}: {e}")

        return call

    def _drop(self, code: str, text: str) -> None:
        self.drops[code] += 1
        self.on_error(code, text)

    # ------------------------------------------------------------------ images
    def _image(self, data: bytes, depth: bool) -> _Image | None:
        what = "depth" if depth else "colour"
        if len(data) > 4 * self.max_pixels + IMAGE_HEADER_BYTES:
            self._drop("ros_image_too_large", f"{what} image of {len(data)} bytes: more than {self.max_pixels} pixels")
            return None
        msg = ros.deserialize(data, ros.IMAGE)
        if int(msg.width) * int(msg.height) > self.max_pixels:
            self._drop("ros_image_too_large", f"{what} image {msg.width}x{msg.height}: more than {self.max_pixels} "
                                              "pixels")
            return None
        own_camera = depth and self.depth_to_color is not None  # depth in its own camera's frame, registered
        if self.cfg.camera_frame and msg.header.frame_id != self.cfg.camera_frame and not own_camera:
            self._drop("ros_frame_id", f"{'depth' if depth else 'colour'} image in frame {msg.header.frame_id!r}, "
                                       f"not camera_frame {self.cfg.camera_frame!r}")
            return None
        arr = ros.image_depth(msg, self.cfg.depth_scale) if depth else ros.image_color(msg)
        return _Image(ros.stamp_ns(msg.header), msg.header.frame_id, arr)

    def on_color(self, data: bytes) -> None:
        img = self._image(data, depth=False)
        if img is not None:
            self._pair(img, self._colors, self._depths, is_color=True)

    def on_depth(self, data: bytes) -> None:
        img = self._image(data, depth=True)
        if img is not None:
            self._pair(img, self._depths, self._colors, is_color=False)

    def on_camera_info(self, data: bytes) -> None:
        intr = ros.camera_intrinsics(ros.deserialize(data, ros.CAMERA_INFO))
        size = (intr.width, intr.height)
        with self._send_lock:
            with self._lock:
                self._infos[size] = intr
                while len(self._infos) > 4:
                    del self._infos[next(iter(self._infos))]
                ready = [p for p in self._waiting if p[1].array.shape[1::-1] == size]
                for p in ready:
                    self._waiting.remove(p)
            for frame_id, color, depth in ready:
                self._send(frame_id, color, depth, intr)

    def on_depth_camera_info(self, data: bytes) -> None:
        intr = ros.camera_intrinsics(ros.deserialize(data, ros.CAMERA_INFO))
        with self._lock:
            self._depth_info = intr

    def _pair(self, img: _Image, mine: collections.deque, others: collections.deque, is_color: bool) -> None:
        with self._send_lock:
            self._pair_and_send(img, mine, others, is_color)

    def _pair_and_send(self, img: _Image, mine: collections.deque, others: collections.deque, is_color: bool) -> None:
        tol = int(self.cfg.pair_tolerance_s * 1e9)
        depth_info = self._depth_info
        with self._lock:
            near = [o for o in others if abs(o.stamp - img.stamp) <= tol]
            # only an image of a size that goes with this one is its pair: an image of another size (a
            # bad message, or depth not registered) takes no good image with it; both wait, and the one
            # left without a pair is dropped as ros_size_mismatch when it ages out
            fit = [o for o in near if self._sizes_fit(*((img, o) if is_color else (o, img)), depth_info)]
            best = min(fit, key=lambda o: abs(o.stamp - img.stamp), default=None)
            if best is None:
                for o in near:
                    color, depth = (img, o) if is_color else (o, img)
                    why = (f"colour {color.array.shape[1]}x{color.array.shape[0]} and depth {depth.array.shape[1]}x"
                           f"{depth.array.shape[0]} at one stamp differ: publish depth registered to the colour "
                           "camera, or its camera info and the depth -> colour extrinsics (depth_to_color)")
                    img.mismatch = o.mismatch = why
                mine.append(img)
                aged = [mine.popleft() for _ in range(max(0, len(mine) - self.cfg.pair_buffer))]
            else:
                others.remove(best)
                color, depth = (img, best) if is_color else (best, img)
                aged = []
        self._age_out(aged)
        if best is None:
            return
        with self._lock:
            h, w = color.array.shape[:2]
            intr = self._infos.get((w, h))
            aged = []
            if intr is not None:  # images older than a pair that goes on will never be paired now (a pair
                # that waits for a camera info of its size may never go on: it purges nothing)
                for q, t in ((self._colors, color.stamp), (self._depths, depth.stamp)):
                    while q and q[0].stamp < t:
                        aged.append(q.popleft())
            self._next_id += 1
            frame_id = self._next_id
        self._age_out(aged)
        if intr is None:
            with self._lock:
                self._waiting.append((frame_id, color, depth))
                pushed_out = len(self._waiting) > self.cfg.pair_buffer
                if pushed_out:
                    self._waiting.popleft()
            if pushed_out:
                self._drop("ros_no_camera_info", f"no camera info for {w}x{h} images on {self.cfg.camera_info_topic} "
                                                 f"while {self.cfg.pair_buffer} pairs waited for it")
            return
        self._send(frame_id, color, depth, intr)

    def _age_out(self, images: list[_Image]) -> None:
        """Count images that leave the pair buffers without a pair: ``ros_size_mismatch`` with its reason
        where an image of the other kind at their stamp was of a size that does not go with them, else
        ``ros_unpaired``."""
        for img in images:
            if img.mismatch:
                self._drop("ros_size_mismatch", img.mismatch)
            else:
                self.drops["ros_unpaired"] += 1

    def _sizes_fit(self, color: _Image, depth: _Image, depth_info: Intrinsics | None) -> bool:
        """Whether ``depth`` can go with ``color``: the same size, or the depth camera's own size when it
        is registered into the colour camera (``depth_to_color``)."""
        if depth.array.shape == color.array.shape[:2]:
            return True
        return (self.depth_to_color is not None and depth_info is not None
                and depth.array.shape == (depth_info.height, depth_info.width))

    def _send(self, frame_id: int, color: _Image, depth: _Image, intr: Intrinsics) -> None:
        depth_info = self._depth_info
        why = ros.registration_mismatch(intr, depth_info) if depth_info is not None else None
        depth_m = depth.array
        if why and self.depth_to_color is not None:
            try:
                depth_m = register_depth(depth_m, depth_info, intr, self.depth_to_color)
            except ValueError as e:  # depth of another size than its camera info says
                self._drop("ros_depth_not_registered", str(e))
                return
        elif why:
            self._drop("ros_depth_not_registered", why)
            return
        msg = FrameMessage(color.stamp, frame_id, color.array, depth_m, intr, None, color.frame_id)
        with self._lock:
            self.frames += 1
        self.submit_frame(encode_frame(msg, "raw_rgb8", "raw_f32"))

    # ------------------------------------------------------------------- poses
    def on_pose(self, data: bytes) -> None:
        msgtype = ros.POSE_TYPES[self.cfg.pose_type]
        poses = ros.poses_from_message(ros.deserialize(data, msgtype), msgtype, self.cfg.base_frame)
        cfg = self.cfg
        for p in poses:
            why = ros.pose_mismatch(p, msgtype, cfg.world_frame, cfg.base_frame)
            if why == "other":
                continue  # other transforms of the tree
            if why:
                self._drop("ros_frame_id", why)
                continue
            self.add_pose(p.stamp_ns, ros.camera_pose(p.matrix, self.extrinsic))
