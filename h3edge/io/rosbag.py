"""rosbag2 recordings (sqlite3 ``.db3`` and MCAP) as a :class:`~h3edge.io.sequence.Sequence`, read
with ``rosbags`` through the same topic options as live ROS input (:class:`~h3edge.io.ros.RosConfig`).

Opening scans the bag once: the colour and depth images' header stamps (not their pixels), every
camera info and every pose message. Colour and depth are paired by nearest stamp within
``pair_tolerance_s``; each pair becomes a frame whose pose is the base pose interpolated at the
colour stamp (SLERP, between poses at most ``MAX_POSE_GAP_S`` apart) composed with the extrinsic.
Pairs without a pose or camera info are left out, counted in :attr:`RosbagSequence.skipped`.
Depth whose own camera info (``depth_camera_info_topic``) differs from the colour camera's is
registered into the colour camera with ``depth_to_color`` (:mod:`h3edge.geometry.registration`) or
the bag's ``/tf_static`` between the two cameras' frame ids, or the bag is refused.
Reading a frame fetches its two messages by their bag time.

:func:`write_rosbag` records a sequence as a robot would publish it (colour ``bgr8``, depth
``16UC1`` mm, camera info, odometry of the base); the tests and ``h3edge sim bag`` use it.
"""

from __future__ import annotations

import bisect
import logging
from pathlib import Path

import numpy as np

import h3edge.io.ros as ros
from h3edge.geometry.camera import Intrinsics, invert_pose, rigid_error
from h3edge.geometry.poses import interpolate_pose
from h3edge.geometry.registration import register_depth
from h3edge.io.ros import RosConfig
from h3edge.io.sequence import DatasetError, Frame, SequenceBase

log = logging.getLogger(__name__)
TF_STATIC_TOPIC = "/tf_static"  # static transforms: the depth -> colour extrinsics of a recording, where it has them
MAX_POSE_GAP_S = 0.2  # a frame is interpolated only between poses at most this far apart


def is_rosbag(path: Path) -> bool:
    p = Path(path)
    return (p.is_dir() and (p / "metadata.yaml").is_file()) or p.suffix in (".mcap", ".db3", ".bag")


def _reader(path: Path):
    from rosbags.highlevel import AnyReader

    p = Path(path)
    try:
        reader = AnyReader([p], default_typestore=ros.typestore())
        reader.open()
    except Exception as e:  # noqa: BLE001 - rosbags raises its own error types per format
        raise DatasetError(f"{p}: cannot open as a ROS 1 or ROS 2 recording ({type(e).__name__}: {e})") from None
    return reader


