"""The zenoh server around a :class:`~h3edge.serving.service.MapService`: frames and poses in,
queries answered.

Keys (``<base>`` = ``h3edge/<map-id>``, :class:`~h3edge.io.protocol.Keys`): ``<base>/frame`` and
``<base>/pose`` (put), queryables ``<base>/status``, ``/profile``, ``/mesh``, ``/render``, ``/sdf``,
``/slice`` and the operator's ``/save``, ``/load``, ``/export`` (docs/protocol.md;
:class:`h3edge.serving.client.Client` asks them).

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

import numpy as np
import zenoh

from h3edge.errors import InputError, QueryError
from h3edge.io.protocol import Keys
from h3edge.serving.queries import MESH_FORMATS, MeshRequest, NamedRequest, RenderRequest, SdfRequest, SliceRequest

log = logging.getLogger(__name__)


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
        self.checkpoint_publisher = None

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
            key = getattr(k, name)
            self._entities.append(self.session.declare_queryable(key, self._enqueue(q, fn, key), complete=True))
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
        if cfg.fleet_checkpoints:
            from h3edge.serving.keeping import CheckpointPublisher

            self.checkpoint_publisher = CheckpointPublisher(self.session, cfg.map_id, lambda: s.checkpoints.last)
            self.checkpoint_publisher.start()
        log.info("serving map under %s/**", k.base)

    def _enqueue(self, q: queue.Queue, fn: Callable, key: str) -> Callable:
        """The queryable's callback: queue the query for ``fn``; it is answered on ``key``, this map's own
        key, also when it came on a wildcard (``h3edge/*/status``): who answered is in the reply's key,
        and a site router's access rules can allow each robot to reply only under its own map id."""
        def cb(query) -> None:
            try:
                q.put_nowait((query, fn, time.monotonic(), key))
            except queue.Full:  # refused with an error reply saying so, never an empty answer
                log.warning("query queue full: refused a query on %s", query.key_expr)
                with query:
                    query.reply_err(f"busy: {q.maxsize} queries on {query.key_expr} already waiting; retry after "
                                    "a second")
        return cb

    def _work(self, q: queue.Queue) -> None:
        while not self._closing.is_set():
            try:
                query, fn, queued_at, key = q.get(timeout=0.2)
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
                    query.reply(key, payload, encoding=encoding)
                except InputError as e:  # a query refused, by the parser (QueryError) or the library
                    query.reply_err(str(e))
                except Exception as e:  # noqa: BLE001 - any failure becomes an error reply
                    log.exception("query on %s failed", query.key_expr)
                    query.reply_err(f"internal error: {type(e).__name__}: {e}")

    @staticmethod
    def _request(query, binary: bool = False) -> dict:
        # binary: the caller decided the payload is not JSON (sdf's raw points) and reads it itself
        """The query's JSON payload merged with its selector parameters; with ``binary``, a payload
        that is not a JSON object is left for the caller (``query.payload``)."""
        out: dict = {}
        if query.payload is not None:
            raw = query.payload.to_bytes()
            if raw and not binary:
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
        binary = bool(raw) and _raw_points(raw, query.encoding)
        req = SdfRequest.parse(self._request(query, binary=binary), raw if binary else None,
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
        if self.checkpoint_publisher is not None:
            self.checkpoint_publisher.close()
        for e in self._entities:
            try:
                e.undeclare()
            except Exception:  # noqa: BLE001 - closing anyway
                pass
        for t in self._workers:
            t.join(5)


def _raw_points(payload: bytes, encoding) -> bool:
    """Whether an sdf query's payload is raw float32 points rather than a JSON request: as its
    encoding says (the client sets octet-stream or JSON); without one, JSON only when it parses as a
    JSON object (raw points may begin with the byte ``{``)."""
    if encoding == zenoh.Encoding.APPLICATION_OCTET_STREAM:
        return True
    if encoding == zenoh.Encoding.APPLICATION_JSON:
        return False
    if payload.lstrip()[:1] != b"{":
        return True
    try:
        return not isinstance(json.loads(payload), dict)
    except (ValueError, RecursionError):
        return True


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """Arrays as an uncompressed ``.npz`` (what sdf and slice replies carry; ``np.load`` reads it)."""
    import io

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()
