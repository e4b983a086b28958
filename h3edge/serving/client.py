"""The typed client of a running h3edge service (``from h3edge import Client``): status, profile, mesh,
render, signed distance, slice, save, load and export over zenoh, answers as numpy arrays and
dataclasses, errors as exceptions carrying the service's message. It imports neither torch nor
numba: a planner or a laptop asks a robot's map without the mapping stack.

The query function below it (:func:`query`: one zenoh get, a reply's bytes) is what the client and
the commands that speak raw payloads share.
"""

from __future__ import annotations

import io
import json
import time
from pathlib import Path

import numpy as np
import zenoh

from h3edge.geometry.camera import Intrinsics
from h3edge.io.distance_types import DistanceSample, DistanceSlice
from h3edge.io.protocol import Keys, decode_frame, pose_to_json
from h3edge.io.zenoh_session import open_session, zenoh_config


class RemoteError(RuntimeError):
    """The service answered with an error reply (the message is the service's)."""


#: Pauses (s) before asking again when the network ends a query at once with no answer. A client's
#: zenoh session routes a query only to the queryables it has learnt of, and that view can lag the
#: network's for a moment (eclipse-zenoh/zenoh#2767): one at-once empty answer is not yet "nobody".
_EMPTY_ANSWER_RETRY_S = (0.1, 0.2, 0.4, 0.8)
#: An empty answer within this many seconds of asking counts as "at once" (the network answered, not a slow service).
_AT_ONCE_S = 0.25


def query(session: zenoh.Session, key: str, payload: dict | bytes | None = None, params: str = "",
          timeout: float = 60.0) -> bytes:
    """One query (``payload``: a JSON object, or raw bytes); the reply's bytes, :class:`RemoteError`
    on an error reply, TimeoutError on none. A query the network ends at once with no answer is asked
    again after 0.1, 0.2, 0.4 and 0.8 s (while that stays under half of ``timeout``) before it says so.
    An h3edge service answers every query it takes with a reply or an error reply, so an at-once empty
    answer reached none, or an access rule of the network dropped its reply (the service's verbs bear
    being asked twice: a second save within ``save_min_interval_s`` is refused)."""
    selector = f"{key}?{params}" if params else key
    body = payload if isinstance(payload, bytes) else json.dumps(payload).encode() if payload is not None else None
    encoding = None if body is None else (zenoh.Encoding.APPLICATION_OCTET_STREAM if isinstance(payload, bytes)
                                          else zenoh.Encoding.APPLICATION_JSON)
    start = time.monotonic()
    pauses = iter(_EMPTY_ANSWER_RETRY_S)
    tries = 0
    while True:
        asked = time.monotonic()
        tries += 1
        for reply in session.get(selector, payload=body, encoding=encoding, timeout=timeout - (asked - start)):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
            raise RemoteError(reply.err.payload.to_bytes().decode("utf-8", "replace"))
        now = time.monotonic()
        if now - asked >= _AT_ONCE_S:
            break
        pause = next(pauses, None)
        if pause is None or now + pause - start >= 0.5 * timeout:
            break
        time.sleep(pause)
    waited = now - start
    if now - asked < _AT_ONCE_S:  # the network answered "nobody" at once: not a slow service
        asked_n = "once" if tries == 1 else f"{tries} times in {waited:.1f} s"
        raise TimeoutError(f"no reply from {selector}: the query ended at once with no answer, asked {asked_n} (no "
                           "service serves this key, or an access-control rule of the network denies it)")
    if waited < 0.9 * timeout:
        raise TimeoutError(f"no reply from {selector}: the query ended after {waited:.1f} s with no answer")
    raise TimeoutError(f"no reply from {selector} within {timeout:.0f} s (is the service running?)")