class RosbagSequence(SequenceBase):
    def __init__(self, root: str | Path, cfg: RosConfig = RosConfig()):
        if not cfg.base_to_camera:
            raise DatasetError("a rosbag needs the base -> camera extrinsic: [ros] base_to_camera or "
                               "--base-to-camera ('x y z qx qy qz qw', or 'identity' when the poses are the camera's)")
        self.root, self.cfg = Path(root), cfg
        self.extrinsic = ros.extrinsic_matrix(cfg.base_to_camera)
        self.skipped: dict[str, int] = {}
        self._color_frame = ""  # the colour camera info's frame id
        self._reader = _reader(self.root)
        conns = {c.topic: c for c in self._reader.connections}
        want = {"color": cfg.color_topic, "depth": cfg.depth_topic, "camera_info": cfg.camera_info_topic,
                "pose": cfg.pose_topic}
        missing = [t for t in want.values() if t not in conns]
        if missing:
            raise DatasetError(f"{self.root}: topics {missing} not in the bag (it has {sorted(conns)})")
        self._conns = {role: conns[t] for role, t in want.items()}
        self._scan()
        # depth from its own camera: registered into the colour camera with cfg.depth_to_color, else refused
        self._registration: tuple[Intrinsics, np.ndarray] | None = None
        if cfg.depth_camera_info_topic in conns:
            self._check_registration(conns[cfg.depth_camera_info_topic], conns.get(TF_STATIC_TOPIC))

    def _check_registration(self, conn, tf_static) -> None:
        """Where the bag's depth camera info says its depth is not registered to colour: the depth
        camera and the depth -> colour transform it is registered with (``depth_to_color``, else the
        bag's ``/tf_static`` between the two camera infos' frame ids), or DatasetError without either."""
        for _, _, raw in self._reader.messages(connections=[conn]):
            try:
                msg = self._reader.deserialize(raw, conn.msgtype)
                depth = ros.camera_intrinsics(msg)
            except ros.RosMessageError as e:
                raise DatasetError(f"{self.root}: {self.cfg.depth_camera_info_topic}: {e}") from None
            why = ros.registration_mismatch(self.intrinsics, depth)
            if not why:
                return
            if self.cfg.depth_to_color:
                extr, source = ros.extrinsic_matrix(self.cfg.depth_to_color, "depth_to_color"), "depth_to_color"
            else:
                extr = self._tf_static(tf_static, self._color_frame, msg.header.frame_id)
                source = f"/tf_static {self._color_frame} <- {msg.header.frame_id}"
                if extr is None:
                    raise DatasetError(f"{self.root}: {why} (no /tf_static chain from the depth camera's frame "
                                       f"{msg.header.frame_id!r} to the colour camera's {self._color_frame!r})")
            self._registration = (depth, extr)
            log.info("%s: depth (%dx%d, fx %.1f) registered into the colour camera (%dx%d, fx %.1f) with %s",
                     self.root, depth.width, depth.height, depth.fx, self.intrinsics.width, self.intrinsics.height,
                     self.intrinsics.fx, source)
            return

    def _tf_static(self, conn, target: str, source: str) -> np.ndarray | None:
        """``target <- source`` from the bag's static transforms (None: no chain, or no ``/tf_static``)."""
        if conn is None:
            return None
        transforms = []
        for _, _, raw in self._reader.messages(connections=[conn]):
            try:
                transforms += ros.poses_from_message(self._reader.deserialize(raw, conn.msgtype), ros.TF)
            except ros.RosMessageError as e:
                log.warning("%s: /tf_static: %s", self.root, e)
        extr = ros.chained_transform(transforms, target, source)
        return extr if extr is not None and rigid_error(extr) is None else None

    def _skip(self, why: str) -> None:
        self.skipped[why] = self.skipped.get(why, 0) + 1

    def _scan(self) -> None:
        cfg = self.cfg
        stamps: dict[str, list[tuple[int, int]]] = {"color": [], "depth": []}  # (header stamp, bag time)
        infos: dict[tuple[int, int], Intrinsics] = {}
        poses: list[tuple[int, np.ndarray]] = []
        pose_type = self._conns["pose"].msgtype
        by_id = {c.id: role for role, c in self._conns.items()}
        for conn, bag_t, raw in self._reader.messages(connections=list(self._conns.values())):
            role = by_id[conn.id]
            try:
                msg = self._reader.deserialize(raw, conn.msgtype)
                if role in stamps:
                    own_camera = role == "depth" and cfg.depth_to_color  # registered from its own frame
                    if cfg.camera_frame and msg.header.frame_id != cfg.camera_frame and not own_camera:
                        self._skip("frame_id")
                        continue
                    stamps[role].append((ros.stamp_ns(msg.header), bag_t))
                elif role == "camera_info":
                    intr = ros.camera_intrinsics(msg)
                    infos[(intr.width, intr.height)] = intr
                    self._color_frame = msg.header.frame_id
                else:
                    for p in ros.poses_from_message(msg, pose_type):
                        if ros.pose_mismatch(p, pose_type, cfg.world_frame, cfg.base_frame) is None:
                            poses.append((p.stamp_ns, p.matrix))
            except ros.RosMessageError as e:
                self._skip(f"bad_{role}")
                log.warning("%s: %s", self.root, e)
        poses.sort(key=lambda x: x[0])
        self._pose_t = [t for t, _ in poses]
        self._poses = [m for _, m in poses]
        depth = sorted(stamps["depth"])
        depth_t = [t for t, _ in depth]
        tol = int(cfg.pair_tolerance_s * 1e9)
        frames = []
        for t, bag_t in sorted(stamps["color"]):
            j = bisect.bisect_left(depth_t, t)
            near = [k for k in (j - 1, j) if 0 <= k < len(depth)]
            if not near:
                self._skip("unpaired")
                continue
            k = min(near, key=lambda k: abs(depth_t[k] - t))
            if abs(depth_t[k] - t) > tol:
                self._skip("unpaired")
                continue
            pose = self._pose_at(t)
            if pose is None:
                self._skip("no_pose")
                continue
            frames.append((t, bag_t, depth[k][1], pose))
        if not frames:
            raise DatasetError(f"{self.root}: no colour + depth pair with a pose (skipped: {self.skipped})")
        if not infos:
            raise DatasetError(f"{self.root}: no camera info on {cfg.camera_info_topic}")
        self._frames = frames
        self._infos = infos
        self.intrinsics = next(iter(infos.values()))
        if self.skipped:
            log.info("%s: %d frames; left out %s", self.root, len(frames), self.skipped)

    def _pose_at(self, t: int) -> np.ndarray | None:
        i = bisect.bisect_left(self._pose_t, t)
        if i < len(self._pose_t) and self._pose_t[i] == t:
            base = self._poses[i]
        elif 0 < i < len(self._pose_t) and self._pose_t[i] - self._pose_t[i - 1] <= MAX_POSE_GAP_S * 1e9:
            t0, t1 = self._pose_t[i - 1], self._pose_t[i]
            base = interpolate_pose(self._poses[i - 1], self._poses[i], (t - t0) / (t1 - t0))
        else:
            return None
        return ros.camera_pose(base, self.extrinsic)

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def poses(self) -> np.ndarray:
        return np.stack([f[3] for f in self._frames])

    def _message(self, role: str, bag_t: int):
        conn = self._conns[role]
        for c, _, raw in self._reader.messages(connections=[conn], start=bag_t, stop=bag_t + 1):
            return self._reader.deserialize(raw, c.msgtype)
        raise DatasetError(f"{self.root}: {conn.topic} message at bag time {bag_t} disappeared")

    def _load(self, i: int) -> Frame:
        t, color_t, depth_t, pose = self._frames[i]
        try:
            color = ros.image_color(self._message("color", color_t))
            depth = ros.image_depth(self._message("depth", depth_t), self.cfg.depth_scale)
        except ros.RosMessageError as e:
            raise DatasetError(f"{self.root}: frame {i}: {e}") from None
        h, w = color.shape[:2]
        intr = self._infos.get((w, h))
        if intr is not None and self._registration is not None:
            try:
                depth = register_depth(depth, self._registration[0], intr, self._registration[1])
            except ValueError as e:
                raise DatasetError(f"{self.root}: frame {i}: {e}") from None
        if intr is None or depth.shape != (h, w):
            raise DatasetError(f"{self.root}: frame {i}: colour {w}x{h}, depth {depth.shape[::-1]}, camera info for "
                               f"{sorted(self._infos)}: publish depth registered to the colour camera")
        return Frame(i, t * 1e-9, color, depth, pose.copy(), intr)

    def close(self) -> None:
        self._reader.close()


