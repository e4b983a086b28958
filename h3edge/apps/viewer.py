"""``h3edge view``: the service's live outputs (:mod:`h3edge.serving.live`) streamed into Rerun.

Entities logged (one ``time`` timeline, the service's frame stamps):

- ``world/mesh/<i>_<j>_<k>``: each map block's latest mesh (``Mesh3D``; an empty block clears);
- ``world/trajectory``: the camera path so far (``LineStrips3D``);
- ``world/camera``: the latest mapped frame's pose (``Transform3D``) and pinhole, with its colour
  image at ``world/camera/image`` and depth at ``world/camera/depth``;
- ``world/render``: with ``render_every_s``, a render of the map from the latest pose (colour +
  depth), asked of the service's ``render`` query;
- ``timings/<component>``: per-component median milliseconds from the service's ``live/timings``
  stream (``Scalars``), and ``status/*`` counters.

The recording goes to a live viewer (``spawn``), a Rerun server (``connect``) or an ``.rrd`` file
(``save``: headless, what the tests read back).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path

import numpy as np

from h3edge.io.protocol import Keys, decode_frame
from h3edge.serving.client import Client, RemoteError

log = logging.getLogger(__name__)


class LiveViewer:
    """Subscribes to one map's live keys and logs them to a Rerun recording stream."""

    def __init__(self, session, keys: Keys, recording, render_every_s: float = 0.0):
        import rerun as rr

        self.rr, self.rec = rr, recording
        self.session, self.keys = session, keys
        self.client = Client(keys.base.split("/", 1)[1], session=session, timeout=60.0)
        self.render_every_s = render_every_s
        self.trajectory: list[np.ndarray] = []
        self.blocks: dict[str, int] = {}  # block -> faces of its latest mesh
        self.counts = {"status": 0, "timings": 0, "poses": 0, "frames": 0, "meshes": 0, "renders": 0}
        self._lock = threading.Lock()
        self._latest: tuple[int, np.ndarray, object] | None = None  # stamp, pose, intrinsics
        self._subs: list = []

    def start(self) -> None:
        base = f"{self.keys.base}/live"
        for key, fn in ((f"{base}/status", self._on_status), (f"{base}/timings", self._on_timings),
                        (f"{base}/poses", self._on_poses),
                        (f"{base}/frame", self._on_frame), (f"{base}/mesh/*", self._on_mesh)):
            self._subs.append(self.session.declare_subscriber(key, self._guard(fn)))

    def _guard(self, fn):
        def cb(sample) -> None:
            try:
                with self._lock:
                    fn(sample)
            except Exception:  # noqa: BLE001 - a bad sample must not end the view
                log.exception("live sample on %s", sample.key_expr)
        return cb

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.rec.flush()

    # ---------------------------------------------------------------- samples
    def _time(self, stamp_ns: int) -> None:
        self.rec.set_time("time", timestamp=stamp_ns * 1e-9)

    def _on_status(self, sample) -> None:
        st = json.loads(sample.payload.to_bytes())
        self.rec.set_time("time", timestamp=time.time())
        for name, value in (("frames_mapped", st["map"]["frames_mapped"]), ("voxels", st["map"]["voxels"]),
                            ("keyframes", st["map"]["keyframes"]), ("dropped", st["frames"]["dropped"]),
                            ("memory_mb", st["memory"]["total_bytes"] / 2**20)):
            if value is not None:
                self.rec.log(f"status/{name}", self.rr.Scalars(float(value)))
        self.counts["status"] += 1

    def _on_timings(self, sample) -> None:
        self.rec.set_time("time", timestamp=time.time())
        for name, t in json.loads(sample.payload.to_bytes()).items():
            if isinstance(t, dict) and t.get("median_ms") is not None:
                self.rec.log(f"timings/{name}", self.rr.Scalars(float(t["median_ms"])))
        self.counts["timings"] += 1

    def _on_poses(self, sample) -> None:
        rr = self.rr
        doc = json.loads(sample.payload.to_bytes())
        for p in doc["poses"]:
            self.trajectory.append(np.asarray(p["matrix"], np.float64).reshape(4, 4)[:3, 3])
        if doc["poses"]:
            self._time(doc["poses"][-1]["t"])
            self.rec.log("world/trajectory", rr.LineStrips3D([np.array(self.trajectory)], colors=[[255, 160, 0]]))
        self.counts["poses"] += len(doc["poses"])

    def _on_frame(self, sample) -> None:
        rr = self.rr
        msg = decode_frame(sample.payload.to_bytes())
        if msg.pose is None:
            return
        self._time(msg.timestamp_ns)
        intr = msg.intrinsics
        self.rec.log("world/camera", rr.Transform3D(translation=msg.pose[:3, 3], mat3x3=msg.pose[:3, :3]))
        self.rec.log("world/camera", rr.Pinhole(image_from_camera=intr.K, resolution=[intr.width, intr.height],
                                                camera_xyz=rr.ViewCoordinates.RDF))
        self.rec.log("world/camera/image", rr.Image(msg.color))
        self.rec.log("world/camera/depth", rr.DepthImage(msg.depth, meter=1.0))
        self._latest = (msg.timestamp_ns, msg.pose, intr)
        self.counts["frames"] += 1

    def _on_mesh(self, sample) -> None:
        import trimesh

        rr = self.rr
        block = str(sample.key_expr).rsplit("/", 1)[-1]
        data = sample.payload.to_bytes()
        self.rec.set_time("time", timestamp=time.time())
        path = f"world/mesh/{block}"
        if not data:
            self.rec.log(path, rr.Clear(recursive=False))
            self.blocks[block] = 0
            return
        mesh = trimesh.load(trimesh.util.wrap_as_stream(data), file_type="ply", process=False)
        colors = getattr(mesh.visual, "vertex_colors", None)
        self.rec.log(path, rr.Mesh3D(vertex_positions=np.asarray(mesh.vertices, np.float32),
                                     triangle_indices=np.asarray(mesh.faces, np.uint32),
                                     vertex_normals=np.asarray(mesh.vertex_normals, np.float32),
                                     vertex_colors=None if colors is None else np.asarray(colors)[:, :3]))
        self.blocks[block] = len(mesh.faces)
        self.counts["meshes"] += 1

    # ----------------------------------------------------------- polled queries
    def poll(self, now: float, last: dict) -> None:
        """Renders from the latest pose at their rate (called from the viewer's loop)."""
        if self.render_every_s > 0 and self._latest is not None and now - last.get("render", 0) > self.render_every_s:
            last["render"] = now
            self._render()

    def _render(self) -> None:
        stamp, pose, intr = self._latest
        small = intr.scaled(min(intr.width, 320), round(intr.height * min(intr.width, 320) / intr.width))
        try:
            color, depth = self.client.render(pose, intrinsics=small)
        except (RemoteError, TimeoutError) as e:
            log.warning("render: %s", e)
            return
        with self._lock:
            self._time(stamp)
            self.rec.log("world/render", self.rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
            self.rec.log("world/render", self.rr.Pinhole(image_from_camera=small.K,
                                                         resolution=[small.width, small.height],
                                                         camera_xyz=self.rr.ViewCoordinates.RDF))
            self.rec.log("world/render/color", self.rr.Image(color))
            self.rec.log("world/render/depth", self.rr.DepthImage(depth, meter=1.0))
            self.counts["renders"] += 1


def run_viewer(session, map_id: str, save: str | None = None, spawn: bool = False, connect: str | None = None,
               duration_s: float | None = None, render_every_s: float = 0.0, stop: threading.Event | None = None
               ) -> dict:
    """Stream the live map into Rerun until ``duration_s`` passes or ``stop`` is set; the counts of
    what was logged."""
    import rerun as rr

    rec = rr.RecordingStream("h3edge", recording_id=f"h3edge-{map_id}")
    if save:
        Path(save).parent.mkdir(parents=True, exist_ok=True)
        rec.save(save)
    elif connect:
        rec.connect_grpc(connect)
    elif spawn:
        rec.spawn()
    else:
        raise ValueError("view needs a sink: save (an .rrd file), connect (a Rerun server URL) or spawn")
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    viewer = LiveViewer(session, Keys.for_map(map_id), rec, render_every_s)
    viewer.start()
    stop = stop or threading.Event()
    end = None if duration_s is None else time.monotonic() + duration_s
    last: dict = {}
    try:
        while not stop.wait(0.2):
            now = time.monotonic()
            if end is not None and now > end:
                break
            viewer.poll(now, last)
    finally:
        viewer.close()
        rec.flush()
        if save:
            rec.disconnect()
    return dict(viewer.counts, blocks=len(viewer.blocks))
