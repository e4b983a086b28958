"""Pose buffer: associates frames to poses by timestamp (SLERP rotation + linear translation).

Poses arrive on their own key at their own rate and may come late, out of order or twice. The
buffer keeps ``capacity`` poses sorted by time; when full, it lets go of the pose farthest in time
from the stream's present (the newest frame stamp looked up, before any the host clock), the oldest
or the newest: a flood of poses stamped ahead of the present pushes out each other, not the present
ones. :meth:`PoseBuffer.lookup` answers a frame timestamp with

* ``("ok", pose)``: an exact match, or the interpolation between the poses just before and just
  after it when they are at most ``max_gap`` apart;
* ``("wait", None)``: no pose at or after the timestamp yet, or none within ``max_gap`` after it
  (a pose far ahead counts as not come yet: the frame's own next pose may still come, so one pose
  stamped far ahead does not make later frames misses; the caller waits a little);
* ``("miss", reason)``: the poses around it are too far apart in time, or imply a motion faster
  than ``max_speed`` (one of them is an outlier: the frame is refused, the buffer is not changed,
  so one bad pose affects only the frames stamped next to it and ages out with the buffer), or
  the frame is older than the buffer.

Thread-safe: the zenoh callback adds, the mapper thread looks up.
"""

from __future__ import annotations

import bisect
import threading
import time

import numpy as np

from h3edge.geometry.camera import rigid_error
from h3edge.geometry.poses import interpolate_pose


class PoseBuffer:
    def __init__(self, capacity: int = 4096, max_gap_s: float = 0.1, max_speed: float = 20.0):
        self.capacity = capacity
        self.max_gap_ns = int(max_gap_s * 1e9)
        self.max_speed = max_speed  # m/s between two buffered poses a frame is interpolated from
        self._t: list[int] = []
        self._poses: list[np.ndarray] = []
        self._present: int | None = None  # ns: the newest frame stamp looked up
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._t)

    def add(self, timestamp_ns: int, pose: np.ndarray) -> str:
        """Insert a pose; returns '' or why it was refused ('duplicate', 'bad_pose')."""
        pose = np.asarray(pose, np.float64)
        if rigid_error(pose):
            return "bad_pose"
        with self._lock:
            i = bisect.bisect_left(self._t, timestamp_ns)
            if i < len(self._t) and self._t[i] == timestamp_ns:
                return "duplicate"
            self._t.insert(i, timestamp_ns)
            self._poses.insert(i, pose)
            if len(self._t) > self.capacity:
                present = self._present if self._present is not None else time.time_ns()
                end = 0 if present - self._t[0] >= self._t[-1] - present else -1  # the farther from the present
                del self._t[end], self._poses[end]
        return ""

    def lookup(self, timestamp_ns: int) -> tuple[str, object]:
        with self._lock:
            self._present = timestamp_ns if self._present is None else max(self._present, timestamp_ns)
            if not self._t or timestamp_ns > self._t[-1]:
                return "wait", None
            i = bisect.bisect_left(self._t, timestamp_ns)
            if self._t[i] == timestamp_ns:
                return "ok", self._poses[i].copy()
            if i == 0:
                return "miss", f"frame is older than every buffered pose ({(self._t[0] - timestamp_ns) / 1e6:.1f} ms)"
            t0, t1 = self._t[i - 1], self._t[i]
            a, b = self._poses[i - 1], self._poses[i]
        if t1 - timestamp_ns > self.max_gap_ns:
            return "wait", None  # the next pose is far ahead: the frame's own may still come, as after the last
        if t1 - t0 > self.max_gap_ns:
            return (
                "miss",
                f"poses around the frame are {(t1 - t0) / 1e6:.1f} ms apart (max {self.max_gap_ns / 1e6:.1f})",
            )
        speed = float(np.linalg.norm(b[:3, 3] - a[:3, 3])) / ((t1 - t0) * 1e-9)
        if speed > self.max_speed:
            return "miss", (f"the poses around the frame imply {speed:.3g} m/s (max {self.max_speed:g}): "
                            "one of them is an outlier")
        return "ok", interpolate_pose(a, b, (timestamp_ns - t0) / (t1 - t0))
