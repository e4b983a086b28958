"""The colour gradient g of H3-Mapping (weak-texture test, keyframe score).

Operator, as the authors compute it: the 3x3 8-neighbour Laplacian [[1,1,1],[1,-8,1],[1,1,1]]
of RGB in [0, 1], absolute values summed over the three channels (range 0..24). The paper's
tr_weak = 0.2 is on this scale.

Occlusion edges do not count as texture: g is 0 where the depth is not one surface across the
3x3 window (:func:`~h3edge.geometry.depth_edges.depth_discontinuities`, a jump relative to the
depth; the mapper passes its depth-edge jump, ``MapEngine.gradient_jump``). The authors' test, the
depth Laplacian above 1 cm, zeroes 45-65 % of the valid pixels of a real Kinect frame (its depth
steps by 1.2-2.6 cm at 2-3 m), and 98 % of the real kitchen's voxels then read as weak texture
(research/textures.md, "Occlusion edges in the colour gradient").
"""

from __future__ import annotations

import cv2
import numpy as np

from h3edge.geometry.depth_edges import depth_discontinuities

_KERNEL = np.array([[1, 1, 1], [1, -8, 1], [1, 1, 1]], np.float32)


def color_gradient(rgb: np.ndarray, depth: np.ndarray | None = None, jump: float | None = None) -> np.ndarray:
    """Per-pixel g (H, W) float32 for uint8 RGB (H, W, 3); with a depth (H, W) metres (0 = invalid),
    0 at its discontinuities larger than ``jump`` times the depth, at invalid pixels and beside them."""
    img = rgb.astype(np.float32) * np.float32(1.0 / 255.0)
    g = np.abs(cv2.filter2D(img, cv2.CV_32F, _KERNEL, borderType=cv2.BORDER_REPLICATE)).sum(axis=-1)
    if depth is not None:
        if jump is None:
            raise ValueError("color_gradient with a depth needs the relative jump of a depth edge")
        g[depth_discontinuities(depth, jump)] = 0.0
    return g
