"""The service's ingest: frames and poses as they arrive from the transport's threads.

Frames: the raw bytes go into a bounded queue (``queue_size`` deep); when it is full the oldest
waiting frame is dropped and counted as ``queue_full``, so a mapper slower than the camera maps
the newest frames and memory stays bounded. Nothing is decoded here: the mapper thread takes the
frames with :meth:`Ingest.pop`. Poses: parsed at once and buffered for association
(:class:`~h3edge.serving.association.PoseBuffer`); a pose that cannot be used (malformed, from
the future, non-rigid, duplicate, out of order) is a drop counted by reason. Neither path blocks
or raises into the transport's callback.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from h3edge.io.protocol import ProtocolError, decode_pose
from h3edge.profiling.timing import Timings
from h3edge.serving.association import PoseBuffer

log = logging.getLogger(__name__)


@dataclass
class PendingFrame:
    data: bytes
    received: float  # time.monotonic()


class Ingest:
    """Bounded frame queue, pose buffer and their counters (module docstring).

    ``on_error(code, text)`` is told of every refused message (the service's ``last_error``)."""

    def __init__(self, queue_size: int, max_future_s: float, poses: PoseBuffer, timings: Timings,
                 on_error: Callable[[str, str], None]):
        self.queue_size, self.max_future_s = queue_size, max_future_s
        self.poses, self.timings, self.on_error = poses, timings, on_error
        self._queue: collections.deque[PendingFrame] = collections.deque()
        self._cond = threading.Condition()
        self.counts = collections.Counter()  # frames_received, poses_received
        self.frame_drops = collections.Counter()  # queue_full
        self.pose_drops = collections.Counter()  # refused pose messages, by reason
        self.recent_received: collections.deque[float] = collections.deque(maxlen=300)

    def __len__(self) -> int:
        """Frames waiting."""
        return len(self._queue)

    # ------------------------------------------------------------ transport threads
    def submit_frame(self, data: bytes) -> None:
        """Queue a raw frame message; never blocks."""
        now = time.monotonic()
        t0 = time.perf_counter()
        with self._cond:
            self.counts["frames_received"] += 1
            self.recent_received.append(now)
            if len(self._queue) >= self.queue_size:
                self._queue.popleft()
                self.frame_drops["queue_full"] += 1
            self._queue.append(PendingFrame(bytes(data), now))
            self._cond.notify()
        self.timings.add("ingest", time.perf_counter() - t0)

    def submit_pose(self, data: bytes) -> None:
        """Parse and buffer a pose message; never raises (a pose that cannot be used is a drop)."""
        self.counts["poses_received"] += 1
        try:
            self._add_pose(data)
        except Exception as e:  # noqa: BLE001 - a bug must not escape into the zenoh callback
            log.exception("pose failed")
            self._pose_drop("internal_error_pose", f"{type(e).__name__}: {e}")

    def _add_pose(self, data: bytes) -> None:
        try:
            msg = decode_pose(data)
        except ProtocolError as e:
            self._pose_drop("malformed_pose", str(e))
            return
        if self.from_future(msg.timestamp_ns):
            self._pose_drop("future_pose", f"pose at {msg.timestamp_ns} ns is more than {self.max_future_s:g} s "
                                           "ahead of this host's clock")
            return
        self._buffer_pose(msg.timestamp_ns, msg.pose)

    def add_pose(self, timestamp_ns: int, pose) -> None:
        """Buffer a camera pose (optical -> world, 4x4) already decoded elsewhere (the ROS ingest);
        the same checks and drop counts as :meth:`submit_pose`."""
        self.counts["poses_received"] += 1
        if self.from_future(timestamp_ns):
            self._pose_drop("future_pose", f"pose at {timestamp_ns} ns is more than {self.max_future_s:g} s "
                                           "ahead of this host's clock")
            return
        self._buffer_pose(timestamp_ns, pose)

    def _buffer_pose(self, timestamp_ns: int, pose) -> None:
        why = self.poses.add(timestamp_ns, pose)
        if why:
            self._pose_drop(f"{why}_pose" if why != "bad_pose" else "bad_pose", f"pose at {timestamp_ns} ns: {why}")

    def _pose_drop(self, code: str, text: str) -> None:
        self.pose_drops[code] += 1
        self.on_error(code, text)

    # ------------------------------------------------------------ mapper thread
    def from_future(self, timestamp_ns: int) -> bool:
        """Stamped more than ``max_future_s`` ahead of this host's clock."""
        return timestamp_ns > time.time_ns() + int(self.max_future_s * 1e9)

    def pop(self) -> PendingFrame | None:
        """The oldest waiting frame, or None."""
        with self._cond:
            return self._queue.popleft() if self._queue else None

    def wait(self, timeout: float, stop: threading.Event) -> None:
        """Until a frame arrives, ``stop`` is set or ``timeout`` passes."""
        with self._cond:
            if not self._queue and not stop.is_set():
                self._cond.wait(timeout)

    def wake(self) -> None:
        """Wake a :meth:`wait` (a request or a stop for the mapper thread)."""
        with self._cond:
            self._cond.notify_all()
