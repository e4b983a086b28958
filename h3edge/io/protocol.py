"""The wire protocol between robots, the service and clients (docs/protocol.md is its spec).

Two message kinds travel on zenoh keys under ``h3edge/<map-id>/``:

* a **frame message** (key ``frame``; also the reply of a ``render`` query): the 4-byte magic
  ``H3FR``, a little-endian uint32 header length, a UTF-8 JSON header, then the colour bytes and
  the depth bytes (sizes in the header). Colour is JPEG, PNG or raw RGB8; depth is a 16-bit PNG,
  raw little-endian uint16 (metres = value / ``depth_scale``) or raw float32 metres. The header may
  carry the camera pose, so a robot with a synchronised pose need not publish poses separately.
* a **pose message** (key ``pose``): JSON with a timestamp and either a translation + quaternion
  (x, y, z, w) or a row-major 4x4 matrix; camera-to-world, OpenCV camera axes.

Decoding is strict: an unknown field, a wrong size, a non-finite number or a non-rigid pose is a
:class:`ProtocolError` whose message says what is wrong. Versions are explicit (``"v": 1``).
"""

from __future__ import annotations

import json
import math
import re
import struct
from dataclasses import dataclass

import cv2
import numpy as np

from h3edge.errors import InputError
from h3edge.geometry.camera import Intrinsics, rigid_error
from h3edge.geometry.poses import pose_from_tq

VERSION = 1
FRAME_MAGIC = b"H3FR"
MAX_HEADER = 64 * 1024
MAX_PIXELS = 4096 * 4096
MAX_SIDE = 16384  # px, width or height of a frame (what a client's decoder and PNG can take)
COLOR_ENCODINGS = ("jpeg", "png", "raw_rgb8")
DEPTH_ENCODINGS = ("png16", "raw_u16", "raw_f32")
_FRAME_KEYS = {"v", "timestamp_ns", "frame_id", "width", "height", "intrinsics", "depth_scale", "color", "depth",
               "pose", "frame_name"}
_POSE_KEYS = {"v", "timestamp_ns", "frame_name", "t", "q", "matrix"}


MAX_TIMESTAMP_NS = (1 << 63) - 1  # stamps are int64 nanoseconds
_MAP_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def check_map_id(map_id: str) -> str:
    """``map_id`` when it is safe as one zenoh key chunk and one file name (1-64 of letters, digits,
    ``_ . -``, starting with a letter or digit: no wildcards, no ``/``, no ``..``); InputError if not."""
    if not isinstance(map_id, str) or not _MAP_ID.fullmatch(map_id):
        raise InputError(f"map id {map_id!r} must be 1-64 letters, digits, '_', '.' or '-', starting with a "
                         "letter or digit")
    return map_id


class ProtocolError(ValueError):
    """A message that does not follow the protocol; the text says which part and why."""


class FrameTooLarge(ProtocolError):
    """A well-formed frame over the receiver's pixel limit (refused before any image is decoded)."""


@dataclass
class FrameMessage:
    timestamp_ns: int
    frame_id: int
    color: np.ndarray  # uint8 (H, W, 3) RGB
    depth: np.ndarray  # float32 (H, W) metres, 0 = invalid
    intrinsics: Intrinsics
    pose: np.ndarray | None = None  # camera-to-world 4x4 when the frame carries one
    frame_name: str = ""

    @property
    def timestamp(self) -> float:
        return self.timestamp_ns * 1e-9


@dataclass
class PoseMessage:
    timestamp_ns: int
    pose: np.ndarray  # camera-to-world 4x4
    frame_name: str = ""


# ------------------------------------------------------------------------------------ helpers
def _check_keys(d: dict, allowed: set, what: str) -> None:
    if not isinstance(d, dict):
        raise ProtocolError(f"{what} must be a JSON object")
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise ProtocolError(f"{what}: unknown field(s) {', '.join(unknown)}")


def _int(d: dict, key: str, what: str, lo: int | None = None, hi: int | None = None) -> int:
    if key not in d:
        raise ProtocolError(f"{what}: missing field {key!r}")
    v = d[key]
    if not isinstance(v, int) or isinstance(v, bool):
        raise ProtocolError(f"{what}: {key!r} must be an integer, got {v!r}")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ProtocolError(f"{what}: {key!r} = {v} outside [{lo}, {hi}]")
    return v


def _float(d: dict, key: str, what: str) -> float:
    if key not in d:
        raise ProtocolError(f"{what}: missing field {key!r}")
    v = d[key]
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
        raise ProtocolError(f"{what}: {key!r} must be a finite number, got {v!r}")
    return float(v)


