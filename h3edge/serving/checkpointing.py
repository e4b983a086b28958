"""Checkpoints of one running map: where they live, resuming from them, capturing the mapper's
state and writing it on a writer thread, and saving to / loading from other files under the
state directory.

The mapper thread captures (:meth:`Checkpointer.capture`, between frames: :meth:`h3edge.Mapper.capture`,
the map's state plus its decoders as ONNX, versioned with the map); a writer thread writes it
atomically (:func:`h3edge.mapping.map_file.write_checkpoint`), one write at a time so
checkpoints land in order. ``<run_dir>/map.h3ckpt`` is the one ``--resume`` reads, with the
previous one kept beside it as the fallback; ``save_path`` / ``load_path`` name other checkpoint
files, confined to ``<run_dir>/maps/`` (a query can never write or read outside it).
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path

import numpy as np

from h3edge.api import Mapper, MapSettings
from h3edge.errors import QueryError
from h3edge.mapping.map_file import (
    CHECKPOINT_NAME,
    READ_SETTINGS,
    CheckpointError,
    check_writable,
    previous_path,
    read_header,
    remove_leftovers,
    saved_settings,
    settings_differences,
    write_checkpoint,
)
from h3edge.profiling.timing import Timings

log = logging.getLogger(__name__)
SAVED_MAPS_DIR = "maps"  # under the run directory: where named saves go and loads come from
EXPORTS_DIR = "exports"  # under the run directory: meshes exported by name
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


class Checkpointer:
    """Checkpoints of map ``map_id`` in ``run_dir``.

    Usage::

        ckpt = Checkpointer(run_dir, "kitchen", "x86-cpu", settings, timings, on_error)
        mapper, resumed = ckpt.resume()          # (None, None) when there is no checkpoint
        ckpt.write_async(ckpt.capture(mapper))   # on the mapper thread; the write runs beside it
        ckpt.join()
    """

    def __init__(self, run_dir: Path, map_id: str, profile_name: str, settings: MapSettings, timings: Timings,
                 on_error: Callable[[str, str], None], after_write: Callable[[], None] = lambda: None):
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / CHECKPOINT_NAME
        self.map_id, self.profile_name, self.settings = map_id, profile_name, settings
        self.timings, self.on_error, self.after_write = timings, on_error, after_write
        check_writable(self.run_dir)
        for folder in (self.run_dir, self.run_dir / SAVED_MAPS_DIR, self.run_dir / EXPORTS_DIR):
            for f in remove_leftovers(folder):
                log.warning("removed %s, left by a write that did not finish", f)
        self.last: dict | None = None  # the newest write that landed
        self.last_time = time.monotonic()
        self._writer: threading.Thread | None = None

    # ----------------------------------------------------------------- reading
    def read_mapper(self, path: Path) -> tuple[Mapper, dict]:
        """The map saved in ``path`` and the file's header; CheckpointError / ValueError / KeyError
        when it cannot be used for this map: another map id, or mapping settings other than this
        service's (loaded under other settings the map would change silently: its distances move)."""
        header, _ = read_header(path)
        if header.get("map_id") != self.map_id:
            raise CheckpointError(f"checkpoint is of map {header.get('map_id')!r}, not {self.map_id!r}")
        # where it runs and how it is read (READ_SETTINGS) are no difference: it is served with this service's
        diff = settings_differences(saved_settings(header, path), self.settings, ("mapper.device", *READ_SETTINGS))
        if diff:
            shown = "; ".join(diff[:6]) + (f"; and {len(diff) - 6} more" if len(diff) > 6 else "")
            profile = str(header.get("profile", "?"))[:64]
            raise CheckpointError(f"checkpoint was saved under other mapping settings (profile {profile!r}): "
                                  f"{shown}. Serve it with the profile it was saved with, or move the file away "
                                  "to start a new map")
        return Mapper.load(path, self.settings), header

    def resume(self) -> tuple[Mapper | None, dict | None]:
        """(mapper, where it came from) from the newest checkpoint, or from the previous one when the
        newest is missing or unreadable (``fallback`` says so); (None, None) when neither exists;
        CheckpointError when neither can be read."""
        newest, prev = self.path, previous_path(self.path)
        if not newest.exists() and not prev.exists():
            log.info("no checkpoint at %s: starting a new map", newest)
            return None, None
        errors = []
        for path in (newest, prev):
            if not path.exists():
                errors.append(f"{path}: missing")
                continue
            try:
                mapper, header = self.read_mapper(path)
            except (CheckpointError, ValueError, KeyError) as e:
                errors.append(f"{path}: {e}")
                log.error("cannot resume from %s: %s", path, e)
                continue
            resumed = {"path": str(path), "frames_mapped": header["frames_mapped"],
                       "created_unix": header["created_unix"], "fallback": path == prev, "skipped": errors}
            if path == prev:
                log.warning("resumed from the previous checkpoint %s: %s", path, "; ".join(errors))
            stats = mapper.stats()
            log.info("resumed map %r from %s: %d frames, %d voxels, %d keyframes", self.map_id, path,
                     stats["frames_mapped"], stats["voxels"], stats["keyframes"])
            return mapper, resumed
        raise CheckpointError("cannot resume: " + "; ".join(errors))

    # ----------------------------------------------------------------- writing
    def capture(self, mapper: Mapper) -> tuple[dict, dict[str, np.ndarray]]:
        """(header, arrays) of the map now (call between frames, on the mapper's thread)."""
        return mapper.capture(self.map_id, self.profile_name)

    def write(self, captured: tuple[dict, dict], futures: list[Future] | None = None,
              path: Path | None = None) -> bool:
        """Write a capture to ``path`` (the resume checkpoint by default); resolve ``futures`` with
        the write's info or a QueryError. False when it failed (reported through ``on_error``)."""
        header, arrays = captured
        path = self.path if path is None else Path(path)
        t0 = time.perf_counter()
        try:
            size = write_checkpoint(path, header, arrays)
            info = {"path": str(path), "frames_mapped": header["frames_mapped"], "bytes": size,
                    "seconds": round(time.perf_counter() - t0, 3), "unix": time.time()}
            if path == self.path:
                self.last = info
            self.timings.add("checkpoint", time.perf_counter() - t0)
            self.after_write()
            log.info("checkpoint: %d frames, %.1f MB in %.2f s -> %s", info["frames_mapped"], size / 1e6,
                     info["seconds"], path)
            for f in futures or []:
                f.set_result(info)
            return True
        except Exception as e:
            self.on_error("checkpoint", f"{type(e).__name__}: {e}")
            for f in futures or []:
                f.set_exception(QueryError(f"checkpoint failed: {e}"))
            return False

    def write_async(self, captured: tuple[dict, dict], futures: list[Future] | None = None,
                    path: Path | None = None) -> None:
        """Write on the writer thread, after the previous write has landed (checkpoints stay ordered)."""
        self.last_time = time.monotonic()
        self.join()
        self._writer = threading.Thread(target=self.write, args=(captured, futures, path), name="h3edge-ckpt",
                                        daemon=True)
        self._writer.start()

    def due(self, mapper: Mapper, interval_s: float) -> bool:
        """True when a periodic checkpoint is due: ``interval_s`` passed and the map has new frames."""
        return (interval_s > 0 and time.monotonic() - self.last_time > interval_s and not mapper.empty
                and mapper.frames_mapped > (self.last or {}).get("frames_mapped", 0))

    def join(self, timeout: float | None = None) -> None:
        if self._writer is not None and self._writer.is_alive():
            self._writer.join(timeout)

    # ------------------------------------------------------- named saves / loads
    @staticmethod
    def check_room(path: Path, limit: int) -> None:
        """QueryError when ``path`` is a new name and its folder already holds ``limit`` files of its
        kind (scratch files not counted); writing over an existing name is always allowed."""
        if path.exists() or not path.parent.is_dir():
            return
        kept = sum(1 for f in path.parent.iterdir() if f.suffix == path.suffix)
        if kept >= limit:
            raise QueryError(f"{path.parent.name}/ holds {kept} {path.suffix} files, the most this service keeps "
                             f"(max_named_files): save over an existing name, or delete some")
    def named_path(self, name: str, folder: str = SAVED_MAPS_DIR, suffix: str = ".h3ckpt") -> Path:
        """``<run_dir>/<folder>/<name><suffix>`` for a plain file name (letters, digits, ``_ . -``, at
        most 64, no path separators); QueryError for anything else."""
        if not isinstance(name, str) or not _NAME.fullmatch(name) or ".." in name:
            raise QueryError(f"name {name!r}: use 1-64 letters, digits, '_', '.' or '-' (a file name under "
                             f"{self.run_dir / folder}, no path)")
        stem = name[: -len(suffix)] if name.endswith(suffix) else name
        return self.run_dir / folder / f"{stem}{suffix}"
