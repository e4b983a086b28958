"""Simulated RGB-D sensor: renders the room and optionally degrades depth like a real camera.

Noise model (off by default): axial Gaussian noise sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m
(Nguyen et al., 3DIMPVT 2012, Kinect v1), and missing depth at depth discontinuities (|depth
Laplacian| > 5 cm, dilated by one pixel), on grazing surfaces (|cos| < 0.15), beyond
``max_depth`` and in random small blobs covering about ``dropout`` of the image. Optionally
(``edge_spill_px`` > 0) the foreground spills past its outline onto the background behind it by
that many pixels, as structured-light sensors' block matching does, the outermost ring at a depth
between the two (mixed "flying" pixels): applied before the missing depth, so the spill outlives the
holes along the true edge as on a Kinect.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from h3edge.geometry.camera import Intrinsics
from h3edge.geometry.raycast import MeshRaycaster
from h3edge.sim.scene import Room


@dataclass(frozen=True)
class SensorModel:
    depth_noise: bool = False
    missing_depth: bool = False
    dropout: float = 0.01
    max_depth: float = 10.0
    edge_spill_px: int = 0  # pixels the foreground's depth spills past its outline (0: none)


class RoomRenderer:
    """Renders colour (uint8 RGB) and z-depth (float32 metres, 0 = no return) of a :class:`Room`."""

    def __init__(self, room: Room):
        self.room = room
        self.raycaster = MeshRaycaster(room.vertices, room.faces)

    def render(self, intr: Intrinsics, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Noise-free colour, depth and the |cos| of incidence per pixel."""
        hits = self.raycaster.hits(intr, c2w)
        rgb = self.room.atlas.sample(hits, intr)
        return np.clip(np.rint(rgb), 0, 255).astype(np.uint8), hits.depth, hits.cos_incidence


def degrade_depth(depth: np.ndarray, cos_incidence: np.ndarray, model: SensorModel,
                  rng: np.random.Generator) -> np.ndarray:
    """Apply the sensor model to a clean depth image; returns a new float32 array."""
    d = depth.astype(np.float32).copy()
    valid = d > 0
    if model.depth_noise:
        sigma = 0.0012 + 0.0019 * (d - 0.4) ** 2
        d = np.where(valid, d + sigma * rng.standard_normal(d.shape).astype(np.float32), 0.0)
    if model.edge_spill_px > 0:
        d = spill_foreground(d, model.edge_spill_px, rng)
    if model.missing_depth:
        # depth discontinuities: the depth Laplacian is ~0 on any plane, even at grazing angles
        lap = np.abs(cv2.Laplacian(depth.astype(np.float32), cv2.CV_32F, ksize=1))
        jump = cv2.dilate((lap > 0.05).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        blobs = rng.random((depth.shape[0] // 8 + 1, depth.shape[1] // 8 + 1)) < model.dropout
        blobs = cv2.resize(blobs.astype(np.uint8), (depth.shape[1], depth.shape[0]),
                           interpolation=cv2.INTER_NEAREST).astype(bool)
        drop = jump | blobs | (cos_incidence < 0.15) | (d > model.max_depth)
        d[drop] = 0.0
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d


def spill_foreground(depth: np.ndarray, px: int, rng: np.random.Generator, jump: float = 0.05) -> np.ndarray:
    """``depth`` with every background pixel within ``px`` pixels of a foreground nearer by more than
    ``jump`` of its depth taking that foreground's depth; of the outermost ring (exactly ``px``
    away), half the pixels take a depth uniformly between the two instead (flying pixels)."""
    far = np.where(depth > 0, depth, np.float32(np.inf)).astype(np.float32)
    near = cv2.erode(far, np.ones((2 * px + 1, 2 * px + 1), np.uint8))
    inner = cv2.erode(far, np.ones((2 * px - 1, 2 * px - 1), np.uint8)) if px > 1 else far
    spill = (depth > 0) & (near < depth * (1.0 - jump))
    ring = spill & ~(inner < depth * (1.0 - jump))
    mixed = ring & (rng.random(depth.shape) < 0.5)
    out = np.where(spill, near, depth).astype(np.float32)
    out[mixed] = (near + (depth - near) * rng.random(depth.shape, dtype=np.float32))[mixed]
    return out
