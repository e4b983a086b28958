"""Zenoh transport: session set-up, the key layout, the server around a :class:`MapService`, the
query client and the publisher used by ``h3edge sim publish``.

Keys (``<base>`` = ``h3edge/<map-id>``): ``<base>/frame`` and ``<base>/pose`` (put), queryables
``<base>/status``, ``/profile``, ``/mesh``, ``/render``, ``/sdf``, ``/slice`` and the operator's
``/save``, ``/load``, ``/export`` (docs/protocol.md).

Zenoh callbacks only hand bytes over (frames to the service's bounded queue, poses to its pose
buffer) or queue the query object; worker threads answer queries (status and profile on one, the
heavy mesh / render / save on another), always inside ``with query:`` so the querier gets its
final reply whatever happens, and errors go back as ``reply_err`` with the message.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zenoh

from h3edge.errors import QueryError
from h3edge.io.protocol import check_map_id
from h3edge.serving.queries import MESH_FORMATS, MeshRequest, NamedRequest, RenderRequest, SdfRequest, SliceRequest

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Keys:
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


def zenoh_config(path: str | None = None, mode: str | None = None, connect: list[str] | None = None,
                 listen: list[str] | None = None, multicast: bool | None = None) -> zenoh.Config:
    """A zenoh config from a JSON5 file (or zenoh's defaults), with command-line overrides."""
    conf = zenoh.Config.from_file(path) if path else zenoh.Config()
    if mode:
        conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if multicast is not None:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast)))
    return conf


def open_session(conf: zenoh.Config) -> zenoh.Session:
    """Open a zenoh session; ConnectionError (one line) when zenoh cannot (e.g. client mode, no router)."""
    zenoh.init_log_from_env_or("error")
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        raise ConnectionError(f"cannot open a zenoh session: {str(e).split(' at /')[0]}") from None


