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

``h3edge view --fleet`` (:func:`run_fleet_viewer`) shows every map of a site in one recording: each
map's entities under ``site/<map-id>/`` (mesh, trajectory, camera, render), placed by its status's
``site_from_world`` (a ``Transform3D`` on ``site/<map-id>``), its counters under ``maps/<map-id>/``;
maps that appear later join at the next scan.

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

    def __init__(self, session, keys: Keys, recording, render_every_s: float = 0.0, root: str = "world",
                 stats: str = ""):
        """``root``: the entity path the map's geometry goes under; ``stats``: the prefix of its
        ``status/`` and ``timings/`` counters."""
        import rerun as rr

        self.rr, self.rec = rr, recording
        self.session, self.keys = session, keys
        self.client = Client(keys.base.split("/", 1)[1], session=session, timeout=60.0)
        self.render_every_s = render_every_s
        self.root, self.stats = root, stats
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
                self.rec.log(f"{self.stats}status/{name}", self.rr.Scalars(float(value)))
        self.counts["status"] += 1

    def _on_timings(self, sample) -> None:
        self.rec.set_time("time", timestamp=time.time())
        for name, t in json.loads(sample.payload.to_bytes()).items():
            if isinstance(t, dict) and t.get("median_ms") is not None:
                self.rec.log(f"{self.stats}timings/{name}", self.rr.Scalars(float(t["median_ms"])))
        self.counts["timings"] += 1

    def _on_poses(self, sample) -> None:
        rr = self.rr
        doc = json.loads(sample.payload.to_bytes())
        for p in doc["poses"]:
            self.trajectory.append(np.asarray(p["matrix"], np.float64).reshape(4, 4)[:3, 3])
        if doc["poses"]:
            self._time(doc["poses"][-1]["t"])
            self.rec.log(f"{self.root}/trajectory", rr.LineStrips3D([np.array(self.trajectory)],
                                                                    colors=[[255, 160, 0]]))
        self.counts["poses"] += len(doc["poses"])

    def _on_frame(self, sample) -> None:
        rr = self.rr
        msg = decode_frame(sample.payload.to_bytes())
        if msg.pose is None:
            return
        self._time(msg.timestamp_ns)
        intr = msg.intrinsics
        self.rec.log(f"{self.root}/camera", rr.Transform3D(translation=msg.pose[:3, 3], mat3x3=msg.pose[:3, :3]))
        self.rec.log(f"{self.root}/camera", rr.Pinhole(image_from_camera=intr.K, resolution=[intr.width, intr.height],
                                                camera_xyz=rr.ViewCoordinates.RDF))
        self.rec.log(f"{self.root}/camera/image", rr.Image(msg.color))
        self.rec.log(f"{self.root}/camera/depth", rr.DepthImage(msg.depth, meter=1.0))
        self._latest = (msg.timestamp_ns, msg.pose, intr)
        self.counts["frames"] += 1

    def _on_mesh(self, sample) -> None:
        import trimesh

        rr = self.rr
        block = str(sample.key_expr).rsplit("/", 1)[-1]
        data = sample.payload.to_bytes()
        self.rec.set_time("time", timestamp=time.time())
        path = f"{self.root}/mesh/{block}"
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
            self.rec.log(f"{self.root}/render", self.rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
            self.rec.log(f"{self.root}/render", self.rr.Pinhole(image_from_camera=small.K,
                                                         resolution=[small.width, small.height],
                                                         camera_xyz=self.rr.ViewCoordinates.RDF))
            self.rec.log(f"{self.root}/render/color", self.rr.Image(color))
            self.rec.log(f"{self.root}/render/depth", self.rr.DepthImage(depth, meter=1.0))
            self.counts["renders"] += 1


def _recording(recording_id: str, save: str | None, spawn: bool, connect: str | None):
    import rerun as rr

    rec = rr.RecordingStream("h3edge", recording_id=recording_id)
    if save:
        Path(save).parent.mkdir(parents=True, exist_ok=True)
        rec.save(save)
    elif connect:
        rec.connect_grpc(connect)
    elif spawn:
        rec.spawn()
    else:
        raise ValueError("view needs a sink: save (an .rrd file), connect (a Rerun server URL) or spawn")
    return rec


def _run(rec, viewers: dict, save: str | None, duration_s: float | None, stop: threading.Event | None,
         scan=None, scan_every_s: float = 5.0) -> None:
    stop = stop or threading.Event()
    end = None if duration_s is None else time.monotonic() + duration_s
    last: dict = {}
    try:
        while not stop.wait(0.2):
            now = time.monotonic()
            if end is not None and now > end:
                break
            if scan is not None and now - last.get("scan", -1e9) > scan_every_s:
                last["scan"] = now
                scan()
            for mid, v in list(viewers.items()):
                v.poll(now, last.setdefault(mid, {}))
    finally:
        for v in viewers.values():
            v.close()
        rec.flush()
        if save:
            rec.disconnect()


def run_viewer(session, map_id: str, save: str | None = None, spawn: bool = False, connect: str | None = None,
               duration_s: float | None = None, render_every_s: float = 0.0, stop: threading.Event | None = None
               ) -> dict:
    """Stream the live map into Rerun until ``duration_s`` passes or ``stop`` is set; the counts of
    what was logged."""
    import rerun as rr

    rec = _recording(f"h3edge-{map_id}", save, spawn, connect)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    viewer = LiveViewer(session, Keys.for_map(map_id), rec, render_every_s)
    viewer.start()
    _run(rec, {map_id: viewer}, save, duration_s, stop)
    return dict(viewer.counts, blocks=len(viewer.blocks))


def run_fleet_viewer(session, save: str | None = None, spawn: bool = False, connect: str | None = None,
                     duration_s: float | None = None, render_every_s: float = 0.0,
                     stop: threading.Event | None = None, scan_every_s: float = 5.0) -> dict:
    """Every map of the site (:func:`h3edge.serving.fleet.fleet_status`, scanned every
    ``scan_every_s`` seconds) streamed into one Rerun recording in the site frame until
    ``duration_s`` passes or ``stop`` is set; per map id, the counts of what was logged."""
    import rerun as rr

    from h3edge.serving.fleet import fleet_status

    rec = _recording("h3edge-fleet", save, spawn, connect)
    rec.log("site", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    viewers: dict[str, LiveViewer] = {}
    placed: dict[str, list] = {}

    def scan() -> None:
        for e in fleet_status(session, 2.0):
            mid, st = e["map_id"], e.get("status")
            if st is None:
                continue
            t = np.asarray(st.get("site_from_world") or np.eye(4), np.float64).reshape(4, 4)
            if placed.get(mid) != t.tolist():  # where the map lies in the site frame (logged again if it moves)
                rec.set_time("time", timestamp=time.time())
                rec.log(f"site/{mid}", rr.Transform3D(translation=t[:3, 3], mat3x3=t[:3, :3]))
                placed[mid] = t.tolist()
            if mid not in viewers:
                viewers[mid] = LiveViewer(session, Keys.for_map(mid), rec, render_every_s, root=f"site/{mid}",
                                          stats=f"maps/{mid}/")
                viewers[mid].start()
                log.info("viewing map %r", mid)

    _run(rec, viewers, save, duration_s, stop, scan, scan_every_s)
    return {mid: dict(v.counts, blocks=len(v.blocks)) for mid, v in viewers.items()}
