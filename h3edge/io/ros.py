"""ROS 2 messages at the edge (topics live through :mod:`h3edge.serving.ros_ingest`, recordings
through :mod:`h3edge.io.rosbag`): CDR bytes <-> arrays, intrinsics and poses, through ``rosbags``'
pure-Python typestore (no ROS install needed).

Conversions (each raises :class:`RosMessageError` naming what is wrong, never anything else):

- ``sensor_msgs/msg/Image`` -> colour uint8 (H, W, 3) RGB from ``rgb8`` / ``bgr8`` / ``rgba8`` /
  ``bgra8`` / ``mono8``; depth float32 metres (H, W) from ``16UC1`` (mm, ``depth_scale`` 1000) or
  ``32FC1`` (m). Row padding (``step``) and big-endian data are handled.
- ``sensor_msgs/msg/CameraInfo`` -> :class:`Intrinsics` from ``k``; a distortion model with
  non-zero coefficients is refused (subscribe to the rectified image, ``image_rect``).
- ``nav_msgs/msg/Odometry``, ``geometry_msgs/msg/PoseStamped``, ``tf2_msgs/msg/TFMessage`` ->
  :class:`RosPose` (stamp, parent frame, child frame, 4x4 parent <- child).

The camera pose h3edge maps with is ``T_world_optical = T_world_base @ T_base_optical``: the
robot's pose of its base frame composed with the base -> camera-optical extrinsic
(:func:`camera_pose`). ROS camera optical frames (x right, y down, z forward) are h3edge's camera
frame, so no axis change is applied beyond the extrinsic.

Key expressions: zenoh-bridge-ros2dds publishes topic ``/ns/topic`` on key ``ns/topic`` (plus the
bridge's optional namespace prefix); rmw_zenoh on ``<domain>/<ns/topic>/<pkg>::msg::dds_::<Type>_/<type hash>``
(:func:`topic_key`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from h3edge.errors import InputError
from h3edge.geometry.camera import Intrinsics, rigid_error
from h3edge.geometry.poses import pose_from_tq, quat_from_matrix

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TF = "tf2_msgs/msg/TFMessage"
POSE_TYPES = {"odometry": ODOMETRY, "pose": POSE_STAMPED, "tf": TF}
KEY_STYLES = ("bridge", "rmw_zenoh")
MAX_MESSAGE_BYTES = 64 << 20  # a larger payload is refused before deserialising

_COLOR = {"rgb8": (3, [0, 1, 2]), "bgr8": (3, [2, 1, 0]), "rgba8": (4, [0, 1, 2]), "bgra8": (4, [2, 1, 0]),
          "mono8": (1, [0, 0, 0])}
_DEPTH = {"16UC1": np.dtype("<u2"), "mono16": np.dtype("<u2"), "32FC1": np.dtype("<f4")}


class RosMessageError(InputError):
    """A ROS message that cannot be used; the message says why."""


@dataclass(frozen=True)
class RosPose:
    stamp_ns: int
    parent: str  # frame the pose is expressed in (odom / map)
    child: str  # frame it places (base_link, or the camera's frame)
    matrix: np.ndarray  # (4, 4) parent <- child


@functools.lru_cache(maxsize=1)
def typestore():
    """The ROS 2 Humble message definitions (the types above are the same in Jazzy)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def deserialize(data: bytes, msgtype: str):
    """A message object from CDR bytes (with the 4-byte encapsulation header)."""
    if len(data) > MAX_MESSAGE_BYTES:
        raise RosMessageError(f"{msgtype}: {len(data)} bytes exceeds the {MAX_MESSAGE_BYTES >> 20} MB limit")
    try:
        return typestore().deserialize_cdr(bytes(data), msgtype)
    except Exception as e:  # noqa: BLE001 - rosbags raises assorted errors on bad bytes
        raise RosMessageError(f"{msgtype}: not a valid CDR message ({type(e).__name__}: {e})") from None


def serialize(msg) -> bytes:
    return bytes(typestore().serialize_cdr(msg, msg.__msgtype__))


def stamp_ns(header) -> int:
    s, ns = int(header.stamp.sec), int(header.stamp.nanosec)
    if s < 0 or not 0 <= ns < 1_000_000_000:
        raise RosMessageError(f"bad header stamp {s} s {ns} ns")
    return s * 1_000_000_000 + ns


def _header(stamp: int, frame_id: str):
    t = typestore().types
    return t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](stamp // 1_000_000_000, stamp % 1_000_000_000),
                                    frame_id)