# ------------------------------------------------------------------------------------ server
class ZenohServer:
    """Wires a :class:`h3edge.serving.service.MapService` to zenoh keys."""

    def __init__(self, service, session: zenoh.Session, map_id: str, heavy_deadline_s: float = 30.0):
        """``heavy_deadline_s``: a mesh, render or save query still waiting in the queue after this
        long is answered with a deadline error (its client has likely given up; the work would be
        wasted and delay the queries behind it)."""
        self.service, self.session, self.keys = service, session, Keys.for_map(map_id)
        self.heavy_deadline_s = heavy_deadline_s
        self._fast: queue.Queue = queue.Queue(maxsize=64)
        self._heavy: queue.Queue = queue.Queue(maxsize=16)
        self._entities: list = []
        self._workers: list[threading.Thread] = []
        self._closing = threading.Event()
        self.live = None

    def start(self) -> None:
        s, k = self.service, self.keys
        self._entities.append(self.session.declare_subscriber(k.frame, lambda sample: s.submit_frame(
            sample.payload.to_bytes())))
        self._entities.append(self.session.declare_subscriber(k.pose, lambda sample: s.submit_pose(
            sample.payload.to_bytes())))
        if s.ros is not None:  # ROS 2 topics, as zenoh-bridge-ros2dds or rmw_zenoh put them on zenoh
            for role, key in s.ros.cfg.keys().items():
                handle = s.ros.handler(role)
                self._entities.append(self.session.declare_subscriber(
                    key, lambda sample, handle=handle: handle(sample.payload.to_bytes())))
                log.info("ROS %s from %s", role, key)
        handlers = {"status": (self._fast, self._status), "profile": (self._fast, self._profile),
                    "mesh": (self._heavy, self._mesh), "render": (self._heavy, self._render),
                    "sdf": (self._heavy, self._sdf), "slice": (self._heavy, self._slice),
                    "save": (self._heavy, self._save), "load": (self._heavy, self._load),
                    "export": (self._heavy, self._export)}
        for name, (q, fn) in handlers.items():
            self._entities.append(self.session.declare_queryable(getattr(k, name), self._enqueue(q, fn),
                                                                 complete=True))
        for name, q in (("fast", self._fast), ("heavy", self._heavy)):
            t = threading.Thread(target=self._work, args=(q,), name=f"h3edge-query-{name}", daemon=True)
            t.start()
            self._workers.append(t)
        cfg = s.cfg
        if cfg.live_interval_s > 0:
            from h3edge.serving.live import LivePublisher

            self.live = LivePublisher(s, self.session, k, cfg.live_interval_s, cfg.live_block_voxels,
                                      cfg.live_max_blocks, cfg.live_frame_width, cfg.live_refresh_s)
            self.live.start()
        log.info("serving map under %s/**", k.base)

    def _enqueue(self, q: queue.Queue, fn: Callable) -> Callable:
        def cb(query) -> None:
            try:
                q.put_nowait((query, fn, time.monotonic()))
            except queue.Full:  # refused with an error reply saying so, never an empty answer
                log.warning("query queue full: refused a query on %s", query.key_expr)
                with query:
                    query.reply_err(f"busy: {q.maxsize} queries on {query.key_expr} already waiting; retry after "
                                    "a second")
        return cb

    def _work(self, q: queue.Queue) -> None:
        while not self._closing.is_set():
            try:
                query, fn, queued_at = q.get(timeout=0.2)
            except queue.Empty:
                continue
            with query:
                waited = time.monotonic() - queued_at
                if q is self._heavy and waited > self.heavy_deadline_s:
                    log.warning("query on %s waited %.1f s: answered past its deadline", query.key_expr, waited)
                    query.reply_err(f"busy: deadline exceeded, the query waited {waited:.1f} s in the queue "
                                    f"(deadline {self.heavy_deadline_s:g} s); retry later")
                    continue
                try:
                    payload, encoding = fn(query)
                    query.reply(query.key_expr, payload, encoding=encoding)
                except QueryError as e:
                    query.reply_err(str(e))
                except Exception as e:  # noqa: BLE001 - any failure becomes an error reply
                    log.exception("query on %s failed", query.key_expr)
                    query.reply_err(f"internal error: {type(e).__name__}: {e}")

    @staticmethod
    def _request(query, binary: bool = False) -> dict:
        """The query's JSON payload merged with its selector parameters; with ``binary``, a payload
        that is not a JSON object is left for the caller (``query.payload``)."""
        out: dict = {}
        if query.payload is not None:
            raw = query.payload.to_bytes()
            if raw and not (binary and raw.lstrip()[:1] != b"{"):
                try:
                    out = json.loads(raw)
                except (ValueError, RecursionError) as e:  # bad UTF-8 or JSON, huge integers, deep nesting
                    raise QueryError(f"query payload must be JSON: {e}") from None
                if not isinstance(out, dict):
                    raise QueryError("query payload must be a JSON object")
        for k, v in query.parameters:  # selector parameters override: mesh?format=glb;resolution=4
            out[k] = v
        return out

    def _status(self, query):
        return json.dumps(self.service.status()).encode(), zenoh.Encoding.APPLICATION_JSON

    def _profile(self, query):
        return json.dumps(self.service.profile()).encode(), zenoh.Encoding.APPLICATION_JSON

    def _mesh(self, query):
        svc = self.service
        req = MeshRequest.parse(self._request(query), svc.settings.mapper.mesh_resolution, svc.cfg.max_mesh_resolution)
        return svc.mesh(req), zenoh.Encoding("model/" + MESH_FORMATS[req.format])

    def _render(self, query):
        req = RenderRequest.parse(self._request(query), self.service.settings.render.max_pixels)
        return self.service.render(req), zenoh.Encoding.APPLICATION_OCTET_STREAM

    def _sdf(self, query):
        raw = query.payload.to_bytes() if query.payload is not None else b""
        binary = bool(raw) and raw.lstrip()[:1] != b"{"
        req = SdfRequest.parse(self._request(query, binary=True), raw if binary else None,
                               self.service.cfg.max_query_points)
        out = self.service.signed_distance(req)
        arrays = {"sdf": out.sdf, "state": out.state}
        if out.gradient is not None:
            arrays["gradient"] = out.gradient
        return npz_bytes(arrays), zenoh.Encoding.APPLICATION_OCTET_STREAM

    def _slice(self, query):
        req = SliceRequest.parse(self._request(query), self.service.cfg.max_slice_cells)
        out = self.service.slice(req)
        meta = {"resolution": out.resolution, "origin": list(out.origin), "frame": "world", "rows": "y up from origin",
                "occupancy": "-1 unknown, 0 free, 100 occupied", "distance": "metres to the nearest occupied cell"}
        return npz_bytes({"occupancy": out.occupancy, "distance": out.distance,
                          "meta": np.frombuffer(json.dumps(meta).encode(), np.uint8)}), \
            zenoh.Encoding.APPLICATION_OCTET_STREAM

    def _exact(self, query, key: str, what: str) -> None:
        if str(query.key_expr) != key:  # a wildcard query must not write or replace anything
            raise QueryError(f"{what} needs the exact key {key}, not {query.key_expr}")

    def _save(self, query):
        self._exact(query, self.keys.save, "save")
        req = NamedRequest.parse(self._request(query), "save")
        return json.dumps(self.service.save(req)).encode(), zenoh.Encoding.APPLICATION_JSON

    def _load(self, query):
        self._exact(query, self.keys.load, "load")
        req = NamedRequest.parse(self._request(query), "load")
        return json.dumps(self.service.load(req)).encode(), zenoh.Encoding.APPLICATION_JSON

    def _export(self, query):
        self._exact(query, self.keys.export, "export")
        req = NamedRequest.parse(self._request(query), "export")
        return json.dumps(self.service.export_mesh(req)).encode(), zenoh.Encoding.APPLICATION_JSON

    def close(self) -> None:
        self._closing.set()
        if self.live is not None:
            self.live.close()
        for e in self._entities:
            try:
                e.undeclare()
            except Exception:  # noqa: BLE001 - closing anyway
                pass
        for t in self._workers:
            t.join(5)


