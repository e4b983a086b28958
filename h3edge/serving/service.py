"""The map service core, transport-free: ingest, the mapper thread, queries, checkpoints, status.

Data path: the transport hands raw frame and pose messages to :meth:`MapService.submit_frame` /
:meth:`MapService.submit_pose`, which never block: a frame goes into a bounded ingest queue
(``ingest_queue`` deep; when full the *oldest* waiting frame is dropped and counted
``queue_full``, so the mapper always works on recent frames and memory stays bounded), a pose is
parsed and put in the :class:`PoseBuffer`. The mapper thread takes the oldest queued frame,
decodes it (``malformed`` when the protocol is broken), finds its pose (its own, or interpolated
from the pose stream; it waits up to ``pose_wait_s`` for a pose after its timestamp, then drops it
as ``no_pose``), and maps it (the mapper's own drop codes: ``bad_pose``, ``stale_timestamp``,
``no_depth``, ...). A bad message never touches the map.

The map is an :class:`h3edge.Mapper` (the library; this module is one of its clients: it reaches
the map through the Mapper's verbs, its counts, ``take_changed_voxels`` and its step hook).

Queries (mesh, render) run on the caller's thread against a frozen copy of the map that the
mapper thread makes between two training steps (so a query waits at most one training
iteration for it, and mapping is held up only for the copy, tens of ms); a copy younger than
``snapshot_max_age_s`` is reused. Status reads counters the mapper thread publishes after each
frame (no lock, no wait).

Checkpoints: every ``checkpoint_interval_s``, on ``save`` and on stop, through the
:class:`~h3edge.serving.checkpointing.Checkpointer` (the mapper thread captures between frames; its
writer thread writes atomically).

Memory budget: ``memory_budget_mb`` is split up front (:mod:`h3edge.mapping.memory_plan`): hash
tables and their optimiser state, the voxel map at its cap, a reserve for query snapshots, the
largest admitted frame's buffers, and what is left for keyframes, which sets the keyframe cap
(keyframes hold a random subset of their pixels).
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from h3edge.api import DecoderRuntime, DistanceSample, DistanceSlice, InferenceConfig, Mapper, MapSettings, MapSnapshot
from h3edge.api import warm_up as warm_up_kernels
from h3edge.errors import InputError, QueryError
from h3edge.io.protocol import (
    FrameMessage,
    FrameTooLarge,
    ProtocolError,
    check_map_id,
    decode_frame,
    encode_frame,
)
from h3edge.io.ros import RosConfig, extrinsic_matrix
from h3edge.mapping.memory_plan import keyframe_bytes, memory_plan
from h3edge.profiling.timing import DurationLog
from h3edge.serving.association import PoseBuffer
from h3edge.serving.checkpointing import EXPORTS_DIR, Checkpointer
from h3edge.serving.ingest import Ingest, PendingFrame
from h3edge.serving.queries import MeshRequest, NamedRequest, RenderRequest, SdfRequest, SliceRequest
from h3edge.serving.ros_ingest import RosIngest

log = logging.getLogger(__name__)
MAX_ERROR_CHARS = 400  # characters of a refused message's error text kept in the status and the log


@dataclass(frozen=True)
class ServiceConfig:
    map_id: str = "default"
    """the map's name: its zenoh keys (h3edge/<map_id>/...) and its folder under state_dir"""
    world_frame: str = "world"
    """the name of the frame the robot's poses, and so the map, are in (what a fleet's status lists beside the map)"""
    site_from_world: str = ""
    """where this map's world frame lies in the site frame a fleet shares, "x y z qx qy qz qw" (metres; the world
    frame's origin and orientation in the site frame) or "" (the world frame is the site frame): fleet queries
    (:mod:`h3edge.serving.fleet`) transform their site-frame points into this map with it"""
    fleet_checkpoints: bool = False
    """publish every checkpoint written on h3edge/<map_id>/checkpoint (1 MiB chunks, then a manifest) for a fleet
    keeper on another host (h3edge fleet keep, or a zenoh storage) to keep; serve --resume-from-fleet fetches it back"""
    state_dir: str = "/var/lib/h3edge"
    """checkpoints (systemd's StateDirectory)"""
    checkpoint_interval_s: float = 60.0
    """0: only on save and on stop"""
    ingest_queue: int = 2
    """frames waiting for the mapper; when full the oldest is dropped"""
    pose_wait_s: float = 0.3
    """how long a frame waits for a pose after its timestamp"""
    pose_max_gap_s: float = 0.1
    """interpolate only between poses at most this far apart"""
    pose_buffer: int = 4096
    """poses kept for association"""
    pose_max_speed: float = 20.0
    """m/s: two poses implying more are not interpolated between (an outlier)"""
    max_future_s: float = 2.0
    """s: frames and poses stamped further ahead of this host's clock are refused (future_timestamp / future_pose); a
    frame stamped ahead within it makes later frames stale for at most this long (clocks: NTP or PTP)"""
    memory_budget_mb: int = 2048
    """the map's memory (tables, voxels, keyframes, query snapshots)"""
    max_frame_pixels: int = 1920 * 1080
    """frames with more pixels are refused (frame_too_large) before decoding; the memory plan holds the decode and
    per-frame buffers of one frame this size"""
    snapshot_max_age_s: float = 2.0
    """a query reuses a map copy this young"""
    max_mesh_resolution: int = 10
    """marching-cubes cells per voxel edge allowed in a query"""
    max_query_points: int = 1_000_000
    """points in one signed-distance query"""
    max_slice_cells: int = 4_000_000
    """cells in one occupancy / distance slice (2000 x 2000)"""
    query_timeout_s: float = 60.0
    """longest a query waits for the mapper thread's map copy"""
    query_deadline_s: float = 30.0
    """a heavy query (mesh, render, save) still queued after this long gets a deadline error reply"""
    max_named_files: int = 32
    """named saves (maps/) and exports (exports/) kept at most, each: a save or export under a new name beyond it is
    refused (a name already there is overwritten), so that requests cannot fill the disk"""
    save_min_interval_s: float = 10.0
    """save requests closer together than this are refused"""
    live_interval_s: float = 1.0
    """live outputs for viewers (serving/live.py): status, new poses, the latest frame and the mesh of the blocks that
    changed, every live_interval_s (0: off)"""
    live_block_voxels: int = 8
    """leaf voxels per edge of a live mesh block"""
    live_max_blocks: int = 64
    """block meshes per update (the rest go in the next)"""
    live_frame_width: int = 320
    """the latest frame's thumbnail width"""
    live_refresh_s: float = 60.0
    """every block's mesh is rebuilt at least this often (0: only on changes)"""
    timings_log_mb: int = 64
    """<state_dir>/<map_id>/timings.jsonl (every duration), rotated to .1 past this"""