def _numbers(v, n: int, what: str) -> np.ndarray:
    if not isinstance(v, list) or len(v) != n or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                         for x in v):
        raise ProtocolError(f"{what} must be a list of {n} numbers")
    a = np.asarray(v, np.float64)
    if not np.all(np.isfinite(a)):
        raise ProtocolError(f"{what} has non-finite values")
    return a


def _check_version(d: dict, what: str) -> None:
    v = d.get("v")
    if v != VERSION:
        raise ProtocolError(f"{what}: unsupported version {v!r} (this service speaks v{VERSION})")


def pose_to_json(pose: np.ndarray) -> dict:
    """A pose as the protocol's {"t": [...], "q": [x, y, z, w]}."""
    from scipy.spatial.transform import Rotation

    return {"t": [float(x) for x in pose[:3, 3]], "q": [float(x) for x in Rotation.from_matrix(pose[:3, :3]).as_quat()]}


def pose_from_json(d: dict, what: str) -> np.ndarray:
    """{"t", "q"} or {"matrix"} (row-major 16) -> a validated rigid 4x4."""
    if "matrix" in d:
        if "t" in d or "q" in d:
            raise ProtocolError(f"{what}: give either matrix or t + q, not both")
        T = _numbers(d["matrix"], 16, f"{what}.matrix").reshape(4, 4)
    else:
        if "t" not in d or "q" not in d:
            raise ProtocolError(f"{what}: needs t and q (x, y, z, w) or matrix")
        t = _numbers(d["t"], 3, f"{what}.t")
        q = _numbers(d["q"], 4, f"{what}.q")
        n = float(np.linalg.norm(q))
        if abs(n - 1.0) > 1e-3:
            raise ProtocolError(f"{what}.q is not a unit quaternion (norm {n:.6f})")
        T = pose_from_tq(t, q)
    why = rigid_error(T)
    if why:
        raise ProtocolError(f"{what}: not a rigid transform: {why}")
    return T


# -------------------------------------------------------------------------------------- poses
def encode_pose(msg: PoseMessage) -> bytes:
    d = {"v": VERSION, "timestamp_ns": int(msg.timestamp_ns), **pose_to_json(np.asarray(msg.pose, np.float64))}
    if msg.frame_name:
        d["frame_name"] = msg.frame_name
    return json.dumps(d).encode()


def decode_pose(data: bytes) -> PoseMessage:
    try:
        d = json.loads(bytes(data).decode("utf-8"))
    except (ValueError, RecursionError) as e:  # bad UTF-8 or JSON, 4300+ digit integers, deep nesting
        raise ProtocolError(f"pose message is not JSON: {e}") from None
    _check_keys(d, _POSE_KEYS, "pose message")
    _check_version(d, "pose message")
    ts = _int(d, "timestamp_ns", "pose message", 0, MAX_TIMESTAMP_NS)
    name = d.get("frame_name", "")
    if not isinstance(name, str):
        raise ProtocolError("pose message: frame_name must be a string")
    return PoseMessage(ts, pose_from_json(d, "pose message"), name)


