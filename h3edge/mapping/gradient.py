"""The colour gradient g of H3-Mapping (weak-texture test, keyframe score).

Operator, as the authors compute it: the 3x3 8-neighbour Laplacian [[1,1,1],[1,-8,1],[1,1,1]]
of RGB in [0, 1], absolute values summed over the three channels (range 0..24), set to 0 where
the depth Laplacian (same kernel, metres) exceeds ``depth_jump`` so that occlusion edges do not
count as texture. The paper's tr_weak = 0.2 is on this scale.
"""

from __future__ import annotations

import cv2
import numpy as np

_KERNEL = np.array([[1, 1, 1], [1, -8, 1], [1, 1, 1]], np.float32)


def color_gradient(rgb: np.ndarray, depth: np.ndarray | None = None, depth_jump: float = 0.01) -> np.ndarray:
    """Per-pixel g (H, W) float32 for uint8 RGB (H, W, 3) and optional depth (H, W) metres."""
    img = rgb.astype(np.float32) * np.float32(1.0 / 255.0)
    g = np.abs(cv2.filter2D(img, cv2.CV_32F, _KERNEL, borderType=cv2.BORDER_REPLICATE)).sum(axis=-1)
    if depth is not None:
        dl = np.abs(cv2.filter2D(depth.astype(np.float32), cv2.CV_32F, _KERNEL, borderType=cv2.BORDER_REPLICATE))
        g[(dl > depth_jump) | (depth <= 0)] = 0.0
    return g