def read_npz(data: bytes) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` reply (sdf, slice), read without pickles."""
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def wait_for_service(session: zenoh.Session, keys: Keys, timeout: float = 60.0) -> dict:
    """Poll ``status`` until the service answers; returns its status (TimeoutError after ``timeout`` s)."""
    end = time.monotonic() + timeout
    while True:
        try:
            return json.loads(query(session, keys.status, timeout=2.0))
        except TimeoutError:
            if time.monotonic() > end:
                raise
            time.sleep(0.2)


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


def open_client_session(config: str | zenoh.Config | None = None, connect: list[str] | None = None,
                        mode: str | None = None, multicast: bool | None = None) -> zenoh.Session:
    """A zenoh session for queries: ``config`` (a JSON5 file or a ``zenoh.Config``; default zenoh's:
    peer, multicast scouting), with ``connect`` / ``mode`` / ``multicast`` overriding it."""
    conf = config if isinstance(config, zenoh.Config) else zenoh_config(config, mode, connect, None, multicast)
    return open_session(conf)


def render_request(c2w, width: int = 320, height: int = 240, intrinsics: Intrinsics | None = None,
                   fov_deg: float = 80.0) -> dict:
    """A render query's JSON (raw colour and metres back) at camera-to-world ``c2w`` (4, 4):
    ``intrinsics`` (its size wins) or a horizontal field of view ``fov_deg`` over ``width`` x ``height``."""
    payload: dict = {"pose": pose_to_json(np.asarray(c2w, np.float64)), "raw": True}
    if intrinsics is not None:
        payload.update(width=intrinsics.width, height=intrinsics.height,
                       intrinsics={"fx": intrinsics.fx, "fy": intrinsics.fy, "cx": intrinsics.cx, "cy": intrinsics.cy})
    else:
        payload.update(width=int(width), height=int(height), fov_deg=float(fov_deg))
    return payload


class SessionUser:
    """Holds a zenoh session for queries: the one it opened (closed by :meth:`close` and on leaving a
    ``with`` block) or one it was given (left open)."""

    def __init__(self, config: str | zenoh.Config | None, connect: list[str] | None, mode: str | None,
                 multicast: bool | None, session: zenoh.Session | None):
        self._owned = session is None
        self.session = session if session is not None else open_client_session(config, connect, mode, multicast)

    def close(self) -> None:
        """Close the zenoh session (when this object opened it)."""
        if self._owned:
            self.session.close()
            self._owned = False

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Client(SessionUser):
    """Queries to the h3edge service of map ``map_id`` over zenoh.

    Usage::

        from h3edge import Client

        with Client("lab", connect=["tcp/robot.local:7447"]) as c:
            c.wait()                                        # the service's status once it answers
            color, depth = c.render(c2w, width=320, height=240)
            c.mesh("glb")                                   # bytes of a glTF binary
            d = c.signed_distance(points, gradient=True)    # DistanceSample
            c.save("before-lunch")

    Every method raises :class:`RemoteError` with the service's message when it refuses (a bad or
    oversized request, nothing mapped yet), TimeoutError when no service answers within ``timeout``
    seconds. Poses are camera-to-world 4x4 in metres, OpenCV optical axes; points world metres."""

    def __init__(self, map_id: str = "default", config: str | zenoh.Config | None = None, *,
                 connect: list[str] | None = None, mode: str | None = None, multicast: bool | None = None,
                 timeout: float = 60.0, session: zenoh.Session | None = None):
        """``config``: a zenoh JSON5 file or a ``zenoh.Config`` (default: zenoh's defaults: peer,
        multicast scouting); ``connect`` / ``mode`` / ``multicast`` override it. ``session``: an
        open session to use instead (the client then does not close it)."""
        super().__init__(config, connect, mode, multicast, session)
        self.keys = Keys.for_map(map_id)
        self.timeout = timeout

    def _ask(self, key: str, payload: dict | bytes | None = None, params: str = "") -> bytes:
        return query(self.session, key, payload, params, self.timeout)

    # ----------------------------------------------------------------- state
    def wait(self, timeout: float = 60.0) -> dict:
        """The service's status as soon as it answers (polling); TimeoutError after ``timeout`` s."""
        return wait_for_service(self.session, self.keys, timeout)

    def status(self) -> dict:
        """The service's status: frames mapped and dropped (by reason), queue, training, memory,
        the map's extent, the last checkpoint (docs/protocol.md)."""
        return json.loads(self._ask(self.keys.status))

    def profile(self) -> dict:
        """The timing profile document (per component: count, median, p90 ms; ``table``: as text)."""
        return json.loads(self._ask(self.keys.profile))

    # --------------------------------------------------------------- queries
    def mesh(self, format: str = "ply", resolution: int | None = None, aabb=None) -> bytes:
        """The mesh as a ``ply``, ``glb`` or ``obj`` file's bytes (world metres, vertex colours;
        ``trimesh.load(io.BytesIO(data), file_type=format)`` reads it). ``resolution``: cells per
        voxel edge (default: the service's); ``aabb``: (2, 3) metres, only that box."""
        payload: dict = {"format": format}
        if resolution is not None:
            payload["resolution"] = int(resolution)
        if aabb is not None:
            payload["aabb"] = np.asarray(aabb, np.float64).reshape(2, 3).tolist()
        return self._ask(self.keys.mesh, payload)

    def render(self, c2w, width: int = 320, height: int = 240, intrinsics: Intrinsics | None = None,
               fov_deg: float = 80.0) -> tuple[np.ndarray, np.ndarray]:
        """The map seen from camera-to-world ``c2w`` (4, 4): colour uint8 (H, W, 3) RGB and z-depth
        float32 (H, W) metres (0: nothing). ``intrinsics`` (its size wins over ``width`` /
        ``height``) or a horizontal field of view ``fov_deg``."""
        msg = decode_frame(self._ask(self.keys.render, render_request(c2w, width, height, intrinsics, fov_deg)))
        return msg.color, msg.depth

    def signed_distance(self, points, gradient: bool = False) -> DistanceSample:
        """Signed distance at world points (N, 3) metres (sent as float32): ``.sdf`` metres (NaN
        unknown), ``.state`` (0 unknown, 1 free, 2 near, 3 inside), ``.gradient`` (N, 3) when asked."""
        raw = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3), "<f4").tobytes()
        a = read_npz(self._ask(self.keys.sdf, raw, "gradient=true" if gradient else ""))
        return DistanceSample(a["sdf"], a["state"], a.get("gradient"))

    def slice(self, z: float, lo, hi, resolution: float = 0.05) -> DistanceSlice:
        """Occupancy and distance images at height ``z`` (m) over ``lo`` = (xmin, ymin) .. ``hi`` =
        (xmax, ymax) metres, ``resolution`` metres a cell (row 0 is the lowest y)."""
        payload = {"z": float(z), "aabb": [[float(lo[0]), float(lo[1])], [float(hi[0]), float(hi[1])]],
                   "resolution": float(resolution)}
        a = read_npz(self._ask(self.keys.slice, payload))
        meta = json.loads(a["meta"].tobytes().decode())
        return DistanceSlice(a["occupancy"], a["distance"], tuple(meta["origin"]), float(meta["resolution"]))

    # ---------------------------------------------------------------- files
    def save(self, name: str | None = None) -> dict:
        """Checkpoint now: the resume checkpoint, or ``maps/<name>.h3ckpt`` under the service's state
        directory. Returns where, how many frames and bytes."""
        return json.loads(self._ask(self.keys.save, {"name": name} if name else {}))

    def load(self, name: str | None = None) -> dict:
        """Replace the running map with a saved one (``maps/<name>.h3ckpt``; none: the resume
        checkpoint). Returns what was loaded."""
        return json.loads(self._ask(self.keys.load, {"name": name} if name else {}))

    def export(self, name: str, format: str = "ply") -> dict:
        """Write the whole map's mesh to ``exports/<name>.<format>`` on the service's machine."""
        return json.loads(self._ask(self.keys.export, {"name": name, "format": format}))