# ------------------------------------------------------------------------------------- frames
def encode_frame(msg: FrameMessage, color_encoding: str = "jpeg", depth_encoding: str = "png16",
                 depth_scale: float = 1000.0, jpeg_quality: int = 95) -> bytes:
    """A frame message; depth is quantised to 1/``depth_scale`` m for the 16-bit encodings."""
    h, w = msg.depth.shape
    if msg.color.shape != (h, w, 3) or msg.color.dtype != np.uint8:
        raise ValueError(f"colour must be uint8 ({h}, {w}, 3)")
    if color_encoding == "jpeg":
        ok, buf = cv2.imencode(".jpg", msg.color[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        cbytes = buf.tobytes()
    elif color_encoding == "png":
        ok, buf = cv2.imencode(".png", msg.color[..., ::-1])
        cbytes = buf.tobytes()
    elif color_encoding == "raw_rgb8":
        ok, cbytes = True, np.ascontiguousarray(msg.color).tobytes()
    else:
        raise ValueError(f"colour encoding must be one of {COLOR_ENCODINGS}")
    if not ok:
        raise ValueError("colour encoding failed")
    d = np.where(np.isfinite(msg.depth) & (msg.depth > 0), msg.depth, 0).astype(np.float64)
    if depth_encoding in ("png16", "raw_u16"):
        q = np.rint(d * depth_scale)
        q = np.where(q > 65535, 0, q).astype("<u2")
        if depth_encoding == "png16":
            ok, buf = cv2.imencode(".png", q)
            dbytes = buf.tobytes()
        else:
            dbytes = q.tobytes()
    elif depth_encoding == "raw_f32":
        dbytes, depth_scale = d.astype("<f4").tobytes(), 1.0
    else:
        raise ValueError(f"depth encoding must be one of {DEPTH_ENCODINGS}")
    i = msg.intrinsics
    header = {"v": VERSION, "timestamp_ns": int(msg.timestamp_ns), "frame_id": int(msg.frame_id), "width": w,
              "height": h, "intrinsics": {"fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy},
              "depth_scale": float(depth_scale), "color": {"encoding": color_encoding, "size": len(cbytes)},
              "depth": {"encoding": depth_encoding, "size": len(dbytes)}}
    if msg.pose is not None:
        header["pose"] = pose_to_json(np.asarray(msg.pose, np.float64))
    if msg.frame_name:
        header["frame_name"] = msg.frame_name
    hb = json.dumps(header).encode()
    return FRAME_MAGIC + struct.pack("<I", len(hb)) + hb + cbytes + dbytes


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def encoded_image_size(data: bytes) -> tuple[int, int, str]:
    """(width, height, "png" | "jpeg") read from a PNG's IHDR or a JPEG's SOF header bytes, without
    decoding: what an image claims to be before anything is allocated for it (ProtocolError when the
    header cannot be read)."""
    if data[:8] == _PNG_SIGNATURE:
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise ProtocolError("PNG without an IHDR header")
        w, h = struct.unpack_from(">II", data, 16)
        return int(w), int(h), "png"
    if data[:2] == b"\xff\xd8":
        i = 2
        while i + 4 <= len(data):
            if data[i] != 0xFF:
                raise ProtocolError("JPEG segment does not start with 0xff")
            marker = data[i + 1]
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            if marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:  # parameterless
                i += 2
                continue
            (length,) = struct.unpack_from(">H", data, i + 2)
            if marker in _JPEG_SOF:
                if i + 9 > len(data):
                    break
                h, w = struct.unpack_from(">HH", data, i + 5)
                return int(w), int(h), "jpeg"
            if marker in (0xD9, 0xDA) or length < 2:  # end of image / start of scan before any frame header
                break
            i += 2 + length
        raise ProtocolError("JPEG without a frame (SOF) header")
    raise ProtocolError("image is neither PNG nor JPEG")


def _check_declared_size(data: bytes, w: int, h: int, what: str) -> None:
    """Refuse an image whose header disagrees with the frame's declared size, before decoding it
    (a small file can declare gigapixels: a decompression bomb)."""
    iw, ih, kind = encoded_image_size(data)
    if (iw, ih) != (w, h):
        raise ProtocolError(f"{what} {kind} header says {iw}x{ih}, frame header says {w}x{h}")


def _decode_color(enc: str, data: bytes, w: int, h: int) -> np.ndarray:
    if enc == "raw_rgb8":
        if len(data) != w * h * 3:
            raise ProtocolError(f"raw colour is {len(data)} bytes, {w}x{h}x3 needs {w * h * 3}")
        return np.frombuffer(data, np.uint8).reshape(h, w, 3).copy()
    _check_declared_size(data, w, h, "colour")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise ProtocolError(f"colour ({enc}) cannot be decoded")
    if img.shape[:2] != (h, w):
        raise ProtocolError(f"colour is {img.shape[1]}x{img.shape[0]}, header says {w}x{h}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _decode_depth(enc: str, data: bytes, w: int, h: int, scale: float) -> np.ndarray:
    if enc == "raw_f32":
        if len(data) != w * h * 4:
            raise ProtocolError(f"raw float depth is {len(data)} bytes, {w}x{h}x4 needs {w * h * 4}")
        d = np.frombuffer(data, "<f4").reshape(h, w).astype(np.float32)
        return np.where(np.isfinite(d) & (d > 0), d, np.float32(0))
    if enc == "raw_u16":
        if len(data) != w * h * 2:
            raise ProtocolError(f"raw 16-bit depth is {len(data)} bytes, {w}x{h}x2 needs {w * h * 2}")
        raw = np.frombuffer(data, "<u2").reshape(h, w)
    else:
        _check_declared_size(data, w, h, "depth")
        raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise ProtocolError("depth (png16) cannot be decoded")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise ProtocolError(f"depth PNG must be single-channel 16-bit, got {raw.dtype} {raw.shape}")
        if raw.shape != (h, w):
            raise ProtocolError(f"depth is {raw.shape[1]}x{raw.shape[0]}, header says {w}x{h}")
    return raw.astype(np.float32) / np.float32(scale)


def decode_frame(data: bytes, max_pixels: int = MAX_PIXELS) -> FrameMessage:
    """Parse and decode one frame message. Sizes are checked before any image is decoded: the
    header's width x height against ``max_pixels`` (:class:`FrameTooLarge`), and each encoded
    image's own dimensions (PNG IHDR / JPEG SOF) against the header's."""
    data = bytes(data)
    if len(data) < 8 or data[:4] != FRAME_MAGIC:
        raise ProtocolError("frame message does not start with the H3FR magic")
    (n,) = struct.unpack_from("<I", data, 4)
    if n > MAX_HEADER or 8 + n > len(data):
        raise ProtocolError(f"frame header length {n} does not fit the {len(data)}-byte message")
    try:
        d = json.loads(data[8:8 + n].decode("utf-8"))
    except (ValueError, RecursionError) as e:  # bad UTF-8 or JSON, 4300+ digit integers, deep nesting
        raise ProtocolError(f"frame header is not JSON: {e}") from None
    what = "frame message"
    _check_keys(d, _FRAME_KEYS, what)
    _check_version(d, what)
    ts = _int(d, "timestamp_ns", what, 0, MAX_TIMESTAMP_NS)
    fid = _int(d, "frame_id", what, 0)
    w, h = _int(d, "width", what, 1, MAX_SIDE), _int(d, "height", what, 1, MAX_SIDE)
    if w * h > min(max_pixels, MAX_PIXELS):
        raise FrameTooLarge(f"{what}: {w}x{h} exceeds the {min(max_pixels, MAX_PIXELS)}-pixel limit")
    intr_d = d.get("intrinsics")
    _check_keys(intr_d, {"fx", "fy", "cx", "cy"}, f"{what}.intrinsics")
    try:
        intr = Intrinsics(w, h, *(_float(intr_d, k, f"{what}.intrinsics") for k in ("fx", "fy", "cx", "cy")))
    except ValueError as e:
        raise ProtocolError(f"{what}: {e}") from None
    scale = _float(d, "depth_scale", what)
    if scale <= 0:
        raise ProtocolError(f"{what}: depth_scale must be positive")
    parts = []
    for key, encodings in (("color", COLOR_ENCODINGS), ("depth", DEPTH_ENCODINGS)):
        p = d.get(key)
        _check_keys(p, {"encoding", "size"}, f"{what}.{key}")
        if p.get("encoding") not in encodings:
            raise ProtocolError(f"{what}.{key}.encoding must be one of {', '.join(encodings)}")
        parts.append((p["encoding"], _int(p, "size", f"{what}.{key}", 0)))
    (cenc, csize), (denc, dsize) = parts
    body = 8 + n
    if body + csize + dsize != len(data):
        raise ProtocolError(f"{what}: header + colour ({csize}) + depth ({dsize}) bytes = {body + csize + dsize}, "
                            f"message has {len(data)} (truncated or padded)")
    color = _decode_color(cenc, data[body:body + csize], w, h)
    depth = _decode_depth(denc, data[body + csize:], w, h, scale)
    pose = None
    if "pose" in d:
        _check_keys(d["pose"], {"t", "q", "matrix"}, f"{what}.pose")
        pose = pose_from_json(d["pose"], f"{what}.pose")
    name = d.get("frame_name", "")
    if not isinstance(name, str):
        raise ProtocolError(f"{what}: frame_name must be a string")
    return FrameMessage(ts, fid, color, depth, intr, pose, name)


@dataclass(frozen=True)
class Keys:
    """The zenoh keys of one map (docs/protocol.md): ``<base>`` = ``h3edge/<map-id>``."""

    base: str

    @classmethod
    def for_map(cls, map_id: str) -> Keys:
        return cls(f"h3edge/{check_map_id(map_id)}")

    frame = property(lambda self: f"{self.base}/frame")
    pose = property(lambda self: f"{self.base}/pose")
    status = property(lambda self: f"{self.base}/status")
    profile = property(lambda self: f"{self.base}/profile")
    mesh = property(lambda self: f"{self.base}/mesh")
    render = property(lambda self: f"{self.base}/render")
    save = property(lambda self: f"{self.base}/save")
    load = property(lambda self: f"{self.base}/load")
    export = property(lambda self: f"{self.base}/export")
    sdf = property(lambda self: f"{self.base}/sdf")
    slice = property(lambda self: f"{self.base}/slice")
    checkpoint = property(lambda self: f"{self.base}/checkpoint")
    """the map's checkpoints kept by the fleet: ``<checkpoint>/chunk/<k>`` and ``<checkpoint>/manifest``"""
    checkpoint_manifest = property(lambda self: f"{self.base}/checkpoint/manifest")

    def checkpoint_chunk(self, k: int) -> str:
        return f"{self.base}/checkpoint/chunk/{int(k)}"
