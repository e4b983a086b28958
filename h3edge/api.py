"""The library: :class:`Mapper`, one object a Python program maps with (``from h3edge import Mapper``).

Frames go in with :meth:`Mapper.add_frame` (integration: voxels, SDF priors, free space, the colour
base, the keyframe decision; milliseconds), the neural fields learn with :meth:`Mapper.train` (on
the calling thread) or :meth:`Mapper.start_training` (a thread of its own, as the service runs it),
and the map answers :meth:`~Mapper.render`, :meth:`~Mapper.mesh`, :meth:`~Mapper.signed_distance`
and :meth:`~Mapper.slice` at any moment; :meth:`~Mapper.snapshot` hands other threads a frozen copy
to query while mapping goes on. :meth:`~Mapper.save` / :meth:`Mapper.load` write and read the map
file the service's checkpoints use (:mod:`h3edge.mapping.map_file`), the map's own settings inside.

Conventions: poses are camera-to-world 4x4 rigid transforms in metres, camera axes OpenCV optical
(x right, y down, z forward); depth is z-depth in metres (0 or NaN: no measurement); colour is
RGB uint8. Inputs may be numpy arrays or torch tensors on any device; outputs are numpy arrays on
the host. The map itself lives on ``Mapper.device`` (the profile's ``mapper.device``; ``auto``
picks CUDA when present).
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh

from h3edge.errors import InputError
from h3edge.geometry.camera import Intrinsics
from h3edge.io.distance_types import slice_cells
from h3edge.io.sequence import Frame
from h3edge.mapping.background import BackgroundTraining
from h3edge.mapping.distance import DistanceSample, DistanceSlice, distance_slice, signed_distance
from h3edge.mapping.engine import FrameResult, MapSettings, synthetic_map
from h3edge.mapping.engine import MapEngine as _Engine
from h3edge.mapping.map_file import map_record, read_map, write_checkpoint
from h3edge.mapping.mesh import fill_scratch_bytes, working_bytes
from h3edge.mapping.onnx_decoders import DecoderRuntime, InferenceConfig
from h3edge.mapping.settings_file import map_settings_from_profile
from h3edge.mapping.view import MapView
from h3edge.mapping.voxels import unpack
from h3edge.profiling.timing import Timings

__all__ = ["DecoderRuntime", "DistanceSample", "DistanceSlice", "FrameResult", "InferenceConfig", "MapSettings",
           "MapSnapshot", "Mapper", "as_intrinsics", "warm_up"]
DEFAULT_PROFILE = "x86-cpu"
MAX_SLICE_CELLS = 1 << 28  # cells a slice may have (a few GB of working arrays): beyond, a mistake, not a map


def _host(a, what: str) -> np.ndarray:
    """A numpy array of ``a`` (a numpy array, a torch tensor on any device, or a nested list)."""
    if hasattr(a, "detach") and hasattr(a, "cpu"):  # a torch tensor: one copy to the host
        a = a.detach().cpu().numpy()
    try:
        return np.asarray(a)
    except (TypeError, ValueError) as e:
        raise InputError(f"{what}: not an array ({e})") from None


def as_intrinsics(intrinsics, width: int, height: int) -> Intrinsics:
    """:class:`~h3edge.geometry.camera.Intrinsics` from an ``Intrinsics`` (its size must be
    ``width`` x ``height``) or a 3x3 pinhole matrix K (pixels; ``fx, fy`` on the diagonal, ``cx, cy``
    in the last column; pixel centres at half-integers, OpenCV's convention)."""
    if isinstance(intrinsics, Intrinsics):
        if (intrinsics.width, intrinsics.height) != (width, height):
            raise InputError(f"intrinsics are for {intrinsics.width}x{intrinsics.height} images, "
                             f"the frame is {width}x{height}")
        return intrinsics
    k = _host(intrinsics, "intrinsics").astype(np.float64)
    if k.shape != (3, 3):
        raise InputError(f"intrinsics must be an Intrinsics or a 3x3 matrix K, got shape {k.shape}")
    try:
        return Intrinsics(width, height, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    except ValueError as e:
        raise InputError(f"intrinsics: {e}") from None


class MapSnapshot:
    """A frozen copy of a :class:`Mapper`'s map at one moment (:meth:`Mapper.snapshot`): safe to
    query from any thread while the mapper maps and trains on; it never changes. The colour base
    and the free-space votes are shared with the live map (copied only where they are read);
    everything the training changes is copied. Queries run on the map's device; outputs are host
    numpy arrays."""

    def __init__(self, view: MapView, frames_mapped: int):
        self._view = view
        self.frames_mapped = frames_mapped  # frames integrated when the copy was taken

    def render(self, intrinsics: Intrinsics, c2w) -> tuple[np.ndarray, np.ndarray]:
        """See :meth:`Mapper.render`."""
        if not isinstance(intrinsics, Intrinsics):
            raise InputError("render needs an Intrinsics (it carries the image size)")
        return self._view.render(intrinsics, _pose(c2w))

    def mesh(self, resolution: int | None = None, aabb=None, fill: bool = True) -> trimesh.Trimesh:
        """See :meth:`Mapper.mesh`; ``fill`` False: without the colour base's surface in the cubes
        whose priors carry no evidence (what a caller short of memory asks, see
        :meth:`mesh_scratch_bytes`)."""
        return self._view.mesh(resolution, None if aabb is None else _aabb(aabb), fill=fill)

    def signed_distance(self, points, gradient: bool = False) -> DistanceSample:
        """See :meth:`Mapper.signed_distance`."""
        return signed_distance(self._view, _points(points), gradient)

    def slice(self, z: float, lo, hi, resolution: float = 0.05) -> DistanceSlice:
        """See :meth:`Mapper.slice`."""
        return _slice(self._view, z, lo, hi, resolution)

    @property
    def voxel_size(self) -> float:
        """Leaf voxel edge, metres."""
        return self._view.voxel_size

    def voxel_coords(self) -> np.ndarray:
        """Integer coordinates (N, 3) int64 of the map's leaf voxels: voxel ``ijk`` spans world
        ``[ijk, ijk + 1) * voxel_size`` metres."""
        return unpack(self._view.voxels.voxel_keys)

    def block_meshes(self, blocks, block_voxels: int, resolution: int | None = None) -> list[trimesh.Trimesh]:
        """Meshes of map blocks ``blocks`` (B, 3) int, each a cube of ``block_voxels`` leaf voxels
        (block ``b`` holds the voxels with ``voxel_coords() // block_voxels == b``); an empty mesh
        for a block with no voxel. World coordinates, metres."""
        return self._view.block_meshes(np.asarray(blocks, np.int64).reshape(-1, 3), int(block_voxels), resolution)

    def mesh_scratch_bytes(self, resolution: int | None = None, aabb=None, fill: bool = True) -> int:
        """Peak scratch bytes :meth:`mesh` with these arguments would take, before the mesh itself:
        what a caller checks against a memory budget before asking (``fill`` as :meth:`mesh`)."""
        view = self._view
        res = view.mesh_resolution if resolution is None else int(resolution)
        base = view.field.color_base if view.mesh_min_support > 0 and fill else None  # fills the cubes left out
        return (working_bytes(view.voxels.voxel_keys, view.voxel_size, res, None if aabb is None else _aabb(aabb))
                + fill_scratch_bytes(0 if base is None else len(base)))


class Mapper:
    """An H3-Mapping map built from posed RGB-D frames, in this process.

    Usage::

        from h3edge import Mapper

        mapper = Mapper.from_profile("x86-cpu")          # or Mapper.load("kitchen.h3ckpt")
        for color, depth, c2w in camera:                 # uint8 (H, W, 3), float32 (H, W) m, (4, 4)
            mapper.add_frame(color, depth, c2w, K)       # integration: milliseconds, every frame
            mapper.train(steps=2)                        # or mapper.start_training() once
        color, depth = mapper.render(intrinsics, c2w)    # any pose
        mapper.mesh().export("map.ply")
        mapper.save("kitchen.h3ckpt")

    Thread safety: every method may be called from any thread; integration, training steps and
    queries take the map's lock in turn (integration goes first). :meth:`snapshot` gives a copy
    that other threads query without waiting for the map at all.
    """

    def __init__(self, settings: MapSettings | None = None, device: str | None = None, *,
                 profile: str = "custom", _engine: _Engine | None = None):
        """A new, empty map with ``settings`` (default: :class:`MapSettings`'s defaults, the paper's
        values; docs/configuration.md);
        ``device``: ``cpu``, ``cuda``, ``cuda:N`` or ``auto`` (default: ``settings.mapper.device``).
        ``profile``: the name saved with the map."""
        if _engine is None:
            settings = MapSettings() if settings is None else settings
            if device is not None:
                settings = dataclasses.replace(settings, mapper=dataclasses.replace(settings.mapper, device=device))
            _engine = _Engine(settings)
        self._engine = _engine
        self.profile = profile
        self._frame_ids = itertools.count(_engine.frames_mapped + sum(_engine.dropped.values()))
        self._training: BackgroundTraining | None = None
        self._training_errors = 0  # steps that raised on earlier training threads

    # ------------------------------------------------------------- building
    @classmethod
    def from_profile(cls, name_or_path: str | Path = DEFAULT_PROFILE, device: str | None = None) -> Mapper:
        """A new map with a profile's mapping settings: a shipped profile's name (``x86-cpu``,
        ``orin-agx``, ``orin-nx``, ``orin-nano``, ``paper-reference``) or a TOML file's path.
        ``device`` overrides the profile's ``mapper.device``. ProfileError (an InputError) names
        what is wrong with the file."""
        return cls(map_settings_from_profile(name_or_path), device, profile=Path(str(name_or_path)).stem)

    @classmethod
    def load(cls, path: str | Path, settings: MapSettings | None = None, device: str | None = None) -> Mapper:
        """The map saved in ``path`` (:meth:`save`, or a service checkpoint), with the settings it
        was saved with; ``settings`` replaces them (it must have the same grid sizes), ``device``
        moves the map (``cpu``, ``cuda``, ...). CheckpointError (an InputError) when the file is not
        a readable map; ValueError when its state does not fit ``settings``."""
        from h3edge.mapping.map_file import read_header, saved_settings

        header, _ = read_header(Path(path))
        chosen = saved_settings(header, Path(path)) if settings is None else settings
        if device is not None:
            chosen = dataclasses.replace(chosen, mapper=dataclasses.replace(chosen.mapper, device=device))
        engine, header = read_map(Path(path), chosen)
        return cls(_engine=engine, profile=str(header.get("profile", "custom")))

    def save(self, path: str | Path, map_id: str = "map") -> int:
        """Write the map to ``path`` (``.h3ckpt``; atomically: a reader sees the old file or the new
        one, never a torn one; a file it replaces is kept as ``<path>.prev``) with its settings, its
        decoders as ONNX and ``map_id``; returns the bytes written. Holds the map only while it
        copies the state. RuntimeError when nothing is mapped yet."""
        return write_checkpoint(Path(path), *self.capture(map_id))

    def capture(self, map_id: str = "map", profile: str | None = None) -> tuple[dict, dict[str, np.ndarray]]:
        """The map's saved form now, (header, arrays), holding the map only while it copies:
        :func:`h3edge.mapping.map_file.write_checkpoint` writes it (on another thread if wanted;
        :meth:`save` does both). ``profile``: the name recorded (default: this map's). RuntimeError
        when nothing is mapped yet."""
        with self._engine.exclusive():
            return map_record(self._engine, map_id, self.profile if profile is None else profile)

    def replace_map(self, other: Mapper) -> None:
        """Go on with ``other``'s map (a loaded one) in place of this one, between two training
        steps: this Mapper's training thread, step hook and timings carry on; ``other`` is spent."""
        with self._engine.exclusive():
            engine = other._engine
            engine.timings, engine.step_hook = self._engine.timings, self._engine.step_hook
            self._engine, self.profile = engine, other.profile
            self._frame_ids = itertools.count(engine.frames_mapped + sum(engine.dropped.values()))
            if self._training is not None:
                self._training.mapper = engine  # read each step: the next step trains the new map

    # -------------------------------------------------------------- mapping
    def add_frame(self, color, depth, c2w, intrinsics, timestamp: float | None = None, *,
                  train: bool = False, frame_id: int | None = None, decode_seconds: float = 0.0) -> FrameResult:
        """Integrate one frame into the map's explicit parts (voxels and their SDF priors, free
        space, the fused colour base, the keyframe decision); no training (:meth:`train`).

        ``color``: uint8 (H, W, 3) RGB. ``depth``: float (H, W) z-depth in metres, 0 or NaN where
        nothing was measured (a uint16 millimetre image: divide by 1000 first). ``c2w``: (4, 4)
        camera-to-world pose, metres, OpenCV optical axes. ``intrinsics``: an ``Intrinsics`` of an
        H x W image, or a 3x3 K. Numpy arrays or torch tensors on any device. ``timestamp``: seconds,
        increasing (default: the host's monotonic clock now). ``train``: also run the profile's
        ``mapper.iterations`` training steps on this frame and the selected keyframes before
        returning (the paper's per-frame mapping; the service's when ``train_between_frames`` is
        off). ``frame_id``: the id logged and returned (default: a counter).
        ``decode_seconds``: the caller's time reading the frame, added to the ``read`` and
        ``integration`` timings.

        Returns a :class:`FrameResult` (``mapped``; ``reason`` when it was dropped). A frame the map
        cannot use (a non-rigid or far pose, too little valid depth, a stale timestamp) is dropped
        with a reason and counted in ``stats()["dropped"]``, and changes nothing; input of the wrong
        shape or dtype raises InputError."""
        col = _host(color, "color")
        dep = _host(depth, "depth")
        if col.dtype != np.uint8 or col.ndim != 3 or col.shape[2] != 3:
            raise InputError(f"color must be uint8 (H, W, 3) RGB, got {col.dtype} {col.shape}")
        if dep.ndim != 2 or dep.shape != col.shape[:2]:
            raise InputError(f"depth must be (H, W) = {col.shape[:2]}, got {dep.shape}")
        if not np.issubdtype(dep.dtype, np.floating):
            raise InputError(f"depth must be float metres, got {dep.dtype} (uint16 millimetres: depth / 1000)")
        pose = _pose(c2w)
        intr = as_intrinsics(intrinsics, col.shape[1], col.shape[0])
        ts = time.monotonic() if timestamp is None else float(timestamp)
        fid = next(self._frame_ids) if frame_id is None else int(frame_id)
        frame = Frame(fid, ts, np.ascontiguousarray(col), dep.astype(np.float32, copy=False), pose, intr)
        if train:
            return self._engine.process(frame, read_seconds=decode_seconds)
        return self._engine.integrate(frame, read_seconds=decode_seconds)

    def train(self, steps: int | None = None, seconds: float | None = None) -> int:
        """Train the neural fields on the calling thread: ``steps`` optimisation steps, or as many as
        fit in ``seconds``, whichever ends first (neither: the profile's ``mapper.iterations``).
        Each step draws ``mapper.rays_per_iteration`` rays from the keyframes and the newest frame
        no step has used. Returns the steps run (0 before a keyframe exists)."""
        if steps is None and seconds is None:
            steps = self._engine.cfg.iterations
        end = None if seconds is None else time.perf_counter() + seconds
        done = 0
        while (steps is None or done < steps) and (end is None or time.perf_counter() < end):
            if self._engine.train_once() is None:
                break
            done += 1
        return done

    def start_training(self, on_error: Callable[[Exception], None] | None = None) -> None:
        """Train on a thread of its own from now on, step after step, beside :meth:`add_frame` on
        the caller's thread (a frame never waits for a step, only for a step's ray draw or update).
        A step that raises is logged, counted in ``training_errors`` and handed to ``on_error`` (on
        the training thread); training goes on. Numba needs a thread-safe layer (OpenMP or TBB):
        RuntimeError otherwise."""
        if self._training is None:
            self._training = BackgroundTraining(self._engine, on_error=on_error, unconditional=True).start()

    def stop_training(self, timeout: float = 60.0) -> None:
        """Stop the training thread after its step in progress, waiting at most ``timeout`` seconds
        (no-op when none runs)."""
        if self._training is not None:
            self._training.stop(timeout)
            self._training_errors += self._training.errors
            self._training = None

    @property
    def training_errors(self) -> int:
        """Training steps on a :meth:`start_training` thread that raised, since this Mapper was made."""
        return self._training_errors + (self._training.errors if self._training is not None else 0)

    @property
    def on_step(self) -> Callable[[], None] | None:
        """Called after every training step, on the thread that ran it (None: nothing). With
        ``add_frame(train=True)`` it runs between the frame's steps, holding the map: a caller that
        serves other work there (copies, saves) keeps it waiting at most one step."""
        return self._engine.step_hook

    @on_step.setter
    def on_step(self, hook: Callable[[], None] | None) -> None:
        self._engine.step_hook = hook

    @contextlib.contextmanager
    def exclusive(self):
        """``with mapper.exclusive():`` holds the map: no integration and no training step's ray draw
        or update runs on another thread inside the block (a step's forward and backward passes
        may). Re-entrant. For a consistent moment across several calls (a copy and a save)."""
        with self._engine.exclusive():
            yield self

    # -------------------------------------------------------------- queries
    def render(self, intrinsics: Intrinsics, c2w) -> tuple[np.ndarray, np.ndarray]:
        """The map seen by a pinhole camera: ``intrinsics`` (an ``Intrinsics``, whose size is the
        image's) at camera-to-world ``c2w`` (4, 4), metres, OpenCV optical axes. Returns colour
        uint8 (H, W, 3) RGB and z-depth float32 (H, W) metres (0: nothing there), host arrays.
        RuntimeError when nothing is mapped yet."""
        if not isinstance(intrinsics, Intrinsics):
            raise InputError("render needs an Intrinsics (it carries the image size)")
        return self._engine.render(intrinsics, _pose(c2w))

    def mesh(self, resolution: int | None = None, aabb=None) -> trimesh.Trimesh:
        """The map's surface by marching cubes, vertex colours from the colour field: world
        coordinates in metres. ``resolution``: cells per voxel edge (default: ``mapper.mesh_resolution``);
        ``aabb``: (2, 3) metres ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``, only that box. An
        empty mesh before anything is mapped."""
        return self._engine.mesh(resolution, None if aabb is None else _aabb(aabb))

    def signed_distance(self, points, gradient: bool = False) -> DistanceSample:
        """Signed distance at world points (N, 3) metres: ``.sdf`` float32 (N,) metres (positive in
        front of a surface; NaN where the map knows nothing), ``.state`` uint8 (N,) (0 unknown,
        1 free, 2 near a surface, 3 inside), ``.gradient`` float32 (N, 3) when ``gradient``
        (pointing away from the surface). Free points beyond the truncation band read ``truncation``
        (a lower bound). See :mod:`h3edge.mapping.distance`."""
        return self.snapshot().signed_distance(points, gradient)

    def slice(self, z: float, lo, hi, resolution: float = 0.05) -> DistanceSlice:
        """An occupancy and distance image at height ``z`` (m) over ``lo`` = (xmin, ymin) ..
        ``hi`` = (xmax, ymax) metres, ``resolution`` metres a cell: ``.occupancy`` int8 (H, W)
        (-1 unknown, 0 free, 100 occupied; row 0 is the lowest y), ``.distance`` float32 (H, W)
        metres to the nearest occupied cell (NaN unknown), ``.origin``, ``.resolution``."""
        return self.snapshot().slice(z, lo, hi, resolution)

    def snapshot(self, decoders: DecoderRuntime | None = None) -> MapSnapshot:
        """A frozen copy of the map now, for queries on other threads while mapping goes on
        (copying takes the map's lock for tens of milliseconds). ``decoders``: run the copy's SDF and
        colour decoders on this onnxruntime (:class:`DecoderRuntime`; its sessions are shared by
        every copy). RuntimeError when nothing is mapped yet (``empty``)."""
        with self._engine.exclusive():
            return MapSnapshot(self._engine.view().frozen(decoders), self._engine.frames_mapped)

    def take_changed_voxels(self) -> np.ndarray:
        """Integer coordinates (N, 3) int64 (as :meth:`MapSnapshot.voxel_coords`) of the voxels around
        the geometry the frames mapped since the last call allocated or initialised: where a live
        view should rebuild its mesh. Call it where a snapshot is taken to pair the two."""
        with self._engine.exclusive():
            return unpack(self._engine.take_changed_keys())

    def stats(self) -> dict:
        """Counts and sizes: ``frames_mapped``, ``dropped`` (by reason), ``iterations`` (training
        steps by when they ran), ``voxels``, ``voxels_refused``, ``vertices``, ``keyframes`` (and
        ``_pruned``, ``_evicted``), ``texture_classes``, ``device``, ``memory_bytes`` (by part),
        ``residual_gain`` (the gain renders apply to the colour residual over the colour base, None
        without ``render.checked_residual``).
        Durations by stage: ``timings.summary()``. Read without the map's lock (counts of a moment)."""
        return self._engine.stats()

    @property
    def timings(self) -> Timings:
        """Durations of every stage (``integration``, ``training``, ``render``, ...; ``.summary()``:
        count, median and p90 milliseconds each); a caller may add its own stages (``.add(name,
        seconds)``) or give it a sink (``.sink``) that logs every duration."""
        return self._engine.timings

    @property
    def frames_mapped(self) -> int:
        """Frames integrated into the map (dropped ones not counted), across save and load."""
        return self._engine.frames_mapped

    @property
    def last_timestamp(self) -> float | None:
        """Timestamp (seconds, as given to :meth:`add_frame`) of the newest mapped frame; None before one."""
        return self._engine.last_timestamp

    def forget_last_timestamp(self) -> None:
        """Forget :attr:`last_timestamp`: the next frame may carry any stamp. For a map whose newest
        stamp came from a clock that is no longer the input's (a recording replayed, a clock reset)."""
        with self._engine.exclusive():
            self._engine.last_timestamp = None

    @property
    def dropped(self) -> dict[str, int]:
        """Frames dropped, by reason (``bad_pose``, ``no_depth``, ...), across save and load."""
        return dict(self._engine.dropped)

    @property
    def iterations(self) -> dict[str, int]:
        """Training steps run: ``frame`` (inline, ``add_frame(train=True)``) and ``between_frames``."""
        return dict(self._engine.iterations)

    @property
    def empty(self) -> bool:
        """True while there is nothing to query (no frame mapped yet): render, snapshot and save
        raise, mesh is empty."""
        return self._engine.field is None

    @property
    def settings(self) -> MapSettings:
        """The settings this map runs with (read only)."""
        return self._engine.settings

    @property
    def device(self) -> str:
        """The device the map lives on (``cpu``, ``cuda:0``, ...)."""
        return str(self._engine.device)


def warm_up(settings: MapSettings, decoders: DecoderRuntime | None = None) -> float:
    """Run every integration, training and query kernel once on a throwaway small map with
    ``settings``' device (two synthetic frames, a render, a mesh), so that loading compiled code is
    start-up cost and not the first frame's or query's; ``decoders``: warm those sessions too.
    Seconds taken."""
    t0 = time.perf_counter()
    engine, intr = synthetic_map(settings)
    view = engine.view().frozen(decoders)
    view.render(intr, np.eye(4))
    view.mesh(2)
    if engine.color_base is not None:  # the mesh fill's volume kernel, whether or not that mesh needed it
        engine.color_base.distances().volume(np.zeros(3, np.int64), 2)
    return time.perf_counter() - t0


def _pose(c2w) -> np.ndarray:
    p = _host(c2w, "c2w").astype(np.float64)
    if p.shape != (4, 4):
        raise InputError(f"c2w must be a (4, 4) camera-to-world matrix, got shape {p.shape}")
    return p


def _points(points) -> np.ndarray:
    p = _host(points, "points").astype(np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"points must be (N, 3) metres, got shape {p.shape}")
    if not np.isfinite(p).all():
        raise InputError("points must be finite")
    return p


def _aabb(aabb) -> np.ndarray:
    box = _host(aabb, "aabb").astype(np.float64)
    if box.shape != (2, 3) or not np.isfinite(box).all() or np.any(box[0] >= box[1]):
        raise InputError("aabb must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max")
    return box


def _slice(view: MapView, z: float, lo, hi, resolution: float) -> DistanceSlice:
    lo, hi = tuple(float(v) for v in lo), tuple(float(v) for v in hi)
    if len(lo) != 2 or len(hi) != 2 or not (lo[0] < hi[0] and lo[1] < hi[1]):
        raise InputError("slice needs lo = (xmin, ymin) < hi = (xmax, ymax)")
    if not (resolution > 0 and np.isfinite([z, *lo, *hi]).all()):
        raise InputError("slice needs a finite z, corners and a positive resolution")
    cells = slice_cells(lo, hi, resolution)
    if not cells <= MAX_SLICE_CELLS:
        raise InputError(f"a slice of {cells:.4g} cells is more than {MAX_SLICE_CELLS}: a coarser resolution or a "
                         "smaller area")
    return distance_slice(view, float(z), lo, hi, float(resolution))
