"""Training apart from integration: a thread that runs the mapper's training steps back to back
while frames are integrated on the caller's thread (:meth:`Mapper.integrate`).

Each step is :meth:`Mapper.train_between_frames` (the selected keyframes and the newest
integrated frame no step has used yet); it holds the map lock for the step and gives way to
integration, snapshots and checkpoints (:meth:`Mapper.exclusive`) between steps, so a frame waits
for at most the step in progress and training never waits for a frame. When there is nothing to
train on yet (no keyframe), the thread polls every ``idle_s``. A step that raises is logged and
counted in :attr:`errors`; the loop goes on.
"""

from __future__ import annotations

import logging
import threading

from h3edge.mapping.mapper import Mapper

log = logging.getLogger(__name__)


class BackgroundTraining:
    """Runs ``mapper``'s training steps on a thread of its own between :meth:`start` and
    :meth:`stop`. ``with mapper.exclusive():`` holds the steps off (an evaluation, a copy of the
    map); ``mapper`` is read each step, so assigning another mapper (a load) takes effect at once."""

    def __init__(self, mapper: Mapper, idle_s: float = 0.01):
        self.mapper = mapper
        self.idle_s = idle_s
        self.steps = 0  # steps this thread ran
        self.errors = 0  # steps that raised
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> BackgroundTraining:
        if self._thread is not None and self._thread.is_alive():
            return self
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="h3edge-training", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 30.0) -> None:
        """Stop after the step in progress."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                trained = self.mapper.train_between_frames() is not None
            except Exception:  # same policy as a frame: log, count, go on
                log.exception("background training step failed")
                self.errors += 1
                trained = False
            if trained:
                self.steps += 1
            else:
                self._stop.wait(self.idle_s)