# --------------------------------------------------------------------------------- service
class MapService:
    def __init__(self, settings: MapSettings, cfg: ServiceConfig = ServiceConfig(), profile_name: str = "",
                 resume: bool = False, inference: InferenceConfig = InferenceConfig(), ros: RosConfig | None = None):
        """``ros``: also take ROS 2 topics (:class:`~h3edge.serving.ros_ingest.RosIngest`); ValueError
        when its configuration is incomplete (no extrinsic)."""
        self.settings, self.cfg, self.profile_name = settings, cfg, profile_name
        self.inference = inference
        self.plan = memory_plan(settings, cfg.memory_budget_mb, keyframe_bytes(settings, cfg.max_frame_pixels),
                                cfg.max_frame_pixels, cfg.ingest_queue)
        if not self.plan["fits"]:
            log.warning("memory budget %d MB leaves little for keyframes: %s", cfg.memory_budget_mb, self.plan)
        kf = dataclasses.replace(settings.keyframes, max_bytes=min(
            settings.keyframes.max_bytes or 1 << 62, self.plan["keyframe_cap_bytes"]))
        self.settings = dataclasses.replace(settings, keyframes=kf)
        check_map_id(cfg.map_id)  # one file name under the state directory, one zenoh key chunk
        # this map's world frame in the fleet's site frame (4x4)
        self.site_from_world = (extrinsic_matrix(cfg.site_from_world, "site_from_world") if cfg.site_from_world
                                else np.eye(4))
        self.state_dir = Path(cfg.state_dir)
        self.run_dir = self.state_dir / cfg.map_id  # checkpoint, profile.json, timings.jsonl
        self.mapper = Mapper(self.settings, profile=profile_name)
        self.checkpoints = Checkpointer(self.run_dir, cfg.map_id, profile_name, self.settings, self.mapper.timings,
                                        self._error, after_write=self._write_profile)
        # one set of onnxruntime sessions for every snapshot; TensorRT engines cached with the map
        self.decoders = (DecoderRuntime(inference, cache_dir=self.run_dir / "trt_cache")
                         if inference.decoders == "onnx" else None)
        self.poses = PoseBuffer(cfg.pose_buffer, cfg.pose_max_gap_s, cfg.pose_max_speed)
        self.resumed_from: dict | None = None
        # training on a thread of its own, apart from integration (the profile's
        # mapper.train_between_frames); without it each frame trains inline (the paper's iterations)
        # and the map copies are handed out between those steps
        self.background_training = self.settings.mapper.train_between_frames
        if not self.background_training:
            self.mapper.on_step = self._serve_requests
        if resume:
            resumed, self.resumed_from = self.checkpoints.resume()
            if resumed is not None:
                self.mapper.replace_map(resumed)
                self._check_clock()
        self.ingest = Ingest(cfg.ingest_queue, cfg.max_future_s, self.poses, self.mapper.timings, self._error)
        self.ros = (RosIngest(ros, self.ingest.submit_frame, self.ingest.add_pose, self._error, cfg.max_frame_pixels)
                    if ros is not None else None)
        self.durations: DurationLog | None = None
        try:
            self.durations = DurationLog(self.run_dir / "timings.jsonl", cfg.timings_log_mb << 20)
            self.mapper.timings.sink = self.durations
        except OSError as e:
            log.error("no timing log in %s: %s", self.run_dir, e)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._view_requests: list[Future] = []
        self._save_requests: list[tuple[Future, Path | None]] = []
        self._load_requests: list[tuple[Future, Path]] = []
        self._req_lock = threading.Lock()
        self._last_write_request: dict[str, float] = {}  # "save" (saves and loads), "export": when last asked
        self._view: MapSnapshot | None = None
        self._view_time = 0.0
        self._drops = collections.Counter()  # service-level frame drop reasons
        self._recent_mapped: collections.deque[float] = collections.deque(maxlen=300)
        self._delays: collections.deque[float] = collections.deque(maxlen=300)
        self._iteration_log: collections.deque[tuple[float, int, int]] = collections.deque(maxlen=2000)
        self.last_error: dict | None = None
        self.latest_frame: FrameMessage | None = None  # the last mapped frame, with its pose (live view)
        self._mapped_poses: collections.deque[tuple[int, np.ndarray]] = collections.deque(maxlen=10_000)
        self._changed_voxels: list[np.ndarray] = []  # (N, 3) voxels changed, collected with each map copy
        if self.resumed_from and self.resumed_from["fallback"]:
            self._error("checkpoint_fallback", "resumed from the previous checkpoint: "
                        + "; ".join(self.resumed_from["skipped"]))
        self.heartbeat = time.monotonic()
        self.started = time.time()
        self._stats = self._collect_stats()
        # the checkpoint's counts: status reports this process's frames (received, mapped, dropped
        # since start, so mapped + dropped never exceeds received) beside the map's total
        self._mapped_at_start = self.mapper.frames_mapped
        self._dropped_at_start = self.mapper.dropped

    # ---------------------------------------------------------------- lifecycle
    def warm_up(self) -> float:
        """Run every kernel once (:func:`h3edge.api.warm_up`: a throwaway small map, its decoders on
        this service's runtime), so that loading compiled code is start-up cost, not the first
        frame's or query's. Seconds."""
        return warm_up_kernels(self.settings, self.decoders)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="h3edge-mapper", daemon=True)
        self._thread.start()
        if self.background_training:
            self.mapper.start_training(on_error=self._training_error)

    def stop(self, checkpoint: bool = True, timeout: float = 60.0) -> bool:
        """Stop mapping (the frame in progress finishes), write a final checkpoint; False when that
        checkpoint was asked for and failed."""
        self._stop.set()
        self.ingest.wake()
        self.mapper.stop_training(timeout)
        if self._thread is not None:
            self._thread.join(timeout)
        self.checkpoints.join(timeout)
        ok = True
        if checkpoint and not self.mapper.empty:
            ok = self.checkpoints.write(self.checkpoints.capture(self.mapper))
        else:
            self._write_profile()
        if self.durations is not None:
            self.durations.close()
        for fut in self._view_requests + [f for f, _ in self._save_requests + self._load_requests]:
            if not fut.done():
                fut.set_exception(QueryError("service stopping"))
        return ok

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # ------------------------------------------------------------------ ingest
    def submit_frame(self, data: bytes) -> None:
        """Queue a raw frame message (called from the transport's thread; never blocks)."""
        self.ingest.submit_frame(data)

    def submit_pose(self, data: bytes) -> None:
        """Parse and buffer a pose message (called from the transport's thread; never raises)."""
        self.ingest.submit_pose(data)

    def _training_error(self, e: Exception) -> None:
        self._error("internal_error", f"training step: {type(e).__name__}: {e}")

    def _check_clock(self) -> None:
        """A map loaded with its newest stamp beyond the host clock's future tolerance (saved before
        the tolerance was seconds, or on a host whose clock was ahead) would make every frame stale
        until that time: its stamp bound is forgotten, with a warning."""
        last = self.mapper.last_timestamp
        if last is not None and last > time.time() + self.cfg.max_future_s:
            log.warning("the loaded map's newest frame is stamped %.0f s ahead of this host's clock: forgetting it, "
                        "so that frames stamped now map", last - time.time())
            self.mapper.forget_last_timestamp()

    def _error(self, code: str, text: str) -> None:
        """Record a refused message (``last_error`` in the status) and log it, the text cut to
        ``MAX_ERROR_CHARS``: a message quotes what it refused (a frame id, a stamp), which a
        hostile sender makes as long as it likes."""
        text = text if len(text) <= MAX_ERROR_CHARS else f"{text[:MAX_ERROR_CHARS]}... ({len(text)} characters)"
        self.last_error = {"code": code[:64], "message": text, "unix": time.time()}
        log.warning("%s: %s", code[:64], text)

    # ------------------------------------------------------------ mapper thread
    def _run(self) -> None:
        log.info("mapper thread up (%s, map %r)", self.mapper.device, self.cfg.map_id)
        while not self._stop.is_set():
            self.heartbeat = time.monotonic()
            self._serve_requests()
            item = self.ingest.pop()
            if item is None:  # no frame waiting (the training thread trains meanwhile)
                self._note_iterations()
                self.ingest.wait(0.05, self._stop)
            else:
                try:
                    self._handle(item)
                except Exception as e:  # a bug must not take the service down: log, count, go on
                    log.exception("frame failed")
                    self._drops["internal_error"] += 1
                    self._error("internal_error", f"{type(e).__name__}: {e}")
                self._stats = self._collect_stats()
                self._note_iterations()
            self._maybe_checkpoint()
        self._serve_requests()
        log.info("mapper thread stopped")

    def _maybe_checkpoint(self) -> None:
        if self.checkpoints.due(self.mapper, self.cfg.checkpoint_interval_s):
            self.checkpoints.write_async(self.checkpoints.capture(self.mapper))

    def _note_iterations(self) -> None:
        """Record (time, iterations so far) for the status's training rate."""
        it = self.mapper.iterations
        self._iteration_log.append((time.monotonic(), it["frame"], it["between_frames"]))

    def training_rate(self, window_s: float = 10.0) -> dict:
        """Optimisation steps per second over the last ``window_s``, the share of them that ran
        between frames (on the training thread), and the training steps that failed."""
        now = time.monotonic()
        log_ = [e for e in list(self._iteration_log) if now - e[0] <= window_s]
        it = self.mapper.iterations
        out = {"iterations": it, "iterations_per_s": 0.0, "between_frames_share": None,
               "errors": self.mapper.training_errors}
        if len(log_) >= 2:
            dt = log_[-1][0] - log_[0][0]
            d_frame, d_idle = log_[-1][1] - log_[0][1], log_[-1][2] - log_[0][2]
            if dt > 0:
                out["iterations_per_s"] = round((d_frame + d_idle) / dt, 2)
            if d_frame + d_idle:
                out["between_frames_share"] = round(d_idle / (d_frame + d_idle), 3)
        return out

    def _handle(self, item: PendingFrame) -> None:
        self.mapper.timings.add("queue_wait", time.monotonic() - item.received)
        t0 = time.perf_counter()
        try:
            msg = decode_frame(item.data, self.cfg.max_frame_pixels)
        except FrameTooLarge as e:
            self._drops["frame_too_large"] += 1
            self._error("frame_too_large", str(e))
            return
        except ProtocolError as e:
            self._drops["malformed"] += 1
            self._error("malformed", str(e))
            return
        if self.ingest.from_future(msg.timestamp_ns):
            self._drops["future_timestamp"] += 1
            self._error("future_timestamp", f"frame {msg.frame_id} stamped {msg.timestamp_ns} ns, more than "
                                            f"{self.cfg.max_future_s:g} s ahead of this host's clock")
            return
        pose = msg.pose
        t_assoc = time.perf_counter()
        if pose is None:
            while True:
                state, value = self.poses.lookup(msg.timestamp_ns)
                if state == "ok":
                    pose = value
                    break
                if state == "miss" or time.monotonic() - item.received > self.cfg.pose_wait_s or self._stop.is_set():
                    self._drops["no_pose"] += 1
                    self._error("no_pose", f"frame {msg.frame_id}: " + (value or "no pose arrived in time"))
                    return
                self._serve_requests()
                time.sleep(0.005)
        self.mapper.timings.add("association", time.perf_counter() - t_assoc)
        try:
            result = self.mapper.add_frame(msg.color, msg.depth, pose, msg.intrinsics, msg.timestamp,
                                           train=not self.background_training, frame_id=msg.frame_id,
                                           decode_seconds=t_assoc - t0)
        except InputError as e:  # a frame the library refuses as input (shape, dtype, intrinsics): counted
            self._drops["malformed"] += 1
            self._error("malformed", f"frame {msg.frame_id}: {e}")
            return
        if result.mapped:
            with self._req_lock:
                self._mapped_poses.append((msg.timestamp_ns, np.asarray(pose, np.float64)))
            self.latest_frame = dataclasses.replace(msg, pose=np.asarray(pose, np.float64))
            now = time.monotonic()
            self._recent_mapped.append(now)
            self._delays.append(now - item.received)
            self.mapper.timings.add("frame_delay", now - item.received)  # arrival to mapped
        else:
            self._error("dropped", f"frame {msg.frame_id}: {result.reason}")

    # ----------------------------------------------------------- snapshot / save
    def _serve_requests(self) -> None:
        """On the mapper thread, between training steps: hand out map copies, capture saves."""
        self.heartbeat = time.monotonic()
        with self._req_lock:
            views, saves, loads = list(self._view_requests), list(self._save_requests), list(self._load_requests)
            self._view_requests.clear()  # cleared in place: _ask holds these lists
            self._save_requests.clear()
            self._load_requests.clear()
        for fut, path in loads:  # first: a copy or save asked after a load sees the loaded map
            self._load_now(fut, path)
        if views or saves:
            with self.mapper.exclusive():  # no training step while the map is copied
                self._copy_for(views, saves)

    def _copy_for(self, views: list[Future], saves: list[tuple[Future, Path | None]]) -> None:
        """Hand ``views`` a frozen map copy and capture the map for ``saves`` (under the map lock)."""
        if views:
            try:
                if self.mapper.empty:
                    raise QueryError("nothing mapped yet")
                view = self.mapper.snapshot(self.decoders)
                self._view, self._view_time = view, time.monotonic()
                with self._req_lock:
                    self._changed_voxels.append(self.mapper.take_changed_voxels())
                    if len(self._changed_voxels) > 64:
                        self._changed_voxels = [np.unique(np.concatenate(self._changed_voxels), axis=0)]
                for f in views:
                    f.set_result(view)
            except Exception as e:
                for f in views:
                    f.set_exception(e if isinstance(e, QueryError) else QueryError(f"snapshot failed: {e}"))
        if saves:
            if self.mapper.empty:
                for f, _ in saves:
                    f.set_exception(QueryError("nothing mapped yet"))
            else:
                captured = self.checkpoints.capture(self.mapper)
                for path in {p for _, p in saves}:
                    self.checkpoints.write_async(captured, [f for f, p in saves if p == path], path)

    def _load_now(self, fut: Future, path: Path) -> None:
        """On the mapper thread: replace the map with the one saved in ``path``; the running map is
        kept when that fails."""
        try:
            mapper, header = self.checkpoints.read_mapper(path)
        except Exception as e:  # noqa: BLE001 - any unusable file is the requester's error, not the map's
            fut.set_exception(QueryError(f"load {path.name}: {e}"))
            return
        old = self.mapper  # this process's counts go on across the swap
        with old.exclusive():  # no frame or training step between the counts and the swap
            for k, v in old.dropped.items():
                if v > self._dropped_at_start.get(k, 0):
                    self._drops[k] += v - self._dropped_at_start.get(k, 0)
            self._mapped_at_start = mapper.frames_mapped - (old.frames_mapped - self._mapped_at_start)
            self._dropped_at_start = mapper.dropped
            old.replace_map(mapper)
            self._check_clock()
        self._view, self._view_time = None, 0.0
        self._stats = self._collect_stats()
        voxels = self._stats.get("voxels", 0)
        log.info("loaded map from %s: %d frames, %d voxels", path, self.mapper.frames_mapped, voxels)
        fut.set_result({"path": str(path), "frames_mapped": self.mapper.frames_mapped, "voxels": voxels,
                        "created_unix": header.get("created_unix")})

    def _ask(self, requests: list, arg: object = ...) -> object:
        """Queue a request (with ``arg`` when given) for the mapper thread and wait for its answer
        (served here when no mapper thread runs)."""
        fut: Future = Future()
        with self._req_lock:
            requests.append(fut if arg is ... else (fut, arg))
        self.ingest.wake()
        if not self.alive:
            self._serve_requests()
        return fut.result(self.cfg.query_timeout_s)

    def take_mapped_poses(self) -> list[tuple[int, np.ndarray]]:
        """(stamp ns, camera pose) of the frames mapped since the last call."""
        with self._req_lock:
            out = list(self._mapped_poses)
            self._mapped_poses.clear()
        return out

    def take_changed_voxels(self) -> np.ndarray:
        """Integer coordinates (N, 3) of the voxels the mapped frames changed, up to the newest map
        copy, since the last call (:meth:`h3edge.Mapper.take_changed_voxels`)."""
        with self._req_lock:
            parts, self._changed_voxels = self._changed_voxels, []
        return np.unique(np.concatenate(parts), axis=0) if parts else np.zeros((0, 3), np.int64)

    def view(self) -> MapSnapshot:
        """A frozen copy of the map, at most ``snapshot_max_age_s`` old."""
        if self._view is not None and time.monotonic() - self._view_time < self.cfg.snapshot_max_age_s:
            return self._view
        return self._ask(self._view_requests)

    def save(self, request: NamedRequest = NamedRequest(None, "ply")) -> dict:
        """Checkpoint now: the resume checkpoint, or ``<state>/<map>/maps/<name>.h3ckpt`` (which
        ``load`` reads back). At most one save per ``save_min_interval_s`` (QueryError otherwise)."""
        path = self.checkpoints.named_path(request.name) if request.name else None
        if path is not None:
            self.checkpoints.check_room(path, self.cfg.max_named_files)
        self._admit_save("save")
        return self._ask(self._save_requests, path)

    def _admit_save(self, what: str) -> None:
        """Count a save or load (one budget), or an export (another), against ``save_min_interval_s``;
        QueryError when one came too soon."""
        now = time.monotonic()
        gap = self.cfg.save_min_interval_s
        kind = "export" if what == "export" else "save"
        with self._req_lock:
            last = self._last_write_request.get(kind)
            if last is not None and now - last < gap:
                asked = "export" if kind == "export" else "save / load"
                raise QueryError(f"{what} refused: the last {asked} was asked {now - last:.1f} s ago; "
                                 f"at most one per {gap:g} s (retry after {gap - (now - last):.1f} s)")
            self._last_write_request[kind] = now

    def load(self, request: NamedRequest) -> dict:
        """Replace the running map with a saved one (``name``: ``maps/<name>.h3ckpt``; none: the
        resume checkpoint), between two training steps; counted like a save against
        ``save_min_interval_s``. The running map stays when the file cannot be used."""
        path = self.checkpoints.named_path(request.name) if request.name else self.checkpoints.path
        if not path.exists():
            raise QueryError(f"load: no saved map {path.name} under {path.parent}")
        self._admit_save("load")
        return self._ask(self._load_requests, path)

    def export_mesh(self, request: NamedRequest) -> dict:
        """Write the whole map's mesh to ``<state>/<map>/exports/<name>.<format>``; its path and size.
        Counted like a save against ``save_min_interval_s`` and ``max_named_files``."""
        path = self.checkpoints.named_path(request.name, EXPORTS_DIR, "." + request.format)
        self.checkpoints.check_room(path, self.cfg.max_named_files)
        self._admit_save("export")
        data = self.mesh(MeshRequest(request.format, self.settings.mapper.mesh_resolution, None))
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_bytes(data)
        tmp.replace(path)
        return {"path": str(path), "bytes": len(data)}

    def signed_distance(self, request: SdfRequest) -> DistanceSample:
        """Signed distance, state and gradient at the request's points (:mod:`h3edge.mapping.distance`)."""
        view = self.view()
        t0 = time.perf_counter()
        out = view.signed_distance(request.points, request.gradient)
        self.mapper.timings.add("sdf_query", time.perf_counter() - t0)
        return out

    def slice(self, request: SliceRequest) -> DistanceSlice:
        """Occupancy and distance images at a height (:mod:`h3edge.mapping.distance`)."""
        view = self.view()
        t0 = time.perf_counter()
        out = view.slice(request.z, request.lo, request.hi, request.resolution)
        self.mapper.timings.add("slice_query", time.perf_counter() - t0)
        return out

    def _write_profile(self) -> None:
        """``profile.json`` beside the checkpoint (``h3edge profile report <state_dir>/<map_id>``) and
        the timing log flushed: with every checkpoint and at stop. Failures are logged only."""
        try:
            doc = self.profile()
            doc.pop("table", None)
            tmp = self.run_dir / "profile.json.tmp"
            tmp.write_text(json.dumps(doc, indent=1) + "\n")
            tmp.replace(self.run_dir / "profile.json")
        except Exception as e:  # noqa: BLE001 - an auxiliary file: it never fails a checkpoint or a stop
            log.error("cannot write %s: %s", self.run_dir / "profile.json", e)
        if self.durations is not None:
            self.durations.flush()

    # ----------------------------------------------------------------- queries
    def _collect_stats(self) -> dict:
        s = self.mapper.stats() if not self.mapper.empty else {
            "frames_mapped": self.mapper.frames_mapped, "dropped": self.mapper.dropped, "voxels": 0,
            "keyframes": 0, "memory_bytes": {}}
        return s

    def status(self) -> dict:
        now = time.monotonic()
        s = self._stats
        dropped = dict(self._drops + self.ingest.frame_drops)
        for k, v in s.get("dropped", {}).items():
            v -= self._dropped_at_start.get(k, 0)
            if v:
                dropped[k] = dropped.get(k, 0) + v
        frames_dropped = sum(dropped.values())  # frames only: mapped + dropped never exceeds received
        for k, v in self.ingest.pose_drops.items():
            dropped[k] = dropped.get(k, 0) + v

        def rate(ts: collections.deque) -> float:
            recent = [t for t in list(ts) if now - t < 10.0]
            return round(len(recent) / 10.0, 2)

        delays = list(self._delays)
        last_mapped = self._recent_mapped[-1] if self._recent_mapped else None
        return {"map_id": self.cfg.map_id, "world_frame": self.cfg.world_frame,
                "site_from_world": self.site_from_world.tolist(), "profile": self.profile_name,
                "device": str(self.mapper.device),
                "last_frame_age_s": None if last_mapped is None else round(now - last_mapped, 1),
                "inference": self.inference_info(),
                "uptime_s": round(time.time() - self.started, 1),
                "frames": {"received": self.ingest.counts["frames_received"],
                           "mapped": s.get("frames_mapped", 0) - self._mapped_at_start,
                           "dropped": frames_dropped, "queued": len(self.ingest)},
                "dropped": dropped, "poses": {"received": self.ingest.counts["poses_received"],
                                              "buffered": len(self.poses),
                                              "dropped": sum(self.ingest.pose_drops.values())},
                "rates_hz": {"received": rate(self.ingest.recent_received), "mapped": rate(self._recent_mapped)},
                "delay_s": {"median": round(float(np.median(delays)), 3) if delays else None},
                "training": self.training_rate(),
                "map": {k: s.get(k) for k in ("frames_mapped", "voxels", "voxels_refused", "vertices", "keyframes",
                                              "keyframes_pruned", "keyframes_evicted", "texture_classes",
                                              "residual_gain", "bounds")},
                "memory": {"parts_bytes": s.get("memory_bytes", {}),
                           "total_bytes": int(sum(s.get("memory_bytes", {}).values())),
                           "budget_bytes": self.plan["budget"], "plan": self.plan},
                "last_error": self.last_error, "last_checkpoint": self.checkpoints.last,
                "resumed_from": self.resumed_from, "mapper_alive": self.alive,
                **({"ros": self.ros.status()} if self.ros is not None else {})}

    def inference_info(self) -> dict:
        """What queries run on: the mapping device and the decoders' runtime and providers."""
        info = {"mapping_device": str(self.mapper.device), "decoders": self.inference.decoders}
        return {**info, **(self.decoders.describe() if self.decoders is not None else {})}

    def profile(self) -> dict:
        """The timing profile document (:mod:`h3edge.profiling.report`) plus a markdown table."""
        from h3edge.profiling.report import profile_document
        from h3edge.profiling.timing import format_timings

        summary = self.mapper.timings.summary()
        n = self.mapper.frames_mapped
        st = self.status()
        doc = profile_document(self.profile_name, str(self.mapper.device), n, summary,
                               st["memory"]["parts_bytes"], st["dropped"], self.inference_info())
        doc["table"] = format_timings(summary, f"per-component timings ({self.profile_name}, {self.mapper.device})",
                                      frames=n)
        return doc

    def mesh(self, request: MeshRequest) -> bytes:
        """The mesh file of the map (or of ``request.aabb``), refused when its scratch would exceed
        the query budget."""
        res, box, fmt = request.resolution, request.aabb, request.format
        view = self.view()
        need, fill = view.mesh_scratch_bytes(res, box), True
        if need > self.plan["query_working_set"]:
            # the colour base's surface in the cubes without evidence is what a mesh can do without (D53-9)
            need, fill = view.mesh_scratch_bytes(res, box, fill=False), False
            log.info("mesh query: the base's fill left out, over the %d MB query budget",
                     self.plan["query_working_set"] >> 20)
        if need > self.plan["query_working_set"]:
            raise QueryError(f"a mesh at resolution {res} of this region needs ~{need >> 20} MB of scratch, over this "
                             f"service's {self.plan['query_working_set'] >> 20} MB query budget: use a lower "
                             f"resolution or an aabb")
        t0 = time.perf_counter()
        mesh = view.mesh(res, box, fill=fill)
        self.mapper.timings.add("mesh", time.perf_counter() - t0)
        if len(mesh.faces) == 0:
            raise QueryError("the map has no surface yet" + (" inside that aabb" if box is not None else ""))
        return mesh.export(file_type=fmt)

    def render(self, request: RenderRequest) -> bytes:
        """A frame message (PNG colour, 16-bit PNG depth in mm, the pose) rendered at a pose."""
        intr, pose, raw = request.intrinsics, request.pose, request.raw
        view = self.view()
        t0 = time.perf_counter()
        rgb, depth = view.render(intr, pose)
        self.mapper.timings.add("render", time.perf_counter() - t0)
        msg = FrameMessage(int(time.time() * 1e9), view.frames_mapped, rgb, depth, intr, pose, "render")
        return encode_frame(msg, "raw_rgb8" if raw else "png", "raw_f32" if raw else "png16", 1000.0)