# ------------------------------------------------------------------------- images
def _pixels(msg, bytes_per_pixel: int, dtype: np.dtype) -> np.ndarray:
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise RosMessageError(f"image {w}x{h}: empty")
    if step < w * bytes_per_pixel:
        raise RosMessageError(f"image step {step} < width {w} x {bytes_per_pixel} bytes")
    data = np.asarray(msg.data, np.uint8)
    if len(data) != step * h:
        raise RosMessageError(f"image data is {len(data)} bytes, step x height = {step * h}")
    rows = data.reshape(h, step)[:, : w * bytes_per_pixel]
    dt = dtype.newbyteorder(">") if msg.is_bigendian and dtype.itemsize > 1 else dtype
    return np.ascontiguousarray(rows).view(dt).reshape(h, w, -1)


def image_color(msg) -> np.ndarray:
    """RGB uint8 (H, W, 3) of a colour ``sensor_msgs/Image``."""
    enc = str(msg.encoding).lower()
    if enc not in _COLOR:
        raise RosMessageError(f"colour encoding {msg.encoding!r} is not one of {sorted(_COLOR)}")
    channels, order = _COLOR[enc]
    px = _pixels(msg, channels, np.dtype(np.uint8))
    return np.ascontiguousarray(px[..., order])


def image_depth(msg, depth_scale: float = 1000.0) -> np.ndarray:
    """Depth float32 metres (H, W) of a ``16UC1`` (units of 1 / ``depth_scale`` m) or ``32FC1``
    (metres) ``sensor_msgs/Image``; invalid pixels (0, NaN, inf) become 0."""
    enc = str(msg.encoding).upper() if str(msg.encoding).lower() != "mono16" else "mono16"
    if enc not in _DEPTH:
        raise RosMessageError(f"depth encoding {msg.encoding!r} is not 16UC1 (mm) or 32FC1 (m)")
    dt = _DEPTH[enc]
    px = _pixels(msg, dt.itemsize, dt)[..., 0]
    depth = px.astype(np.float32) / np.float32(depth_scale) if dt.kind == "u" else px.astype(np.float32)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


def color_message(rgb: np.ndarray, stamp: int, frame_id: str, encoding: str = "rgb8"):
    """A ``sensor_msgs/Image`` of RGB uint8 (H, W, 3) in ``encoding`` (the inverse of :func:`image_color`)."""
    channels, order = _COLOR[encoding]
    if channels == 1:
        px = np.round(rgb.mean(-1, keepdims=True))
    else:
        px = rgb[..., [order.index(j) for j in range(3)]]  # message channel j holds RGB channel order.index(j)
        if channels == 4:
            px = np.concatenate([px, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], -1)
    px = np.ascontiguousarray(px, np.uint8)
    h, w = rgb.shape[:2]
    return typestore().types[IMAGE](_header(stamp, frame_id), h, w, encoding, 0, w * channels, px.reshape(-1))


def depth_message(depth_m: np.ndarray, stamp: int, frame_id: str, encoding: str = "16UC1",
                  depth_scale: float = 1000.0):
    """A ``sensor_msgs/Image`` of depth in metres as ``16UC1`` or ``mono16`` (units of 1 / ``depth_scale``
    m) or ``32FC1``."""
    h, w = depth_m.shape
    if encoding in ("16UC1", "mono16"):
        px = np.clip(np.round(np.nan_to_num(depth_m) * depth_scale), 0, 65535).astype("<u2")
    else:
        px = depth_m.astype("<f4")
    return typestore().types[IMAGE](_header(stamp, frame_id), h, w, encoding, 0, w * px.itemsize,
                                    px.reshape(-1).view(np.uint8))


# ------------------------------------------------------------------ camera info
def camera_intrinsics(msg) -> Intrinsics:
    """Pinhole intrinsics of a ``sensor_msgs/CameraInfo`` (its ``k``; ROS 1's, as a ROS 1 bag or
    one converted from it keeps it, ``K`` and ``D``)."""
    k = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), np.float64)
    if k.shape != (9,) or not np.isfinite(k).all():
        raise RosMessageError("camera info: k is not 9 finite numbers")
    d = np.asarray(getattr(msg, "d", getattr(msg, "D", ())), np.float64)
    if len(d) and (not np.isfinite(d).all() or np.abs(d).max() > 1e-9):
        raise RosMessageError(f"camera info: {msg.distortion_model or 'distortion'} coefficients are not zero; "
                              "subscribe to the rectified image (image_rect) and its camera info")
    fx, fy, cx, cy = k[0], k[4], k[2], k[5]
    w, h = int(msg.width), int(msg.height)
    if w <= 0 or h <= 0 or fx <= 0 or fy <= 0:
        raise RosMessageError(f"camera info: size {w}x{h}, fx {fx}, fy {fy}")
    try:
        return Intrinsics(w, h, float(fx), float(fy), float(cx), float(cy))
    except ValueError as e:  # not a pinhole camera (fx = 1e-6, cx = 1e300): a counted drop, not a crash
        raise RosMessageError(f"camera info: {e}") from None


