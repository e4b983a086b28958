"""Simulated robots: stream a sequence onto zenoh as a robot would, in h3edge's own messages
(``h3edge sim publish``) or as ROS 2 topics through a zenoh bridge (CDR), at a camera's rate."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable

import numpy as np
import zenoh

from h3edge.io.protocol import Keys


class SubSequence:
    """Frames ``idx`` of ``seq`` as a sequence of their own (what one robot of a fleet streams), their
    poses moved into another world frame by ``world_from_seq`` (4, 4; default: the same frame)."""

    def __init__(self, seq, idx, world_from_seq: np.ndarray | None = None):
        self.seq, self.idx = seq, [int(i) for i in idx]
        self.intrinsics = seq.intrinsics
        self.world_from_seq = np.eye(4) if world_from_seq is None else np.asarray(world_from_seq, np.float64)
        self.poses = self.world_from_seq @ np.asarray(seq.poses)[self.idx]

    def __len__(self) -> int:
        return len(self.idx)

    def __getitem__(self, k: int):
        f = self.seq[self.idx[k]]
        return dataclasses.replace(f, pose=self.world_from_seq @ f.pose)


def publish_sequence(session: zenoh.Session, seq, keys: Keys, rate: float = 30.0, pose_rate: float | None = None,
                     jitter_ms: float = 0.0, frames: int | None = None, stride: int = 1, embed_pose: bool = False,
                     seed: int = 0, stop: threading.Event | None = None, on_frame: Callable | None = None,
                     color_encoding: str = "jpeg") -> dict:
    """Stream a sequence as the robot would: frames at ``rate`` Hz and poses on their own key at
    ``pose_rate`` Hz (SLERP-interpolated along the trajectory; default: 30 Hz, odometry-like), each
    message sent up to ``jitter_ms`` late (timestamps stay exact). Timestamps are host time."""
    from h3edge.geometry.poses import interpolate_pose
    from h3edge.io.protocol import FrameMessage, PoseMessage, encode_frame, encode_pose

    idx = list(range(0, len(seq), max(1, stride)))[:frames]
    rng = np.random.default_rng(seed)
    pub_f = session.declare_publisher(keys.frame, congestion_control=zenoh.CongestionControl.BLOCK)
    pub_p = session.declare_publisher(keys.pose, congestion_control=zenoh.CongestionControl.BLOCK)
    poses = seq.poses[idx]
    t0 = time.time() + 0.5
    frame_t = t0 + np.arange(len(idx)) / rate
    events: list[tuple[float, str, int]] = [(t, "frame", i) for i, t in enumerate(frame_t)]
    if not embed_pose:
        pr = pose_rate or 30.0
        pose_t = np.arange(t0 - 0.2, frame_t[-1] + 0.3, 1.0 / pr)
        events += [(t, "pose", j) for j, t in enumerate(pose_t)]
    jit = rng.uniform(0, jitter_ms / 1000.0, len(events)) if jitter_ms > 0 else np.zeros(len(events))
    order = np.argsort([e[0] + j for e, j in zip(events, jit)], kind="stable")
    sent = {"frames": 0, "poses": 0}
    for k in order:
        t, kind, i = events[k]
        delay = t + jit[k] - time.time()
        if delay > 0:
            if stop is not None and stop.wait(delay):
                break
            elif stop is None:
                time.sleep(delay)
        ts = int(t * 1e9)
        if kind == "frame":
            f = seq[idx[i]]
            msg = FrameMessage(ts, int(idx[i]), f.color, f.depth, f.intrinsics, f.pose if embed_pose else None)
            pub_f.put(encode_frame(msg, color_encoding))
            sent["frames"] += 1
            if on_frame is not None:
                on_frame(i, len(idx))
        else:
            u = (t - t0) * rate  # position along the frame sequence
            a = int(np.clip(np.floor(u), 0, len(idx) - 1))
            b = min(a + 1, len(idx) - 1)
            alpha = float(np.clip(u - a, 0.0, 1.0)) if b > a else 0.0
            pub_p.put(encode_pose(PoseMessage(ts, interpolate_pose(poses[a], poses[b], alpha))))
            sent["poses"] += 1
    pub_f.undeclare()
    pub_p.undeclare()
    return sent


def publish_ros_sequence(session: zenoh.Session, seq, cfg, rate: float = 30.0, pose_rate: float = 60.0,
                         frames: int | None = None, stride: int = 1, stop: threading.Event | None = None,
                         encoded: list | None = None) -> dict:
    """Stream a sequence as a ROS 2 robot would through zenoh (``cfg``: a
    :class:`~h3edge.io.ros.RosConfig`: its topics and key style): colour ``bgr8`` + depth ``16UC1``
    + camera info at ``rate``, odometry of the base (the camera pose composed with the inverse of
    ``cfg.base_to_camera``) at ``pose_rate``, all as CDR. ``encoded``: pre-serialised frames
    ``[(color, depth, info)]`` to send in turn instead of encoding each (a rate benchmark)."""
    from h3edge.geometry.camera import invert_pose
    from h3edge.geometry.poses import interpolate_pose
    from h3edge.io import ros

    keys = {role: key.replace("/*", "/RIHS01_h3edge") for role, key in cfg.keys().items()}
    # BLOCK, as publish_sequence: on a loaded host zenoh's default (DROP) sheds whole images
    # when the transmit queue is full, and a simulated robot should deliver what it counts as sent.
    pubs = {role: session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            for role, key in keys.items()}
    inv = invert_pose(ros.extrinsic_matrix(cfg.base_to_camera or "identity"))
    idx = list(range(0, len(seq), max(1, stride)))[:frames]
    bases = [seq.poses[i] @ inv for i in idx]
    cam = cfg.camera_frame or "camera_color_optical_frame"
    world = cfg.world_frame or "odom"
    t0 = time.time() + 0.2
    per_frame = max(1, round(pose_rate / rate))
    sent = {"frames": 0, "poses": 0}
    for n, i in enumerate(idx):
        t_frame = t0 + n / rate
        delay = t_frame - time.time()
        if delay > 0:
            if stop is None:
                time.sleep(delay)
            elif stop.wait(delay):
                break
        ts = int(t_frame * 1e9)
        nxt = bases[min(n + 1, len(bases) - 1)]
        for k in range(per_frame):
            a = k / per_frame
            pubs["pose"].put(ros.serialize(ros.odometry_message(interpolate_pose(bases[n], nxt, a),
                                                                ts + int(a * 1e9 / rate), world, cfg.base_frame)))
            sent["poses"] += 1
        if encoded is not None:
            color, depth, info = encoded[n % len(encoded)]
            color, depth, info = (restamp(color, ts), restamp(depth, ts), restamp(info, ts))
        else:
            f = seq[i]
            info = ros.serialize(ros.camera_info_message(f.intrinsics, ts, cam))
            color = ros.serialize(ros.color_message(f.color, ts, cam, "bgr8"))
            depth = ros.serialize(ros.depth_message(f.depth, ts, cam, depth_scale=cfg.depth_scale))
        pubs["camera_info"].put(info)
        if "depth_camera_info" in pubs:  # depth registered to colour: the same camera
            pubs["depth_camera_info"].put(info)
        if n == 0:  # topics arrive on separate callbacks: the first images must not beat their camera info
            time.sleep(0.2)
        pubs["color"].put(color)
        pubs["depth"].put(depth)
        sent["frames"] += 1
    for p in pubs.values():
        p.undeclare()
    return sent


def restamp(cdr: bytes, stamp_ns: int) -> bytes:
    """A CDR message whose first field is a ``std_msgs/Header`` with its stamp replaced (bytes 4-11
    after the encapsulation header: sec int32, nanosec uint32, little endian)."""
    import struct

    return cdr[:4] + struct.pack("<iI", stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000) + cdr[12:]
