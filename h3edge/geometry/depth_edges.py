"""Depth-edge pixels: the near side of every depth discontinuity (measured wrong), its far side,
and both sides (:func:`depth_discontinuities`, where the colour gradient is not texture).

Structured-light and time-of-flight sensors blur depth edges: pixels along a silhouette take the
foreground's depth a few pixels past the object's true outline, or a depth between foreground and
background (mixed, "flying" pixels). Mapped, both put surface where other views see free space.
:func:`near_side_of_edges` marks the pixels that have a valid neighbour markedly farther within a
small window: the foreground's rim and the flying pixels, never the background beside them, whose
rays still carve the free space along the silhouette. :func:`far_side_of_edges` marks that
background: the pixels whose rays pass just beside a foreground outline, where a map's surface
bulges into free space unless training rays carve it.

A jump is relative to depth, but a surface seen at a grazing angle also changes depth across a few
pixels, the more so the wider each pixel's angle: at 160x120 with a 95 px focal length a 5 % jump
over 2 px is any surface beyond 67 degrees of incidence (a third of a room's view), at 640x480 with
525 px only beyond 86 degrees. :func:`discontinuity_jump` raises the jump to what a surface at a
given incidence gives over the window, so the tests mean the same at every resolution.

Usage::

    jump = discontinuity_jump(0.05, radius=2, focal=min(fx, fy), max_incidence=80.0)
    depth = np.where(near_side_of_edges(depth, radius=2, jump=jump), 0.0, depth)
    beside = np.flatnonzero(far_side_of_edges(depth, radius=8, jump=0.05))
"""

from __future__ import annotations

import cv2
import numpy as np


def discontinuity_jump(jump: float, radius: int, focal: float, max_incidence: float) -> float:
    """The relative depth jump within ``radius`` pixels that counts as a depth edge: ``jump``, or
    the change a surface seen at ``max_incidence`` degrees (between ray and normal) shows across
    ``radius`` pixels of a camera with ``focal`` px, radius / focal * tan(incidence), whichever is
    larger."""
    return max(float(jump), radius / float(focal) * float(np.tan(np.radians(max_incidence))))


def near_side_of_edges(depth: np.ndarray, radius: int, jump: float) -> np.ndarray:
    """(H, W) bool: valid pixels of ``depth`` (m, 0 = invalid) with a neighbour within ``radius``
    pixels (a square window) farther by more than ``jump`` times their own depth."""
    d = np.asarray(depth, np.float32)
    if radius <= 0:
        return np.zeros(d.shape, bool)
    farthest = cv2.dilate(d, np.ones((2 * radius + 1, 2 * radius + 1), np.uint8))
    return (d > 0) & (farthest > d * (1.0 + jump))


def far_side_of_edges(depth: np.ndarray, radius: int, jump: float, step: int = 3, near_too: bool = False) -> np.ndarray:
    """(H, W) bool: valid pixels of ``depth`` (m, 0 = invalid) within ``radius`` pixels (a square
    window) of a foreground outline and farther than it by more than ``jump`` times its depth: the
    background just beside a silhouette, whose rays pass the outline (and see through the gaps of a
    slatted or thin object). An outline pixel is a valid pixel with a neighbour within ``step``
    pixels farther by ``jump`` (:func:`near_side_of_edges`: a discontinuity, reached across the
    rim :attr:`MapperConfig.edge_radius` leaves out), so a surface seen at a grazing angle, whose
    depth grows steadily across the window, is not taken for an edge. ``near_too``: the foreground
    within ``radius`` of its outline as well (both sides of every edge)."""
    d = np.asarray(depth, np.float32)
    if radius <= 0:
        return np.zeros(d.shape, bool)
    on_outline = near_side_of_edges(d, step, jump)
    window = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    if near_too:
        return (d > 0) & (cv2.dilate(on_outline.astype(np.uint8), window) > 0)
    nearest = cv2.erode(np.where(on_outline, d, np.float32(1e30)), window)  # 1e30: no outline near
    return (d > 0) & (nearest * np.float32(1.0 + jump) < d)


def depth_discontinuities(depth: np.ndarray, jump: float) -> np.ndarray:
    """(H, W) bool: the pixels where ``depth`` (m, 0 = invalid) is not one surface across their 3x3
    window: invalid pixels, valid ones beside an invalid one, and valid ones with a valid neighbour
    nearer or farther by more than ``jump`` times their own depth (both sides of an occlusion
    edge). The test is relative, like the sensors' noise and quantisation (a Kinect's depth steps
    by ~1 % of the depth at 2-3 m): an absolute threshold on a depth Laplacian marks half a real
    Kinect frame at 1 cm, as if every pixel were an occlusion."""
    d = np.asarray(depth, np.float32)
    valid = d > 0
    window = np.ones((3, 3), np.uint8)
    nearest = cv2.erode(np.where(valid, d, np.float32(np.inf)), window, borderType=cv2.BORDER_REPLICATE)
    not_all_valid = cv2.erode(valid.astype(np.uint8), window, borderType=cv2.BORDER_REPLICATE) == 0  # also ~valid
    return not_all_valid | near_side_of_edges(d, 1, jump) | (nearest * np.float32(1.0 + jump) < d)
