"""The training steps' own CUDA stream, and the order kept between it and the default stream.

On CUDA the steps a training thread runs (:meth:`MapEngine.train_once`) enqueue their kernels on a
stream of their own, so that the work of integration, snapshots and queries (the default stream,
on their threads) does not queue behind a step's forward and backward passes: a host-to-device
copy from pageable memory waits for everything before it on its stream, and on one stream
integration's copies of new priors would wait for the step in flight. Order is kept at the map
lock (:meth:`MapEngine.exclusive` and the training turns):

- a training turn (a step's ray draw, its update) starts with the training stream waiting for the
  default stream's work so far: the priors and voxels integration put up, a render still reading
  the parameters the update will write;
- it ends by recording an event on the training stream (the update);
- an :meth:`MapEngine.exclusive` caller makes the default stream wait for that event: a snapshot,
  a checkpoint or integration's growth of the priors sees the step's update, and waits for
  nothing the next step enqueues after it (its forward pass runs beside).

Tensors made on the default stream that a step reads (the priors, grown by integration) are
marked as used on the training stream (``record_stream``), so that the caching allocator does
not hand their memory to the default stream while a step's kernels may still read it.

On a CPU every method is a no-op (one stream: the host).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable

import torch


class TrainingStream:
    """The training stream of a map on ``device`` (module docstring); no-ops unless CUDA."""

    def __init__(self, device: torch.device):
        self.device = torch.device(device)
        self.cuda = self.device.type == "cuda"
        self.stream = torch.cuda.Stream(self.device) if self.cuda else None
        self._updated = None  # torch.cuda.Event recorded at the end of the last training turn

    def active(self):
        """A context in which this thread's CUDA work goes to the training stream."""
        return torch.cuda.stream(self.stream) if self.cuda else contextlib.nullcontext()

    def follow_default(self, shared: Iterable[torch.Tensor] = ()) -> None:
        """At a training turn's start (map lock held): the training stream waits for the default
        stream's work so far; ``shared`` tensors (made on the default stream) are marked as used
        on the training stream."""
        if not self.cuda:
            return
        self.stream.wait_stream(torch.cuda.default_stream(self.device))
        for t in shared:
            if t.device.type == "cuda":
                t.record_stream(self.stream)

    def mark_turn_end(self) -> None:
        """At a training turn's end (map lock held): record where the training stream is."""
        if self.cuda:
            event = torch.cuda.Event()
            event.record(self.stream)
            self._updated = event

    def before_exclusive_work(self) -> None:
        """At an exclusive caller's start (map lock held): its stream waits for the last training
        turn's end, not for the steps' work enqueued since."""
        if self.cuda and self._updated is not None:
            torch.cuda.current_stream(self.device).wait_event(self._updated)