# ------------------------------------------------------------------------------------ client
def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """Arrays as an uncompressed ``.npz`` (what sdf and slice replies carry; ``np.load`` reads it)."""
    import io

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def read_npz(data: bytes) -> dict[str, np.ndarray]:
    import io

    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def save_render_reply(data: bytes, out: Path) -> tuple[Path, Path]:
    """Write a render reply as OUT_color.png + OUT_depth.png (16-bit, mm); returns the paths."""
    from h3edge.io.protocol import decode_frame
    from h3edge.io.sequence import write_color, write_depth

    msg = decode_frame(data)
    out = Path(out)
    stem = out.with_suffix("") if out.suffix else out
    cpath, dpath = Path(f"{stem}_color.png"), Path(f"{stem}_depth.png")
    cpath.parent.mkdir(parents=True, exist_ok=True)
    write_color(cpath, msg.color)
    write_depth(dpath, msg.depth, 1000.0)
    return cpath, dpath


class RemoteError(RuntimeError):
    """The service answered with an error reply (the message is the service's)."""


def query(session: zenoh.Session, key: str, payload: dict | bytes | None = None, params: str = "",
          timeout: float = 60.0) -> bytes:
    """One query (``payload``: a JSON object, or raw bytes); the reply's bytes, :class:`RemoteError`
    on an error reply, TimeoutError on none."""
    selector = f"{key}?{params}" if params else key
    body = payload if isinstance(payload, bytes) else json.dumps(payload).encode() if payload is not None else None
    for reply in session.get(selector, payload=body, timeout=timeout):
        if reply.ok is not None:
            return reply.ok.payload.to_bytes()
        raise RemoteError(reply.err.payload.to_bytes().decode("utf-8", "replace"))
    raise TimeoutError(f"no reply from {selector} within {timeout:.0f} s (is the service running?)")


def fetch_profile(conf: zenoh.Config, map_id: str, timeout: float = 10.0) -> dict:
    """The profile document of the live service ``map_id`` (for ``h3edge profile report zenoh:``)."""
    with open_session(conf) as s:
        return json.loads(query(s, Keys.for_map(map_id).profile, timeout=timeout))


def wait_for_service(session: zenoh.Session, keys: Keys, timeout: float = 60.0) -> dict:
    """Poll ``status`` until the service answers; returns its status."""
    end = time.monotonic() + timeout
    while True:
        try:
            return json.loads(query(session, keys.status, timeout=2.0))
        except TimeoutError:
            if time.monotonic() > end:
                raise
            time.sleep(0.2)


# --------------------------------------------------------------------------------- publisher
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
