"""Training apart from integration: a thread that runs the mapper's training steps back to back
while frames are integrated on the caller's thread (:meth:`MapEngine.integrate`).

Each step is :meth:`MapEngine.train_between_frames` (the selected keyframes and the newest
integrated frame no step has used yet); it holds the map lock only to draw its rays and to apply
its updates, and gives way there to integration, snapshots and checkpoints
(:meth:`MapEngine.exclusive`): its forward and backward passes run beside integration, on the other
core, so a frame waits at most for a step's ray draw or update and training never waits for a
frame. The thread runs ``[mapper] training_nice`` nice levels below integration
(:mod:`h3edge.mapping.threads`): when both want a core, a frame's integration gets it. When there
is nothing to train on yet (no keyframe), the thread polls every ``idle_s``. A step that raises is
logged, counted in :attr:`errors` and handed to ``on_error``; the loop goes on.

Integration and training both call numba's parallel kernels, now from two threads: that needs a
thread-safe numba threading layer (OpenMP or TBB; numba picks one when it finds it). Numba's own
``workqueue`` layer is not, and :meth:`BackgroundTraining.start` refuses to run on it.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable

from h3edge.mapping.engine import MapEngine
from h3edge.mapping.threads import lower_thread_priority, size_pools

log = logging.getLogger(__name__)


class BackgroundTraining:
    """Runs ``mapper``'s training steps on a thread of its own between :meth:`start` and
    :meth:`stop`. ``with mapper.exclusive():`` holds the steps' map updates off (a copy of the
    map), :meth:`paused` the steps themselves; ``mapper`` is read each step, so assigning another
    mapper (a load) takes effect at once."""

    def __init__(self, mapper: MapEngine, idle_s: float = 0.01, on_error: Callable[[Exception], None] | None = None,
                 unconditional: bool = False):
        self.mapper = mapper
        # True: every step is MapEngine.train_once (the library's start_training), whatever the
        # profile's mapper.train_between_frames says
        self.unconditional = unconditional
        self.idle_s = idle_s
        self.on_error = on_error  # called on the training thread with a step's exception
        self.errors = 0  # steps that raised
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._turn = threading.Condition()  # paused() against the step in progress
        self._pauses = 0
        self._in_step = False

    def start(self) -> BackgroundTraining:
        """Start the training thread (RuntimeError on numba's thread-unsafe workqueue layer)."""
        if self._thread is not None and self._thread.is_alive():
            return self
        _check_threading_layer()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="h3edge-training", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 30.0) -> None:
        """Stop after the step in progress."""
        self._stop.set()
        with self._turn:
            self._turn.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    @contextlib.contextmanager
    def paused(self):
        """No step runs inside this block, not even its forward and backward passes (which
        :meth:`MapEngine.exclusive` lets finish): the step in progress ends first. For work that must
        have the machine to itself (a benchmark's scoring, whose time does not count)."""
        with self._turn:
            self._pauses += 1
            self._turn.wait_for(lambda: not self._in_step)
        try:
            yield
        finally:
            with self._turn:
                self._pauses -= 1
                self._turn.notify_all()

    def _run(self) -> None:
        cfg = self.mapper.cfg
        size_pools(cfg.threads)
        lower_thread_priority(cfg.training_nice)  # before its first parallel region starts workers
        while not self._stop.is_set():
            with self._turn:
                self._turn.wait_for(lambda: self._pauses == 0 or self._stop.is_set())
                if self._stop.is_set():
                    break
                self._in_step = True
            try:
                step = self.mapper.train_once if self.unconditional else self.mapper.train_between_frames
                trained = step() is not None
            except Exception as e:  # same policy as a frame: log, count, go on
                log.exception("background training step failed")
                self.errors += 1
                trained = False
                if self.on_error is not None:
                    self.on_error(e)
            finally:
                with self._turn:
                    self._in_step = False
                    self._turn.notify_all()
            if not trained:
                self._stop.wait(self.idle_s)


def _check_threading_layer() -> None:
    import numba
    import numpy as np

    from h3edge.geometry.camera import Intrinsics, backproject

    backproject(np.ones((2, 2), np.float32), Intrinsics(2, 2, 1.0, 1.0, 1.0, 1.0))  # a parallel kernel: layer chosen
    if numba.threading_layer() == "workqueue":
        raise RuntimeError("training on its own thread needs a thread-safe numba threading layer (OpenMP: "
                           "libgomp, or TBB >= 2021.6); only numba's workqueue layer is available here")