def camera_info_message(intr: Intrinsics, stamp: int, frame_id: str):
    t = typestore().types
    k = np.array([intr.fx, 0, intr.cx, 0, intr.fy, intr.cy, 0, 0, 1], np.float64)
    p = np.array([intr.fx, 0, intr.cx, 0, 0, intr.fy, intr.cy, 0, 0, 0, 1, 0], np.float64)
    roi = t["sensor_msgs/msg/RegionOfInterest"](0, 0, 0, 0, False)
    return t[CAMERA_INFO](_header(stamp, frame_id), intr.height, intr.width, "plumb_bob", np.zeros(5), k,
                          np.eye(3).reshape(-1), p, 0, 0, roi)


# ------------------------------------------------------------------------ poses
def _matrix(position, orientation) -> np.ndarray:
    t = np.array([position.x, position.y, position.z], np.float64)
    q = np.array([orientation.x, orientation.y, orientation.z, orientation.w], np.float64)
    if not (np.isfinite(t).all() and np.isfinite(q).all()):
        raise RosMessageError("pose is not finite")
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > 1e-3:
        raise RosMessageError(f"orientation quaternion has norm {n:.6f}, not 1")
    m = pose_from_tq(t, q / n)
    err = rigid_error(m)
    if err:
        raise RosMessageError(f"pose: {err}")
    return m


def poses_from_message(msg, msgtype: str, base_frame: str | None = None) -> list[RosPose]:
    """The poses a pose message carries (one, or every transform of a TF message). With
    ``base_frame``, a TF message's transforms of other children are left out before they are read:
    other links of the tree, a NaN or a long list among them, never cost the robot's pose."""
    if msgtype == ODOMETRY:
        return [RosPose(stamp_ns(msg.header), msg.header.frame_id, msg.child_frame_id,
                        _matrix(msg.pose.pose.position, msg.pose.pose.orientation))]
    if msgtype == POSE_STAMPED:
        return [RosPose(stamp_ns(msg.header), msg.header.frame_id, "", _matrix(msg.pose.position,
                                                                                msg.pose.orientation))]
    if msgtype == TF:
        return [RosPose(stamp_ns(tf.header), tf.header.frame_id, tf.child_frame_id,
                        _matrix(tf.transform.translation, tf.transform.rotation)) for tf in msg.transforms
                if base_frame is None or tf.child_frame_id == base_frame]
    raise RosMessageError(f"{msgtype} is not a pose type ({', '.join(POSE_TYPES.values())})")


def chained_transform(transforms: list[RosPose], target: str, source: str) -> np.ndarray | None:
    """``target <- source`` (4x4) through a tree of static transforms (each ``parent <- child``, as
    ``/tf_static`` carries them): both frames walked up to their root, None where they share none
    (or a frame id is empty). The last transform given for a child wins."""
    if not target or not source:
        return None
    parent = {t.child: t for t in transforms}

    def to_root(frame: str) -> tuple[str, np.ndarray]:
        m, seen = np.eye(4), {frame}
        while frame in parent:
            t = parent[frame]
            m, frame = t.matrix @ m, t.parent
            if frame in seen:  # a loop: no tree
                break
            seen.add(frame)
        return frame, m

    root_t, m_t = to_root(target)
    root_s, m_s = to_root(source)
    return np.linalg.inv(m_t) @ m_s if root_t == root_s else None


def _pose_parts(matrix: np.ndarray):
    t = typestore().types
    q = quat_from_matrix(matrix[:3, :3])  # x, y, z, w
    return (t["geometry_msgs/msg/Point"](*map(float, matrix[:3, 3])),
            t["geometry_msgs/msg/Quaternion"](*map(float, q)))


