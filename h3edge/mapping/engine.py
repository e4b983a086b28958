"""The mapping engine behind :class:`h3edge.Mapper` (the library's façade, which users call) and the
service: owns the voxel map, the field, the optimisers and the keyframe set, and turns a stream of
posed RGB-D frames into a map you can mesh and render (Sec. IV).

Integration (:meth:`MapEngine.integrate`, every frame that arrives; timed per component, the paper's
Table I names): validate and clean the frame (``read``); allocate leaf voxels and initialise their
SDF priors (``priors``); mark free space and the fine free-space votes; fuse its colours into the
colour base (``color_base``, :mod:`h3edge.mapping.color_base`); every ``update_interval`` frames,
determine the voxels' texture patterns and refresh the texture encoder's warps (``texture``);
decide keyframe insertion, scored by the colour gradient (``keyframes``); free space and the colour
base on a helper thread beside the rest (D53-6). A bad frame is dropped with a reason (logged and
counted); it never touches the map.

Training (:meth:`MapEngine.train_between_frames`): one optimisation step on ``rays_per_iteration``
rays drawn evenly from the selected keyframes and the newest integrated frame no step has used yet
(``idle_training``). The service and the live replay run it back to back on a thread of their own
(:class:`~h3edge.mapping.background.BackgroundTraining`), apart from integration: a step holds the
map lock (:meth:`MapEngine.exclusive`, which integration takes first) only to draw its rays and to
apply its updates, and its forward and backward passes run beside integration, so a frame waits at
most for one of those and training never waits for a frame.

The paper's protocol (:meth:`MapEngine.process`): integrate, then ``iterations`` steps on the frame and
the keyframes selected for each (``training``), one frame after the other.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from h3edge.geometry.camera import Intrinsics, backproject, pixel_rays_camera, rigid_error
from h3edge.geometry.depth_edges import discontinuity_jump, near_side_of_edges
from h3edge.io.sequence import Frame
from h3edge.mapping.cell_votes import CellVotes, VoteConfig
from h3edge.mapping.color_base import ColorBase, ColorBaseConfig
from h3edge.mapping.device_frames import DeviceFrame
from h3edge.mapping.field import Field, FieldConfig
from h3edge.mapping.free_space import FreeSpace, FreeSpaceConfig
from h3edge.mapping.gradient import color_gradient
from h3edge.mapping.hashgrid import HashGrid
from h3edge.mapping.keyframes import (
    KeyframeConfig,
    KeyframeSet,
    StoredFrame,
    edge_pixels,
    gradient_scores,
)
from h3edge.mapping.losses import LossWeights
from h3edge.mapping.raymarch import MapRenderer, RenderConfig, floor_window_weight
from h3edge.mapping.residual_check import PROBE_EVERY, RESCORE_STEPS, ResidualCheck, ResidualProbe, take_probe
from h3edge.mapping.texture_grid import QuasiHeteroTexture
from h3edge.mapping.texture_patterns import TextureConfig, TexturePatterns
from h3edge.mapping.threads import size_pools
from h3edge.mapping.trainer import RayBatch, TrainConfig, Trainer
from h3edge.mapping.training_stream import TrainingStream
from h3edge.mapping.view import MapView
from h3edge.mapping.voxels import PriorAdam, VoxelConfig, VoxelMap, pack, unpack
from h3edge.profiling.timing import Timings

log = logging.getLogger(__name__)
RAY_TABLES = 4  # camera ray tables kept (keyframes from a few cameras / intrinsics)
STATE_VERSION = 2  # of MapEngine.state_dict (2: keyframes keep whole images)
# states this build still reads; from version 1 (keyframes kept a fixed pixel subset) the map is
# taken and the keyframes are dropped: new frames rebuild the set
READABLE_STATE_VERSIONS = (1, 2)


@dataclass(frozen=True)
class MapperConfig:
    device: str = "auto"
    """auto (CUDA when available) | cpu | cuda"""
    iterations: int = 2
    """optimisation steps per frame (paper)"""
    rays_per_iteration: int = 8192
    """paper"""
    extent: float = 12.8
    """m, side of the hash grids' reference cube, centred on the first camera: it sets the grids' cell sizes and where
    their coarse levels are dense; the map itself extends anywhere"""
    max_position: float = 1000.0
    """m, farthest camera position from the world origin that is mapped (float32 coordinates keep sub-millimetre
    precision within it; a pose beyond is refused as bad_pose)"""
    min_depth: float = 0.01
    """m, valid depth range (authors: (0.01, 10))"""
    max_depth: float = 10.0
    """m, farthest valid depth (authors: 10 m); farther pixels are dropped"""
    min_valid_fraction: float = 0.01
    """frames with less valid depth are dropped"""
    edge_radius: int = 0
    """px: depth pixels with a neighbour within this radius farther by more than edge_jump are left out (flying and
    foreground-fattened pixels, :mod:`h3edge.geometry.depth_edges`); paper 0 (every pixel); D0-2"""
    edge_jump: float = 0.05
    """relative depth jump within edge_radius pixels that makes a depth edge (0.05: 5 % of the depth)"""
    edge_max_incidence: float = 80.0
    """degrees of incidence up to which a surface's steady depth change is not an edge: at a wide pixel angle the jump
    is raised to match (:func:`~h3edge.geometry.depth_edges.discontinuity_jump`; 160x120 at 95 px focal: 5 % -> 12 %,
    which keeps the 32 % of a tiny room's pixels the 5 % test dropped; 640x480 Kinect or Replica frames keep 5 %)"""
    edge_rays: float = 0.0
    """share of each frame's training rays drawn on the far side of its depth edges (rays beside a silhouette or
    through a gap); paper 0 (uniform among valid pixels); D0-2"""
    edge_rays_radius: int = 8
    """pixels beside a depth edge whose rays count as edge rays (edge_rays)"""
    edge_rays_near_too: bool = False
    """edge rays also on the near side (the foreground within edge_rays_radius of its outline); paper: none; D0-2"""
    observe_stride: int = 4
    """pixel stride when listing the voxels a frame observes (keyframe policy)"""
    mesh_resolution: int = 8
    """marching-cubes cells per voxel edge; authors 8 (1.25 cm at 10 cm voxels)"""
    mesh_min_support: float = 0.0
    """share of each mesh cube's trilinear weight that must lie on vertices whose prior a frame set (and within
    voxels.observed_behind of a seen surface), else the cube shows the colour base's fused surface if any (D53-9);
    authors 0 (every allocated voxel); D0-3"""
    train_between_frames: bool = False
    """train on a thread of its own, every frame integrated as it comes (false: each frame trains inline with
    ``iterations`` steps); paper false (per-frame mapping); D53-1"""
    threads: int = 0
    """CPU threads of the mapper's torch and numba pools (0: every core; :mod:`h3edge.mapping.threads`); fewer leave
    cores to the rest of the robot; paper: not stated"""
    training_nice: int = 2
    """nice levels the background training thread runs below the integrating thread (Linux; 0..19): when both want a
    core, a frame's integration gets it; 0: equal; paper: none (it trains inline); D53-6"""
    seed: int = 0
    """seed of the mapper's random draws (rays, keyframe picks, sampling): the same frames map the same"""

    def __post_init__(self) -> None:
        if not 0.0 <= self.edge_rays <= 1.0:
            raise ValueError(f"edge_rays is a share of the rays, in [0, 1], got {self.edge_rays}")
        if not 0.0 <= self.edge_max_incidence < 90.0:
            raise ValueError(f"edge_max_incidence must be in [0, 90) degrees, got {self.edge_max_incidence}")
        if self.observe_stride < 1:
            raise ValueError(f"observe_stride is a pixel stride, >= 1, got {self.observe_stride}")
        if self.threads < 0 or not 0 <= self.training_nice <= 19:
            raise ValueError(f"threads must be >= 0 (0: every core) and training_nice in [0, 19], got {self.threads} "
                             f"and {self.training_nice}")


@dataclass(frozen=True)
class MapSettings:
    """Everything the mapper is configured by (one profile's mapping sections)."""

    mapper: MapperConfig = dataclasses.field(default_factory=MapperConfig)
    voxels: VoxelConfig = dataclasses.field(default_factory=VoxelConfig)
    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)
    losses: LossWeights = dataclasses.field(default_factory=LossWeights)
    keyframes: KeyframeConfig = dataclasses.field(default_factory=KeyframeConfig)
    texture: TextureConfig = dataclasses.field(default_factory=TextureConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    free_space: FreeSpaceConfig = dataclasses.field(default_factory=FreeSpaceConfig)
    votes: VoteConfig = dataclasses.field(default_factory=VoteConfig)
    color_base: ColorBaseConfig = dataclasses.field(default_factory=ColorBaseConfig)

    def __post_init__(self) -> None:
        self.votes.cells_per_side(self.voxels.voxel_size)  # refused when the profile loads, not at the first frame
        r = self.render
        weight = floor_window_weight(r, self.field.beta)
        if r.free_floor > 0 and weight >= r.min_weight:
            raise ValueError(f"render.free_floor = {r.free_floor:g} lets a window of seen-free samples render: its "
                             f"weight {weight:.3f} reaches render.min_weight = {r.min_weight:g} "
                             f"(field.beta = {self.field.beta:g}); raise the floor")


@dataclass
class FrameResult:
    frame_id: int
    mapped: bool
    reason: str = ""  # why it was dropped
    new_voxels: int = 0
    keyframe: bool = False
    losses: dict = dataclasses.field(default_factory=dict)


@dataclass
class ImageFrame:
    """The frame being mapped: its images and valid pixels, read only where rays are drawn (no
    per-frame gather of every valid pixel)."""

    color: np.ndarray  # uint8 (H, W, 3)
    depth: np.ndarray  # float32 (H, W), cleaned
    pose: np.ndarray
    intrinsics: Intrinsics
    pix: np.ndarray  # int32 flat indices of the valid-depth pixels
    _edges: dict = dataclasses.field(default_factory=dict, repr=False)  # as StoredFrame's
    base_depth: np.ndarray | None = dataclasses.field(default=None, repr=False)  # what the colour base fuses
    _on_device: dict = dataclasses.field(default_factory=dict, repr=False)  # as StoredFrame's

    def draw(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``n`` valid pixels drawn uniformly with replacement: flat indices, colours, depths (as
        :meth:`StoredFrame.draw`)."""
        return self.at(self.pix[rng.integers(0, len(self.pix), n)])

    def at(self, pix: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`StoredFrame.at`."""
        return pix, self.color.reshape(-1, 3)[pix], self.depth.reshape(-1)[pix]

    def edge_pixels(self, radius: int, jump: float, step: int, near_too: bool = False) -> np.ndarray:
        """As :meth:`StoredFrame.edge_pixels`."""
        return edge_pixels(self._edges, self.depth, radius, jump, step, near_too)

    def store(self) -> StoredFrame:
        """What a keyframe keeps of this frame: the whole images (:class:`StoredFrame`) and the edge
        pixels found so far."""
        kept = StoredFrame.of(self.color, self.depth, self.pose, self.intrinsics)
        kept._edges.update(self._edges)
        return kept


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but CUDA is not available")
    return dev


class MapEngine:
    """The incremental H3 mapper (module docstring): integration, training steps, queries and state
    of one map. Internal: programs use :class:`h3edge.Mapper`; the service and the benchmarks drive
    this engine directly."""

    def __init__(self, settings: MapSettings = MapSettings(), bound: np.ndarray | None = None):
        self.settings = settings
        self.cfg = settings.mapper
        self.device = resolve_device(self.cfg.device)
        self.train_cfg = dataclasses.replace(settings.train, weights=settings.losses)
        self.voxels = VoxelMap(settings.voxels, self.device)
        self.keyframes = KeyframeSet(settings.keyframes)
        self.patterns = TexturePatterns(settings.texture)
        self.free_space = FreeSpace(settings.free_space, settings.voxels.voxel_size, settings.voxels.truncation)
        self.cell_votes = CellVotes(settings.votes, settings.voxels.voxel_size, settings.train.sdf_behind,
                                    settings.voxels.max_voxels)
        self.color_base = ColorBase(settings.color_base) if settings.color_base.enabled else None
        # the gain renders apply to the colour residual over the base, scored on frames no step fits (D53-14)
        self.residual_check = (ResidualCheck(self.cfg.seed)
                               if self.color_base is not None and settings.render.checked_residual else None)
        # keys of the voxels allocated or observed since the last take_changed_keys() (live mesh updates)
        self._changed: list[np.ndarray] = []
        self.timings = Timings()
        self.bound = None if bound is None else np.asarray(bound, np.float64)
        self.field: Field | None = None
        self.optimizer: torch.optim.Optimizer | None = None
        self.trainer: Trainer | None = None  # built with the field
        self.prior_opt = PriorAdam(settings.train.lr)
        self.rng = np.random.default_rng(self.cfg.seed)
        self.generator = torch.Generator(device=self.device).manual_seed(self.cfg.seed)
        self.frames_mapped = 0
        self.dropped: dict[str, int] = {}
        self.last_timestamp: float | None = None
        self.iterations = {"frame": 0, "between_frames": 0}  # optimisation steps, by when they ran
        self._rays_cache: dict[Intrinsics, np.ndarray] = {}
        self._untrained: ImageFrame | None = None  # the newest integrated frame no step has used yet
        self._texture_pending: tuple[ImageFrame, np.ndarray] | None = None  # left for the training thread
        self._lock = threading.RLock()  # the map: integration, training steps, snapshots
        self._turns = threading.Condition()  # exclusive() callers waiting go before training steps
        self._stream = TrainingStream(self.device)  # train_once's CUDA stream; no-ops on a CPU
        self._waiting = 0
        self._helper: concurrent.futures.ThreadPoolExecutor | None = None  # integration's second track
        # called on the mapping thread after every training step: where a service hands out
        # consistent snapshots without waiting for the whole frame
        self.step_hook: Callable[[], None] | None = None
        # the field, built before the first frame and moved to its pose then (building takes ~90 ms of
        # random tables: at 30 Hz the first frame's integration would skip the next two frames)
        self._unplaced: Field | None = None
        if self.bound is not None:
            self._build_field()
        else:
            half = np.full(3, self.cfg.extent / 2)
            self._unplaced = self._new_field(np.stack([-half, half]))

    def __getstate__(self) -> dict:  # copies (tests) take the map, not its locks
        state = dict(self.__dict__)
        for k in ("_lock", "_turns", "_waiting", "_helper"):
            state.pop(k)
        state["_unplaced"] = None  # a copy builds its field where it places it
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock, self._turns, self._waiting, self._helper = threading.RLock(), threading.Condition(), 0, None

    # ----------------------------------------------------------------- set-up
    def _new_field(self, bound: np.ndarray) -> Field:
        torch.manual_seed(self.cfg.seed)
        return Field(self.settings.field, bound, self.settings.voxels.voxel_size, self.device, self.settings.texture)

    def _build_field(self) -> None:
        """The field over ``self.bound``: the one built before the first frame, moved there, where its
        reference cube has that size (the same tables either way), else a new one."""
        spare, self._unplaced = self._unplaced, None
        size = self.bound[1] - self.bound[0]
        if spare is not None and np.allclose(spare.geo_grid.bound_size.cpu().numpy(), size):
            spare.place(self.bound[0])
            self.field = spare
        else:
            self.field = self._new_field(self.bound)
        self.field.color_base = self.color_base
        # training locates its samples where the field runs: on the device with the torch backend
        self.voxels.device_lookup = self.field.geo_grid.backend == "torch"
        params = list(self.field.sdf_mlp.parameters()) + list(self.field.color_mlp.parameters())
        self.optimizer = torch.optim.Adam(params, lr=self.settings.train.lr)
        self.trainer = Trainer(self.train_cfg, self.settings.render.near, self.field, self.voxels, self.optimizer,
                               self.prior_opt, self.cell_votes if self.cell_votes.enabled else None, self.generator)

    def _camera_rays(self, intr: Intrinsics) -> np.ndarray:
        """Camera-frame ray table of ``intr``, from a cache of the ``RAY_TABLES`` most recently used
        intrinsics (each distinct intrinsics would otherwise keep a full table forever)."""
        rays = self._rays_cache.pop(intr, None)
        if rays is None:
            rays = pixel_rays_camera(intr).reshape(-1, 3).astype(np.float32)
        self._rays_cache[intr] = rays  # most recent last
        while len(self._rays_cache) > RAY_TABLES:
            del self._rays_cache[next(iter(self._rays_cache))]
        return rays

    # ------------------------------------------------------------- validation
    def check_frame(self, frame: Frame) -> tuple[str, str]:
        """(drop code, message) saying why ``frame`` cannot be mapped; ('', '') when it can."""
        intr = frame.intrinsics
        h, w = intr.height, intr.width
        if not isinstance(frame.color, np.ndarray) or frame.color.shape != (h, w, 3) or frame.color.dtype != np.uint8:
            return "bad_colour", f"colour must be uint8 ({h}, {w}, 3), got {getattr(frame.color, 'shape', None)}"
        if not isinstance(frame.depth, np.ndarray) or frame.depth.shape != (h, w):
            return "bad_depth", f"depth must be ({h}, {w}), got {getattr(frame.depth, 'shape', None)}"
        pose = np.asarray(frame.pose, np.float64)
        if pose.shape != (4, 4):
            return "bad_pose", f"pose must be 4x4, got {pose.shape}"
        err = rigid_error(pose)
        if err:
            return "bad_pose", f"pose: {err}"
        dist = float(np.linalg.norm(pose[:3, 3]))
        if dist > self.cfg.max_position:
            return "bad_pose", (f"camera {dist:.4g} m from the world origin, beyond mapper.max_position "
                                f"({self.cfg.max_position:g} m)")
        if not np.isfinite(frame.timestamp):
            return "bad_timestamp", "timestamp is not finite"
        if self.last_timestamp is not None and frame.timestamp <= self.last_timestamp:
            return "stale_timestamp", (f"timestamp {frame.timestamp:.6f} not after the last mapped "
                                       f"{self.last_timestamp:.6f} (out of order or duplicate)")
        return "", ""

    def depth_in_range(self, depth: np.ndarray) -> np.ndarray:
        """Depth float32 (H, W) metres, 0 where not finite or outside (``min_depth``, ``max_depth``)."""
        d = np.asarray(depth, np.float32)
        ok = np.isfinite(d) & (d > self.cfg.min_depth) & (d < self.cfg.max_depth)
        return np.where(ok, d, np.float32(0))

    def clean_depth(self, depth: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
        """Valid depth in range, the near side of depth edges left out (``edge_radius``)."""
        return self._edges_left_out(self.depth_in_range(depth), intrinsics)

    def _edges_left_out(self, d: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
        """``d`` (in range) with the near side of its depth edges set to 0, in place."""
        if self.cfg.edge_radius > 0:
            d[near_side_of_edges(d, self.cfg.edge_radius, self.edge_jump(intrinsics, self.cfg.edge_radius))] = 0
        return d

    def edge_jump(self, intrinsics: Intrinsics, radius: int) -> float:
        """The relative depth jump within ``radius`` pixels that is a depth edge in this camera
        (``edge_jump``, raised for wide pixels: ``edge_max_incidence``)."""
        return discontinuity_jump(self.cfg.edge_jump, radius, min(intrinsics.fx, intrinsics.fy),
                                  self.cfg.edge_max_incidence)

    def gradient_jump(self, intrinsics: Intrinsics) -> float:
        """The relative depth jump that makes a pixel an occlusion edge for the colour gradient
        (:func:`~h3edge.mapping.gradient.color_gradient`): the depth-edge jump across its 3x3
        window."""
        return self.edge_jump(intrinsics, 1)

    def _drop(self, frame: Frame, code: str, reason: str) -> FrameResult:
        self.dropped[code] = self.dropped.get(code, 0) + 1
        log.warning("frame %d dropped: %s", frame.index, reason)
        return FrameResult(frame.index, False, reason)

    # ------------------------------------------------------------------ frame
    def integrate(self, frame: Frame, read_seconds: float = 0.0, defer_texture: bool | None = None) -> FrameResult:
        """Integrate one frame into the explicit parts of the map, without training: check it,
        allocate voxels and their priors, mark free space and cell votes, fuse its colours into the
        colour base, determine texture patterns (every ``update_interval`` frames), decide keyframe
        insertion. The frame becomes the newest frame :meth:`train_between_frames` trains on until
        a step has used it.
        ``frame``: colour uint8 (H, W, 3), depth float32 (H, W) in metres, pose camera-to-world
        (OpenCV optical), host numpy arrays. ``read_seconds``: the caller's reading / decoding
        time, added to ``read``. Timed as ``integration`` (the call's own work, ``read_seconds``
        included); its wait for the map (a training step in progress on another thread) apart, as
        ``integration_wait``. ``defer_texture`` (default: ``train_between_frames``): leave a due
        texture pattern determination (tens of ms) to the next :meth:`train_between_frames` call,
        on the training thread. A dropped frame changes nothing in the map. Thread-safe against
        :meth:`train_between_frames` and :meth:`exclusive` on other threads."""
        t_frame = time.perf_counter()
        size_pools(self.cfg.threads)  # numba's count is the calling thread's
        defer_texture = self.cfg.train_between_frames if defer_texture is None else defer_texture
        code, reason = self.check_frame(frame)
        if code:
            return self._drop(frame, code, reason)
        current, pts = self._prepare(frame)  # the frame's own work: no map state, no lock
        if len(current.pix) < self.cfg.min_valid_fraction * current.depth.size:
            return self._drop(frame, "no_depth", f"too little valid depth ({len(current.pix)} of "
                                                 f"{current.depth.size} pixels)")
        self.timings.add("read", time.perf_counter() - t_frame + read_seconds)
        t_wait = time.perf_counter()
        with self.exclusive():
            waited = time.perf_counter() - t_wait
            self.timings.add("integration_wait", waited)
            result = self._commit(frame, current, pts, defer_texture)
        if result.mapped:
            self.timings.add("integration", time.perf_counter() - t_frame - waited + read_seconds)
        return result

    def _commit(self, frame: Frame, current: ImageFrame, pts: np.ndarray, defer_texture: bool) -> FrameResult:
        """The map-changing part of :meth:`integrate` (under the map lock). Two tracks: free space
        and the colour base (which do not read the voxels) on the integration helper thread, beside
        the priors, cell votes and keyframe decision on this one; both end before it returns. While
        the map has no voxel yet the tracks run one after the other (a frame that allocates none is
        dropped and must leave no trace)."""
        # the frame's residual probe, due every PROBE_EVERY frames (its number shifts the pixels probed)
        probe = (self.frames_mapped if self.residual_check is not None and self.frames_mapped % PROBE_EVERY == 0
                 else None)
        beside = self._beside(current, frame.intrinsics, probe) if len(self.voxels) else None
        taken = None
        try:
            with self.timings.time("priors"):
                set_before = self.voxels.prior_set.copy()
                new, observed = self.voxels.allocate_observing(current.depth, frame.intrinsics, current.pose,
                                                               points=pts, every=self.cfg.observe_stride)
                self._note_changes(new, set_before)
            if len(self.voxels) == 0:  # nothing to train on: the frame leaves no trace
                return self._drop(frame, "no_voxels",
                                  f"no voxel has {self.settings.voxels.min_points} depth points yet")
            if beside is None:
                taken = self._fuse_unplaced(current, frame.intrinsics, probe)
            if self.cell_votes.enabled:
                with self.timings.time("cell_votes"):
                    self.cell_votes.mark(self.voxels, current.depth, frame.intrinsics, current.pose)
            result = self._decide(frame, current, pts, new, observed, defer_texture)
        finally:
            if beside is not None:
                taken = beside.result()  # its exception, if any, is the frame's
        if taken is not None and not result.keyframe:  # a keyframe's pixels are trained on: no probe of it
            self.residual_check.add(taken)
        return result

    def _beside(self, current: ImageFrame, intr: Intrinsics, probe: int | None) -> concurrent.futures.Future:
        """:meth:`_fuse_unplaced` on the integration helper thread (made on first use)."""
        if self._helper is None:
            self._helper = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="h3edge-integration",
                                                                 initializer=size_pools, initargs=(self.cfg.threads,))
        return self._helper.submit(self._fuse_unplaced, current, intr, probe)

    def _fuse_unplaced(self, current: ImageFrame, intr: Intrinsics, probe: int | None) -> ResidualProbe | None:
        """The parts of integration that do not read the voxels: free space, the colour base; and,
        unless ``probe`` is None, the frame's residual probe, taken before the base fuses the frame
        (its pixels shifted by that number), returned."""
        taken = None
        with self.timings.time("free_space"):
            self.free_space.mark(current.depth, intr, current.pose)
        if self.color_base is not None:
            with self.timings.time("color_base"):
                if probe is not None:
                    taken = take_probe(self.color_base, current.color, current.depth, current.pix, intr,
                                       current.pose, probe)
                self.color_base.fuse(current.color, current.depth if current.base_depth is None else current.base_depth,
                                     intr, current.pose)
        return taken

    def _decide(self, frame: Frame, current: ImageFrame, pts: np.ndarray, new: np.ndarray, observed: np.ndarray,
                defer_texture: bool) -> FrameResult:
        """The rest of :meth:`_commit`: the field placed, texture patterns, the keyframe decision
        (``observed``: the voxels the frame observes, from allocation)."""
        if self.field is None:  # the first frame that maps places the grids' reference cube
            self._place_field(current.pose[:3, 3])
        grad = None
        if self._texture_due():
            if defer_texture:  # the training thread determines it (the newest due frame wins)
                self._texture_pending = (current, pts)
            else:
                grad = self._determine_texture(current, pts)
        with self.timings.time("keyframes"):
            is_kf = self._update_keyframes(frame.index, current, pts, grad, observed)
        self._untrained = current
        self.frames_mapped += 1
        self.last_timestamp = frame.timestamp
        return FrameResult(frame.index, True, new_voxels=len(new), keyframe=is_kf)

    def process(self, frame: Frame, read_seconds: float = 0.0) -> FrameResult:
        """Map one frame the paper's way: :meth:`integrate` it, then run ``iterations`` training
        steps on rays drawn from it and the keyframes selected for each step (timed as
        ``training``; the whole as ``frame``). Arguments and drops as :meth:`integrate`."""
        t_frame = time.perf_counter()
        result = self.integrate(frame, read_seconds, defer_texture=False)
        if not result.mapped:
            return result
        with self.exclusive():
            current, self._untrained = self._untrained, None
            self._score_probes(self._located_probes())
            with self.timings.time("training"):  # the keyframe picks included
                picks = [self.keyframes.select() for _ in range(self.cfg.iterations)]
                for kfs in picks:
                    result.losses = self._step(self._sample_rays([current] + [k.payload for k in kfs]), "frame")
        self.timings.add("frame", time.perf_counter() - t_frame + read_seconds)
        return result

    @contextlib.contextmanager
    def exclusive(self):
        """Hold the map against every other thread (integration, training steps' ray draws and
        updates, snapshots and checkpoints take it); a caller here goes before a training step that
        waits for it, so a step on another thread delays it by at most its ray draw or its update.
        Re-entrant. ``with mapper.exclusive(): view = mapper.view().frozen()`` is a consistent copy
        while training runs on another thread."""
        with self._turns:
            self._waiting += 1
        self._lock.acquire()
        with self._turns:
            self._waiting -= 1
            self._turns.notify_all()
        try:
            self._stream.before_exclusive_work()  # on CUDA: after the last step's update (training_stream)
            yield self
        finally:
            self._lock.release()

    @contextlib.contextmanager
    def _training_turn(self):
        """The map lock for one training step, taken only when no :meth:`exclusive` caller waits (on
        CUDA the step's stream ordered after the default stream's work, :mod:`~h3edge.mapping.training_stream`)."""
        with self._turns:
            self._turns.wait_for(lambda: self._waiting == 0)
        with self._lock:
            self._stream.follow_default((self.voxels.priors,))
            try:
                yield
            finally:
                self._stream.mark_turn_end()

    def _prepare(self, frame: Frame) -> tuple[ImageFrame, np.ndarray]:
        """The frame with cleaned depth and its valid pixels, and its world points (H, W, 3)."""
        in_range = self.depth_in_range(frame.depth)
        outlines = self.color_base is not None and self.settings.color_base.fuse_edges and self.cfg.edge_radius > 0
        depth = self._edges_left_out(in_range.copy() if outlines else in_range, frame.intrinsics)
        pose = np.asarray(frame.pose, np.float64)
        valid = np.flatnonzero(depth.reshape(-1) > 0).astype(np.int32)
        current = ImageFrame(frame.color, depth, pose, frame.intrinsics, valid,
                             base_depth=in_range if outlines else None)  # the base fuses the outlines too (D53-11)
        return current, backproject(depth, frame.intrinsics, pose)

    def _place_field(self, centre: np.ndarray) -> None:
        self.bound = np.stack([centre - self.cfg.extent / 2, centre + self.cfg.extent / 2])
        self._build_field()

    def _texture_due(self) -> bool:
        """Texture patterns are determined on every ``update_interval``-th mapped frame (H3)."""
        tex = self.settings.texture
        return tex.quasi_heterogeneous and self.frames_mapped % max(1, tex.update_interval) == 0

    def _determine_texture(self, current: ImageFrame, pts: np.ndarray) -> np.ndarray:
        """Determine texture patterns on ``current`` and refresh the warps; the colour gradient
        image (the keyframe score reuses it)."""
        with self.timings.time("texture"):
            grad = color_gradient(current.color, current.depth, self.gradient_jump(current.intrinsics))
            self.patterns.update(current.color, current.depth, current.intrinsics, current.pose, pts,
                                 self.voxels.locate, self.settings.voxels.voxel_size, grad)
            self.refresh_warps()
        return grad

    def _determine_pending_texture(self) -> None:
        """On the training thread: the texture determination integration left for it, its frame-only
        part (gradient, line segments) beside integration, the pattern and warp update under the
        map lock."""
        with self._training_turn():
            pending, self._texture_pending = self._texture_pending, None
        if pending is None:
            return
        current, pts = pending
        t0 = time.perf_counter()
        grad = color_gradient(current.color, current.depth, self.gradient_jump(current.intrinsics))
        lifted = (self.patterns.observe(current.color, current.depth, current.intrinsics, current.pose)
                  if self.settings.texture.max_directions > 0 else None)
        with self._training_turn():
            self.patterns.update(current.color, current.depth, current.intrinsics, current.pose, pts,
                                 self.voxels.locate, self.settings.voxels.voxel_size, grad, lifted)
            self.refresh_warps()
        self.timings.add("texture", time.perf_counter() - t0)

    def _update_keyframes(self, frame_id: int, current: ImageFrame, pts: np.ndarray, grad: np.ndarray | None,
                          observed: np.ndarray) -> bool:
        """Insert the frame as a keyframe when the coverage rule says so on the voxels it observes
        (``observed``: sorted ids, the voxels of every ``observe_stride``-th valid pixel's point, from
        :meth:`VoxelMap.allocate_observing`), scored per voxel by the colour gradient with
        ``gradient_aided``; whether it was. (Those voxels came from locating the pixels' points here
        until allocation's pass over them counted them: 3.7 -> 0.1 ms a real 640x480 frame at 30 Hz.)"""
        if not self.keyframes.should_insert(observed):
            return False
        scores = None
        if self.settings.keyframes.gradient_aided:  # the scores need each sampled pixel's voxel
            stride = self.cfg.observe_stride
            sub = current.pix[::stride]
            vox, _ = self.voxels.locate(pts.reshape(-1, 3)[sub])
            observed = np.flatnonzero(np.bincount(vox[vox >= 0], minlength=len(self.voxels)))  # np.unique, O(n)
            if grad is None:
                grad = color_gradient(current.color, current.depth, self.gradient_jump(current.intrinsics))
            scores = gradient_scores(vox, grad.reshape(-1)[sub], stride)
        self.keyframes.insert(frame_id, observed, scores,
                              payload=current.store())
        return True

    def train_between_frames(self) -> dict | None:
        """One optimisation step on the keyframes the coverage rule selects and on the newest
        integrated frame when no step has used it yet (:meth:`integrate`); its losses (floats), or
        None when there is nothing to train on yet (or the profile turns it off). Timed as
        ``idle_training``. Safe to call from a training thread of its own while another thread
        integrates: the step holds the map lock to draw its rays and to apply its updates, and gives
        way to :meth:`exclusive` callers there; its forward and backward passes only read the map
        and run beside integration."""
        if not self.cfg.train_between_frames:
            return None
        return self.train_once()

    def train_once(self) -> dict | None:
        """One :meth:`train_between_frames` step whatever ``train_between_frames`` says (the
        library's :meth:`h3edge.MapEngine.train`); None when there is nothing to train on yet."""
        with self._stream.active():  # on CUDA the training stream (h3edge.mapping.training_stream)
            return self._train_once()

    def _train_once(self) -> dict | None:
        if self._texture_pending is not None:
            self._determine_pending_texture()
        t0 = time.perf_counter()
        with self._training_turn():
            if self.field is None or not self.keyframes.keyframes or len(self.voxels) == 0:
                return None
            frames = [k.payload for k in self.keyframes.select() if k.payload is not None]
            if self._untrained is not None:
                frames.insert(0, self._untrained)
                self._untrained = None
            if not frames:
                return None
            rays = self._sample_rays(frames)
            located = self._located_probes()
        self._score_probes(located)
        losses = self._step(rays, "between_frames", self._training_turn)
        self.timings.add("idle_training", time.perf_counter() - t0)
        return losses

    def _located_probes(self) -> tuple[list[ResidualProbe], torch.Tensor] | None:
        """Every ``RESCORE_STEPS`` training steps (under the map lock): the residual check's kept
        probes as they are now (integration may replace one before they are scored) and their points'
        voxels, for :meth:`_score_probes`; None when no scoring is due."""
        check = self.residual_check
        if check is None or not check.probes or sum(self.iterations.values()) % RESCORE_STEPS:
            return None
        probes = list(check.probes)
        return probes, self.voxels.locate_points(torch.from_numpy(check.points(probes)).to(self.device))[0]

    def _score_probes(self, located: tuple[list[ResidualProbe], torch.Tensor] | None) -> None:
        """Score :meth:`_located_probes`' probes and hand renders the gain the check keeps (on the
        thread that trains, between its steps: it reads the colour MLP)."""
        if located is not None:
            with self.timings.time("residual_check"):
                self.field.residual_gain = self.residual_check.score(self.field, located[1], located[0])

    def _step(self, rays: RayBatch, when: str, commit=contextlib.nullcontext) -> dict:
        losses = self.trainer.step(rays, commit)
        with commit():
            self.iterations[when] += 1
        if self.step_hook is not None:
            self.step_hook()
        return losses

    def refresh_warps(self) -> None:
        """Hand the current texture classes and directions to the quasi-heterogeneous encoder."""
        if isinstance(self.field.texture, QuasiHeteroTexture):
            classes = self.patterns.classes(len(self.voxels))  # grows the pattern state to every voxel
            self.field.texture.set_warps(unpack(self.voxels.voxel_keys), self.settings.voxels.voxel_size,
                                         classes, self.patterns.dirs, self.patterns.n_dirs)

    def _sample_rays(self, frames: list[ImageFrame | StoredFrame]) -> RayBatch:
        """Rays drawn evenly from ``frames`` (``rays_per_iteration``), and with
        ``train.surface_color_points`` as many more pixels per frame back-projected to their
        measured surface points (:func:`~h3edge.mapping.trainer.surface_color_loss`). On the torch
        backend drawn on the device from the frames' images kept there
        (:mod:`h3edge.mapping.device_frames`), else on the host."""
        n_each = max(1, self.cfg.rays_per_iteration // len(frames))
        n_edge = int(round(self.cfg.edge_rays * n_each))
        n_surf = self.train_cfg.surface_color_points // len(frames)
        step = self.cfg.edge_radius + 1  # an outline's jump reaches across the rim clean_depth left out

        def edges_of(f: ImageFrame | StoredFrame) -> np.ndarray:
            return f.edge_pixels(self.cfg.edge_rays_radius, self.edge_jump(f.intrinsics, step), step,
                                 self.cfg.edge_rays_near_too)

        if self.voxels.device_lookup:
            return self._draw_on_device(frames, n_each, n_edge, n_surf, edges_of)
        o, d, z, c, sp, sc = [], [], [], [], [], []
        for f in frames:
            edges = edges_of(f) if n_edge else np.zeros(0, np.int32)
            # the rest uniformly, also what a frame without edges falls short of
            parts = [f.draw(n_each - (n_edge if len(edges) else 0), self.rng)]
            if len(edges):
                parts.append(f.at(edges[self.rng.integers(0, len(edges), n_edge)]))
            pix, rgb, depth = (np.concatenate(a) for a in zip(*parts))
            rot, origin = f.pose[:3, :3].T.astype(np.float32), f.pose[:3, 3].astype(np.float32)
            cam = self._camera_rays(f.intrinsics)
            d.append(cam[pix] @ rot)
            o.append(np.broadcast_to(origin, (n_each, 3)))
            z.append(depth)
            c.append(rgb)
            if n_surf:
                pix, rgb, depth = f.draw(n_surf, self.rng)
                sp.append((cam[pix] * depth[:, None]) @ rot + origin)
                sc.append(rgb)
        dev = self.device
        t = lambda a, dt=torch.float32: torch.from_numpy(np.ascontiguousarray(np.concatenate(a))).to(dev, dt)  # noqa: E731
        surface = (t(sp), t(sc) / 255.0) if sp else (None, None)
        return RayBatch(t(o), t(d), t(z), t(c) / 255.0, *surface)

    def _draw_on_device(self, frames: list[ImageFrame | StoredFrame], n_each: int, n_edge: int, n_surf: int,
                        edges_of) -> RayBatch:
        """:meth:`_sample_rays` on the device: the same draw (uniform among valid pixels, ``n_edge``
        of them among a frame's edge pixels where it has any) from :meth:`_on_device`'s images, with
        the map's torch generator; no host transfer, nothing uploaded but frames not seen before."""
        g, parts, surface = self.generator, [], []
        for f in frames:
            df = self._on_device(f)
            edges = df.edge_pixels("training rays", lambda f=f: edges_of(f)) if n_edge else None
            pix = [df.draw(n_each - (n_edge if edges is not None and len(edges) else 0), g)]
            if edges is not None and len(edges):
                pix.append(edges[torch.randint(0, len(edges), (n_edge,), generator=g, device=edges.device)])
            parts.append(df.rays(torch.cat(pix)))
            if n_surf:
                so, sd, sz, scol = df.rays(df.draw(n_surf, g))
                surface.append((so + sd * sz[:, None], scol))
        o, d, z, c = (torch.cat(a) for a in zip(*parts))
        sp, sc = (torch.cat(a) for a in zip(*surface)) if surface else (None, None)
        return RayBatch(o, d, z, c, sp, sc)

    def _on_device(self, f: ImageFrame | StoredFrame) -> DeviceFrame:
        """``f``'s images on the map's device (:class:`DeviceFrame`), uploaded on its first draw and
        kept with the frame (a keyframe's until it is pruned)."""
        got = f._on_device.get(self.device)
        if got is None:
            if isinstance(f, StoredFrame):
                got = DeviceFrame.upload(f.color, f.depth_q, f.depth_unit, f.n_valid, f.pose, f.intrinsics,
                                         self.device)
            else:
                got = DeviceFrame.upload(f.color, f.depth, 0.0, len(f.pix), f.pose, f.intrinsics, self.device)
            f._on_device[self.device] = got
        return got

    # ---------------------------------------------------------------- queries
    def view(self) -> MapView:
        """The live map as a :class:`MapView` (``.frozen()`` copies it for queries beside training)."""
        if self.field is None:
            raise RuntimeError("nothing mapped yet")
        return MapView(self.field, self.voxels, self.settings.voxels.voxel_size, self.settings.render,
                       self.cfg.mesh_resolution, self.frames_mapped,
                       self.cfg.mesh_min_support, self.free_space,
                       self.cell_votes if self.cell_votes.enabled else None, self.cfg.max_position)

    def _note_changes(self, new_keys: np.ndarray, prior_set_before: np.ndarray) -> None:
        """Remember where this frame changed the map's geometry: its new voxels, and the voxels around
        the vertices whose prior it set (training refines everywhere a little; a live view refreshes
        those regions on its own schedule)."""
        newly = np.flatnonzero(self.voxels.prior_set[:len(prior_set_before)] & ~prior_set_before)
        ijk = unpack(self.voxels.vertex_keys[newly])
        self._changed.append(np.concatenate([new_keys, pack(ijk), pack(ijk - 1)]))
        if len(self._changed) > 256:  # nobody takes them: keep the union bounded
            self._changed = [np.unique(np.concatenate(self._changed))]

    def take_changed_keys(self) -> np.ndarray:
        """Keys of the voxels (some maybe unallocated) around the geometry the frames mapped since the
        last call allocated or initialised: the regions whose mesh a live view should rebuild now."""
        parts, self._changed = self._changed, []
        return np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)

    def renderer(self) -> MapRenderer:
        return self.view().renderer()

    def render(self, intr: Intrinsics, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Colour uint8 (H, W, 3) and z-depth float32 (H, W) metres (0: nothing) seen from
        camera-to-world ``c2w`` (OpenCV optical) with ``intr``; holds the map while it renders."""
        with self.exclusive(), self.timings.time("render"):
            return self.view().render(intr, c2w)

    def mesh(self, resolution: int | None = None, aabb: np.ndarray | None = None, color: bool = True
             ) -> trimesh.Trimesh:
        """Marching-cubes mesh of the map, vertex colours from the colour field."""
        if self.field is None or len(self.voxels) == 0:
            return trimesh.Trimesh()
        with self.exclusive(), self.timings.time("mesh"):
            return self.view().mesh(resolution, aabb, color)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> tuple[dict, dict[str, np.ndarray]]:
        """Everything needed to resume, as a JSON-able ``meta`` dict and named numpy arrays (what a
        checkpoint holds; holds the map while it copies). Each component contributes its own
        ``state_dict``; hash tables are stored sparsely (:meth:`HashGrid.sparse_state_dict`)."""
        with self.exclusive():
            return self._state_dict()

    def _state_dict(self) -> tuple[dict, dict[str, np.ndarray]]:
        if self.field is None:
            raise RuntimeError("nothing mapped yet")
        meta: dict = {"state_version": STATE_VERSION, "frames_mapped": self.frames_mapped,
                      "dropped": dict(self.dropped), "last_timestamp": self.last_timestamp,
                      "iterations": dict(self.iterations), "bound": self.bound.tolist(),
                      "rng": self.rng.bit_generator.state, "grid_steps": {}}
        arrays: dict[str, np.ndarray] = {}
        for name, grid in self._named_grids().items():
            gmeta, garrays = grid.sparse_state_dict()
            meta["grid_steps"][name] = gmeta["adam_steps"]
            arrays.update(_prefixed(f"grid/{name}", garrays))
        grid_parts = tuple(f"{p}.{part}" for p in self._grid_paths() for part in ("table", "adam_m", "adam_v"))
        for k, v in self.field.state_dict().items():
            if k not in grid_parts:
                arrays[f"field/{k}"] = v.detach().cpu().numpy().copy()
        opt = self.optimizer.state_dict()
        meta["optimizer_groups"] = opt["param_groups"]
        for i, st in opt["state"].items():
            for k, v in st.items():
                arrays[f"opt/{i}/{k}"] = v.detach().cpu().numpy().copy() if torch.is_tensor(v) else np.asarray(v)
        arrays["torch_generator"] = self.generator.get_state().numpy().copy()
        for prefix, part in (("voxels", self.voxels), ("prior_opt", self.prior_opt), ("kf", self.keyframes),
                             ("patterns", self.patterns), ("free", self.free_space)):
            pmeta, parrays = part.state_dict()
            meta.update(_renamed_meta(prefix, pmeta))
            arrays.update(_prefixed(prefix, parrays))
        arrays.update(_prefixed("votes", self.cell_votes.state_dict()))
        if self.color_base is not None:
            arrays.update(_prefixed("color_base", self.color_base.state_dict()))
        if self.residual_check is not None:
            meta["residual_check"], check_arrays = self.residual_check.state_dict()
            arrays.update(_prefixed("residual_check", check_arrays))
        return meta, arrays

    def load_state_dict(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        """Take the state :meth:`state_dict` captured, on a mapper built with the same settings and
        the captured ``bound`` (:meth:`from_state_dict` does both). ValueError when it does not fit."""
        version = meta.get("state_version")
        if version not in READABLE_STATE_VERSIONS:
            raise ValueError(f"map state version {version} is not one of {READABLE_STATE_VERSIONS}")
        if self.field is None or not np.allclose(self.bound, np.asarray(meta["bound"], np.float64)):
            raise ValueError("load_state_dict needs a mapper built with the state's bound (use from_state_dict)")
        for name, grid in self._named_grids().items():
            grid.load_sparse_state_dict({"adam_steps": meta["grid_steps"][name]},
                                        _unprefixed(f"grid/{name}", arrays))
        current = self.field.state_dict()
        saved = {k[len("field/"):]: torch.from_numpy(np.asarray(v)) for k, v in arrays.items()
                 if k.startswith("field/")}
        for k, v in saved.items():
            if k not in current:
                raise ValueError(f"checkpoint field entry {k!r} does not exist in this configuration")
            per_voxel = k.startswith("texture.") and k.split(".")[1] in QuasiHeteroTexture.PER_VOXEL
            if not per_voxel and current[k].shape != v.shape:
                raise ValueError(f"checkpoint field entry {k!r} has shape {tuple(v.shape)}, "
                                 f"this configuration {tuple(current[k].shape)}")
        with torch.no_grad():
            self.field.load_state_dict(saved, strict=False)
        state: dict = {}
        for k, v in arrays.items():
            if k.startswith("opt/"):
                _, i, name = k.split("/")
                vt = torch.from_numpy(np.array(v))
                state.setdefault(int(i), {})[name] = vt if name != "step" else vt.to(torch.float32)
        self.optimizer.load_state_dict({"state": state, "param_groups": meta["optimizer_groups"]})
        self.generator.set_state(torch.from_numpy(np.asarray(arrays["torch_generator"])))
        self.voxels.load_state_dict(meta, _unprefixed("voxels", arrays))
        self.prior_opt.load_state_dict(_original_meta("prior_opt", meta), _unprefixed("prior_opt", arrays),
                                       self.device)
        if version >= 2:
            self.keyframes.load_state_dict(meta, _unprefixed("kf", arrays))
        else:
            log.warning("map state version %s: its keyframes kept pixel subsets; dropped (new frames rebuild "
                        "the keyframe set)", version)
        self.patterns.load_state_dict(_original_meta("patterns", meta), _unprefixed("patterns", arrays))
        if "free/keys" in arrays:  # checkpoints from before the free-space record have none
            self.free_space.load_state_dict(meta, _unprefixed("free", arrays))
        self.cell_votes.load_state_dict(_unprefixed("votes", arrays))
        if self.color_base is not None:  # a checkpoint from before the base (or without it) starts it empty
            self.color_base.load_state_dict(_unprefixed("color_base", arrays))
        if self.residual_check is not None and "residual_check" in meta:  # saved with the check on
            self.residual_check.load_state_dict(meta["residual_check"], _unprefixed("residual_check", arrays))
            self.field.residual_gain = self.residual_check.gain
        self.frames_mapped = int(meta["frames_mapped"])
        self.dropped = dict(meta["dropped"])
        self.last_timestamp = meta["last_timestamp"]
        self.iterations.update({k: int(v) for k, v in meta.get("iterations", {}).items() if k in self.iterations})
        self.rng.bit_generator.state = meta["rng"]

    @classmethod
    def from_state_dict(cls, settings: MapSettings, meta: dict, arrays: dict[str, np.ndarray]) -> MapEngine:
        """A mapper in the captured state (``settings`` must be the ones it ran with)."""
        if meta.get("state_version") not in READABLE_STATE_VERSIONS:
            raise ValueError(f"map state version {meta.get('state_version')} is not one of {READABLE_STATE_VERSIONS}")
        m = cls(settings, bound=np.asarray(meta["bound"], np.float64))
        m.load_state_dict(meta, arrays)
        return m

    def _named_grids(self) -> dict[str, HashGrid]:
        return {"geo": self.field.geo_grid, "tex": self.field.texture.grid}

    @staticmethod
    def _grid_paths() -> tuple[str, str]:
        return ("geo_grid", "texture.grid")

    def stats(self) -> dict:
        kf_bytes = sum(k.payload.nbytes for k in self.keyframes.keyframes if k.payload is not None)
        field = self.field or self._unplaced
        grids = sum(g.table.numel() * 3 * 4 for g in field.hash_grids()) if field else 0
        keys = unpack(self.voxels.voxel_keys) if len(self.voxels) else None
        vs = self.settings.voxels.voxel_size
        return {
            # m, world frame: the allocated voxels' box (None before any)
            "bounds": None if keys is None else [(keys.min(0) * vs).tolist(), ((keys.max(0) + 1) * vs).tolist()],
            "frames_mapped": self.frames_mapped,
            "iterations": dict(self.iterations),
            "dropped": dict(self.dropped),
            "voxels": len(self.voxels),
            "voxels_refused": self.voxels.refused,
            "vertices": len(self.voxels.vertex_keys),
            "keyframes": len(self.keyframes.keyframes),
            "keyframes_pruned": self.keyframes.pruned,
            "keyframes_evicted": self.keyframes.evicted,
            "device": str(self.device),
            "residual_gain": (self.field.residual_gain if self.residual_check is not None and self.field is not None
                              else None),
            "texture_classes": self.patterns.counts(len(self.voxels))
            if self.settings.texture.quasi_heterogeneous
            else {},
            "memory_bytes": {
                "keyframes": kf_bytes,
                "hash_grids_with_adam": grids,
                # prior, its Adam moments, seen_behind; trained rays per voxel
                "priors": len(self.voxels.vertex_keys) * 4 * 4 + self.voxels.trained_nbytes,
                "ray_tables": sum(r.nbytes for r in self._rays_cache.values()),
                "texture_patterns": self.patterns.nbytes,
                "free_space": self.free_space.nbytes,
                "cell_votes": self.cell_votes.nbytes,
                "color_base": self.color_base.nbytes if self.color_base is not None else 0,
                "residual_check": self.residual_check.nbytes if self.residual_check is not None else 0,
            },
        }


def _prefixed(prefix: str, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {f"{prefix}/{k}": v for k, v in arrays.items()}


def _unprefixed(prefix: str, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    n = len(prefix) + 1
    return {k[n:]: v for k, v in arrays.items() if k.startswith(prefix + "/")}


# components whose meta keys are stored under another name (checkpoints written before the
# components had their own state_dict keep loading)
_META_NAMES = {"prior_opt": {"steps": "prior_steps"}, "patterns": {"updates": "texture_updates"}}


def _renamed_meta(prefix: str, meta: dict) -> dict:
    names = _META_NAMES.get(prefix, {})
    return {names.get(k, k): v for k, v in meta.items()}


def _original_meta(prefix: str, meta: dict) -> dict:
    return {k: meta[stored] for k, stored in _META_NAMES[prefix].items()}


def synthetic_map(settings: MapSettings, frames: int = 2) -> tuple[MapEngine, Intrinsics]:
    """A throwaway small map with ``settings``' sections and device (small hash tables and voxel
    cap): ``frames`` synthetic 64x48 frames of a checkerboard wall 1.5 m ahead, the camera stepping
    2 cm sideways, each mapped the paper's way (:meth:`MapEngine.process`). Every integration and
    training kernel has run once: the service's start-up warm-up and ``h3edge doctor``'s map check.
    Returns the map and the frames' intrinsics (the wall fills the view from the identity pose)."""
    small = dataclasses.replace(
        settings, field=dataclasses.replace(settings.field, geo_log2_table=12, tex_log2_table=12),
        voxels=dataclasses.replace(settings.voxels, min_points=1, max_voxels=10_000),
        mapper=dataclasses.replace(settings.mapper, rays_per_iteration=256, extent=4.0),
        texture=dataclasses.replace(settings.texture, update_interval=1))
    m = MapEngine(small)
    intr = Intrinsics(64, 48, 50.0, 50.0, 32.0, 24.0)
    u, v = np.meshgrid(np.arange(64), np.arange(48))
    color = np.where(((u // 8 + v // 8) % 2 == 0)[..., None], np.uint8(200), np.uint8(40)).repeat(3, -1)
    depth = np.full((48, 64), 1.5, np.float32)
    for i in range(frames):
        pose = np.eye(4)
        pose[0, 3] = 0.02 * i
        result = m.process(Frame(i, float(i), color, depth, pose, intr))
        if not result.mapped:
            raise RuntimeError(f"synthetic frame {i} was dropped: {result.reason}")
    return m, intr
