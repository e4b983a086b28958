"""Depth-edge pixels a range sensor measures wrong: the near side of every depth discontinuity.

Structured-light and time-of-flight sensors blur depth edges: pixels along a silhouette take the
foreground's depth a few pixels past the object's true outline, or a depth between foreground and
background (mixed, "flying" pixels). Mapped, both put surface where other views see free space.
:func:`near_side_of_edges` marks the pixels that have a valid neighbour markedly farther within a
small window: the foreground's rim and the flying pixels, never the background beside them, whose
rays still carve the free space along the silhouette.

Usage::

    depth = np.where(near_side_of_edges(depth, radius=2, jump=0.05), 0.0, depth)
"""

from __future__ import annotations

import cv2
import numpy as np


def near_side_of_edges(depth: np.ndarray, radius: int, jump: float) -> np.ndarray:
    """(H, W) bool: valid pixels of ``depth`` (m, 0 = invalid) with a neighbour within ``radius``
    pixels (a square window) farther by more than ``jump`` times their own depth."""
    d = np.asarray(depth, np.float32)
    if radius <= 0:
        return np.zeros(d.shape, bool)
    farthest = cv2.dilate(d, np.ones((2 * radius + 1, 2 * radius + 1), np.uint8))
    return (d > 0) & (farthest > d * (1.0 + jump))