def odometry_message(matrix: np.ndarray, stamp: int, parent: str, child: str):
    t = typestore().types
    pos, q = _pose_parts(matrix)
    pose = t["geometry_msgs/msg/PoseWithCovariance"](t["geometry_msgs/msg/Pose"](pos, q), np.zeros(36))
    twist = t["geometry_msgs/msg/TwistWithCovariance"](
        t["geometry_msgs/msg/Twist"](t["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
                                     t["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0)), np.zeros(36))
    return t[ODOMETRY](_header(stamp, parent), child, pose, twist)


def pose_stamped_message(matrix: np.ndarray, stamp: int, parent: str):
    t = typestore().types
    pos, q = _pose_parts(matrix)
    return t[POSE_STAMPED](_header(stamp, parent), t["geometry_msgs/msg/Pose"](pos, q))


def tf_message(transforms: list[tuple[np.ndarray, int, str, str]]):
    """A TF message of (matrix, stamp, parent, child) transforms."""
    t = typestore().types
    out = []
    for matrix, stamp, parent, child in transforms:
        pos, q = _pose_parts(matrix)
        tr = t["geometry_msgs/msg/Transform"](t["geometry_msgs/msg/Vector3"](pos.x, pos.y, pos.z), q)
        out.append(t["geometry_msgs/msg/TransformStamped"](_header(stamp, parent), child, tr))
    return t[TF](out)


def pose_mismatch(pose: RosPose, msgtype: str, world_frame: str, base_frame: str) -> str | None:
    """Why ``pose`` is not the robot's base pose in the world frame (None when it is); a TF message's
    other transforms answer ``"other"`` (not an error: they are other links of the tree)."""
    wrong_parent = bool(world_frame) and pose.parent != world_frame
    wrong_child = msgtype != POSE_STAMPED and pose.child != base_frame
    if not (wrong_parent or wrong_child):
        return None
    if msgtype == TF:
        return "other"
    where = world_frame or "any frame"
    return f"pose of {pose.child or '?'!r} in {pose.parent!r}, expected {base_frame!r} in {where!r}"


def camera_pose(base_pose: np.ndarray, base_to_camera: np.ndarray) -> np.ndarray:
    """``T_world_optical``: the base's pose composed with the base -> camera-optical extrinsic."""
    return np.asarray(base_pose, np.float64) @ np.asarray(base_to_camera, np.float64)


@dataclass(frozen=True)
class RosConfig:
    """ROS 2 input (profile table ``[ros]``; ``h3edge serve --ros`` turns it on)."""

    key_style: str = "bridge"
    """bridge (zenoh-bridge-ros2dds) | rmw_zenoh"""
    key_prefix: str = ""
    """bridge: the bridge's namespace prefix on the zenoh side, if any"""
    domain: int = 0
    """rmw_zenoh: ROS_DOMAIN_ID"""
    color_topic: str = "/camera/color/image_raw"
    """sensor_msgs/Image colour topic (rgb8 / bgr8 / rgba8 / bgra8 / mono8)"""
    depth_topic: str = "/camera/aligned_depth_to_color/image_raw"
    """depth registered to the colour camera"""
    camera_info_topic: str = "/camera/color/camera_info"
    """sensor_msgs/CameraInfo of the colour camera (the intrinsics)"""
    depth_camera_info_topic: str = "/camera/aligned_depth_to_color/camera_info"
    """sensor_msgs/CameraInfo of the depth images: when it differs from the colour camera's, depth is not registered to
    colour: registered into the colour camera with ``depth_to_color``, else its frames are refused, never mapped
    misaligned ("": no check)"""
    depth_to_color: str = ""
    """the depth camera's optical frame in the colour camera's optical frame, "x y z qx qy qz qw" (metres; the driver's
    depth -> colour extrinsics, the tf colour_optical -> depth_optical) or "identity": depth whose camera info differs
    from the colour camera's is registered into the colour camera (:mod:`h3edge.geometry.registration`); "": such
    depth is refused"""
    pose_topic: str = "/odom"
    """the robot's pose topic (see pose_type)"""
    pose_type: str = "odometry"
    """odometry | pose (PoseStamped) | tf (TFMessage)"""
    world_frame: str = ""
    """poses must be expressed in this frame ("": any)"""
    base_frame: str = "base_link"
    """the frame the poses place (Odometry child frame; TF child)"""
    camera_frame: str = ""
    """images must carry this frame id ("": any); depth that ``depth_to_color`` registers carries its own camera's"""
    base_to_camera: str = ""
    """base -> camera optical frame as "x y z qx qy qz qw" (metres, quaternion: the order of
    static_transform_publisher), or "identity" when the poses already are the camera's"""
    depth_scale: float = 1000.0
    """16UC1 depth units per metre (mm)"""
    pair_tolerance_s: float = 0.02
    """colour and depth stamps closer than this are one frame"""
    pair_buffer: int = 8
    """images of each kind kept waiting for their pair"""

    def __post_init__(self):
        if self.key_style not in KEY_STYLES:
            raise ValueError(f"key_style {self.key_style!r} is not one of {KEY_STYLES}")
        if self.pose_type not in POSE_TYPES:
            raise ValueError(f"pose_type {self.pose_type!r} is not one of {sorted(POSE_TYPES)}")
        if self.base_to_camera:
            extrinsic_matrix(self.base_to_camera)
        if self.depth_to_color:
            extrinsic_matrix(self.depth_to_color, "depth_to_color")

    def keys(self) -> dict[str, str]:
        """Zenoh key expression of each input (role -> key)."""
        topics = {"color": (self.color_topic, IMAGE), "depth": (self.depth_topic, IMAGE),
                  "camera_info": (self.camera_info_topic, CAMERA_INFO),
                  "pose": (self.pose_topic, POSE_TYPES[self.pose_type])}
        if self.depth_camera_info_topic:
            topics["depth_camera_info"] = (self.depth_camera_info_topic, CAMERA_INFO)
        return {role: topic_key(t, mt, self.key_style, self.key_prefix, self.domain)
                for role, (t, mt) in topics.items()}


def registration_mismatch(color: Intrinsics, depth: Intrinsics) -> str | None:
    """Why depth images with camera info ``depth`` are not registered to the colour camera
    ``color`` (another size, focal length or principal point), or None when they are."""
    if (depth.width, depth.height) != (color.width, color.height) or \
            not np.allclose([depth.fx, depth.fy], [color.fx, color.fy], rtol=0.01) or \
            not np.allclose([depth.cx, depth.cy], [color.cx, color.cy], atol=1.0):
        return (f"depth is not registered to colour: depth camera {depth.width}x{depth.height} fx {depth.fx:.1f} "
                f"cx {depth.cx:.1f}, colour camera {color.width}x{color.height} fx {color.fx:.1f} cx {color.cx:.1f}; "
                "give the depth -> colour extrinsics (depth_to_color, --depth-to-color) to register it, use depth "
                "aligned to colour (e.g. the driver's aligned_depth_to_color), or set depth_camera_info_topic to "
                "\"\" if it is registered")
    return None


def extrinsic_matrix(spec: str, name: str = "base_to_camera") -> np.ndarray:
    """4x4 rigid transform (the base -> camera-optical extrinsic, or the one setting ``name`` says)
    from ``"x y z qx qy qz qw"`` or ``"identity"``."""
    if spec.strip() == "identity":
        return np.eye(4)
    try:
        v = [float(x) for x in spec.replace(",", " ").split()]
    except ValueError:
        v = []
    if len(v) != 7 or not np.isfinite(v).all():
        raise ValueError(f"{name} {spec!r}: give 'x y z qx qy qz qw' (7 numbers) or 'identity'")
    try:
        m = pose_from_tq(np.array(v[:3]), np.array(v[3:]))
    except ValueError as e:
        raise ValueError(f"{name}: {e}") from None
    err = rigid_error(m)
    if err:
        raise ValueError(f"{name}: {err}")
    return m


# ------------------------------------------------------------------ key expressions
def dds_type_name(msgtype: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (the DDS / rmw_zenoh type name)."""
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def topic_key(topic: str, msgtype: str, style: str = "bridge", prefix: str = "", domain: int = 0) -> str:
    """The zenoh key expression a ROS 2 topic arrives on.

    ``bridge`` (zenoh-bridge-ros2dds): ``[prefix/]ns/topic``; ``rmw_zenoh``:
    ``<domain>/ns/topic/<dds type>/*`` (any type hash)."""
    name = topic.strip("/")
    if not name or any(c in name for c in "*$?#") or "//" in name:
        raise ValueError(f"ROS topic {topic!r} is not a plain topic name")
    if style == "bridge":
        return f"{prefix.strip('/')}/{name}" if prefix.strip("/") else name
    if style == "rmw_zenoh":
        return f"{int(domain)}/{name}/{dds_type_name(msgtype)}/*"
    raise ValueError(f"key style {style!r} is not one of {KEY_STYLES}")
