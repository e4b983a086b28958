"""Live outputs: what the service publishes as it maps, for viewers (``h3edge view`` -> Rerun) and
for anyone subscribed on zenoh.

Every ``live_interval_s`` (``<base>`` = ``h3edge/<map-id>``):

- ``<base>/live/status``: the status document (JSON);
- ``<base>/live/timings``: the per-component timing summary (JSON ``{component: {median_ms, p95_ms,
  mean_ms, total_s, count}}``);
- ``<base>/live/poses``: the camera poses of the frames mapped since the last update (JSON
  ``{"poses": [{"t": ns, "matrix": [16 row-major]}]}``; a viewer accumulates the trajectory);
- ``<base>/live/frame``: the latest mapped frame's colour image as JPEG (at most
  ``live_frame_width`` wide), with its pose and intrinsics in a frame message;
- ``<base>/live/mesh/<i>_<j>_<k>``: the PLY mesh (vertex colours) of block (i, j, k), a cube of
  ``live_block_voxels`` leaf voxels: each block where the mapped frames allocated voxels or set
  priors since the last update, and a share of the others, stalest first, so that every block is
  rebuilt at least every ``live_refresh_s`` (training refines the whole map a little all the
  time); at most ``live_max_blocks`` per update, the rest at the next. A block mesh replaces that
  block's previous one; the union of the latest block meshes is the map.

Runs on its own thread against the service's frozen map copies (never on the mapper thread), and
only while someone subscribes to ``<base>/live/status`` (zenoh's matching status; every viewer does):
with nobody watching it takes no map copies and builds no meshes. A viewer that starts watching
gets every block, ``live_max_blocks`` per update, then the changes.
"""

from __future__ import annotations

import json
import logging
import threading
import time

import cv2
import numpy as np
import zenoh

from h3edge.io.protocol import FrameMessage, encode_frame

log = logging.getLogger(__name__)


def block_key(block: np.ndarray) -> str:
    return "_".join(str(int(v)) for v in block)


def parse_block_key(text: str) -> tuple[int, int, int]:
    i, j, k = (int(v) for v in text.split("_"))
    return i, j, k


class LivePublisher:
    """Publishes the service's live outputs on ``keys`` (module docstring)."""

    def __init__(self, service, session: zenoh.Session, keys, interval_s: float, block_voxels: int,
                 max_blocks: int, frame_width: int, refresh_s: float = 60.0):
        self.service, self.session, self.keys = service, session, keys
        self.interval_s, self.block_voxels, self.max_blocks = interval_s, block_voxels, max_blocks
        self.refresh_s = refresh_s
        self._sent: dict[tuple[int, int, int], float] = {}  # block -> when its mesh was last published
        self._status_pub = session.declare_publisher(f"{keys.base}/live/status")
        self._watched = False
        self.frame_width = frame_width
        self._pending: set[tuple[int, int, int]] = set()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.updates = 0  # mesh updates published
        self.last: dict = {}  # the last update's blocks, bytes and seconds

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="h3edge-live", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(30)
        self._status_pub.undeclare()

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                self.publish_once()
            except Exception:  # noqa: BLE001 - a failed update must not end the live stream
                log.exception("live update failed")

    def publish_once(self) -> dict:
        """One update (status, new poses, latest frame, changed blocks); what it sent."""
        svc = self.service
        if not self._status_pub.matching_status.matching:
            self._watched = False
            return {"watched": False}
        if not self._watched:  # a new viewer: every block, stalest (all of them) first
            self._watched = True
            self._sent.clear()
            self._pending.clear()
            if not svc.mapper.empty:
                self._pending.update(tuple(int(v) for v in b) for b in
                                     np.unique(np.floor_divide(svc.view().voxel_coords(), self.block_voxels), axis=0))
        self._status_pub.put(json.dumps(svc.status()).encode())
        self.session.put(f"{self.keys.base}/live/timings", json.dumps(svc.mapper.timings.summary()).encode())
        poses = svc.take_mapped_poses()
        if poses:
            doc = {"poses": [{"t": int(t), "matrix": np.asarray(p).reshape(-1).tolist()} for t, p in poses]}
            self.session.put(f"{self.keys.base}/live/poses", json.dumps(doc).encode())
        latest = svc.latest_frame
        if latest is not None and poses:
            self.session.put(f"{self.keys.base}/live/frame", self._thumbnail(latest))
        if svc.mapper.empty:
            return {"blocks": 0}
        view = svc.view()
        changed = svc.take_changed_voxels()
        if len(changed):
            blocks = np.unique(np.floor_divide(changed, self.block_voxels), axis=0)
            self._pending.update(tuple(int(v) for v in b) for b in blocks)
        if self.refresh_s > 0:  # the stalest share of the map's blocks
            every = [tuple(int(v) for v in b) for b in
                     np.unique(np.floor_divide(view.voxel_coords(), self.block_voxels), axis=0)]
            share = int(np.ceil(len(every) * self.interval_s / self.refresh_s))
            self._pending.update(sorted(every, key=lambda b: self._sent.get(b, -np.inf))[:share])
        todo = sorted(self._pending, key=lambda b: self._sent.get(b, -np.inf))[: self.max_blocks]
        sent, t0 = 0, time.perf_counter()
        meshes = view.block_meshes(np.array(todo, np.int64).reshape(-1, 3), self.block_voxels) if todo else []
        for block, mesh in zip(todo, meshes):
            self._pending.discard(block)
            data = mesh.export(file_type="ply") if len(mesh.faces) else b""
            self.session.put(f"{self.keys.base}/live/mesh/{block_key(np.array(block))}", data)
            self._sent[block] = time.monotonic()
            sent += len(data)
        if todo:
            self.updates += 1
            svc.mapper.timings.add("live_mesh", time.perf_counter() - t0)
        self.last = {"blocks": len(todo), "bytes": sent, "seconds": time.perf_counter() - t0,
                     "pending": len(self._pending)}
        return self.last

    def _thumbnail(self, msg: FrameMessage) -> bytes:
        h, w = msg.color.shape[:2]
        if w > self.frame_width:
            s = self.frame_width / w
            color = cv2.resize(msg.color, (self.frame_width, max(1, round(h * s))), interpolation=cv2.INTER_AREA)
            depth = cv2.resize(msg.depth, (color.shape[1], color.shape[0]), interpolation=cv2.INTER_NEAREST)
            intr = msg.intrinsics.scaled(color.shape[1], color.shape[0])
        else:
            color, depth, intr = msg.color, msg.depth, msg.intrinsics
        return encode_frame(FrameMessage(msg.timestamp_ns, msg.frame_id, color, depth, intr, msg.pose), "jpeg", "png16")