def write_rosbag(seq, out: str | Path, cfg: RosConfig, storage: str = "mcap", rate: float = 30.0,
                 start_ns: int = 1_700_000_000_000_000_000, frames: int | None = None,
                 depth_intrinsics: Intrinsics | None = None, depth_to_color: np.ndarray | None = None) -> Path:
    """Record ``seq`` as a robot would publish it on ``cfg``'s topics (odometry of the base, whose
    pose with ``cfg.base_to_camera`` is the camera's); ``storage``: ``mcap`` or ``sqlite3`` (ROS 2
    bags), ``ros1`` (a ROS 1 ``.bag``: ROS 1 message definitions, ``K`` / ``D`` in the camera info).
    ``depth_intrinsics``: also a depth camera info (on ``cfg.depth_camera_info_topic``) saying so,
    as a driver recording unregistered depth does; with ``depth_to_color`` (4x4, the depth camera's
    optical frame in the colour camera's) the depth images are written as that depth camera sees
    them (the sequence's depth registered into it, in its own frame id, with ``/tf_static`` from a
    camera link to both optical frames), else as they are."""
    from rosbags.rosbag1 import Writer as Ros1Writer
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    out = Path(out)
    if out.exists():
        raise DatasetError(f"{out}: exists")
    inv = invert_pose(ros.extrinsic_matrix(cfg.base_to_camera))
    ts = ros.typestore()
    n = len(seq) if frames is None else min(frames, len(seq))
    cam = cfg.camera_frame or "camera_color_optical_frame"
    if storage == "ros1":
        from rosbags.typesys import get_types_from_msg

        writer, conn_ts = Ros1Writer(out), get_typestore(Stores.ROS1_NOETIC)
        # ROS 1's tf2_msgs/TFMessage, which the Noetic store leaves out
        conn_ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", ros.TF))

        def encode(msg, msgtype: str) -> bytes:  # the same fields in ROS 1's wire format
            return ts.cdr_to_ros1(ros.serialize(msg), msgtype)
    else:
        plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
        writer, conn_ts = Writer(out, version=9, storage_plugin=plugin), ts

        def encode(msg, msgtype: str) -> bytes:
            return ros.serialize(msg)
    with writer as w:
        conn = {"color": w.add_connection(cfg.color_topic, ros.IMAGE, typestore=conn_ts),
                "depth": w.add_connection(cfg.depth_topic, ros.IMAGE, typestore=conn_ts),
                "camera_info": w.add_connection(cfg.camera_info_topic, ros.CAMERA_INFO, typestore=conn_ts),
                "pose": w.add_connection(cfg.pose_topic, ros.ODOMETRY, typestore=conn_ts)}
        depth_cam = cam
        if depth_intrinsics is not None:
            conn["depth_info"] = w.add_connection(cfg.depth_camera_info_topic, ros.CAMERA_INFO, typestore=conn_ts)
        if depth_intrinsics is not None and depth_to_color is not None:
            # the driver's static tree: camera_link -> each optical frame
            depth_cam = "camera_depth_optical_frame"
            link_color = ros.extrinsic_matrix("0 0.015 0 -0.5 0.5 -0.5 0.5")
            tf = ros.tf_message([(link_color, start_ns, "camera_link", cam),
                                 (link_color @ depth_to_color, start_ns, "camera_link", depth_cam)])
            w.write(w.add_connection(TF_STATIC_TOPIC, ros.TF, typestore=conn_ts), start_ns, encode(tf, ros.TF))
        for i in range(n):
            f = seq[i]
            t = start_ns + int(i * 1e9 / rate)
            base = f.pose @ inv
            w.write(conn["pose"], t, encode(ros.odometry_message(base, t, cfg.world_frame or "odom", cfg.base_frame),
                                            ros.ODOMETRY))
            w.write(conn["camera_info"], t, encode(ros.camera_info_message(f.intrinsics, t, cam), ros.CAMERA_INFO))
            if depth_intrinsics is not None:
                w.write(conn["depth_info"], t, encode(ros.camera_info_message(depth_intrinsics, t, depth_cam),
                                                      ros.CAMERA_INFO))
            w.write(conn["color"], t, encode(ros.color_message(f.color, t, cam, "bgr8"), ros.IMAGE))
            depth = f.depth
            if depth_intrinsics is not None and depth_to_color is not None:
                depth = register_depth(depth, f.intrinsics, depth_intrinsics, invert_pose(depth_to_color))
            w.write(conn["depth"], t + 1000, encode(ros.depth_message(depth, t + 2_000_000, depth_cam,
                                                                      depth_scale=cfg.depth_scale), ros.IMAGE))
    return out
