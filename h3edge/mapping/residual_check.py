"""How much of the colour field's trained residual over the colour base the frames it has not seen
confirm: the gain renders apply to it.

Where the colour base (:mod:`h3edge.mapping.color_base`) knows a colour b, the field's colour is
sigmoid(logit(b) + g (z - z0)) (:func:`~h3edge.mapping.color_base.compose`): z - z0 the colour
MLP's residual, trained with g = 1 on the keyframes' pixels. Whether that residual carries to views
no step used depends on the sequence: on the synthetic scenes it adds the detail a 1 cm cell cannot
hold (30 s still: +0.6 dB over the base alone); on the real Kinect set the keyframes disagree
(auto-exposure, registration) and the residual fits their disagreement, so held-out views render
worse with it than with the base alone (D53-8: 17.14 / 0.588 against 17.26 / 0.599).

Every frame that arrives is such a view. Before the colour base fuses it, every
:data:`PROBE_EVERY`-th frame leaves a probe: :data:`PROBE_PIXELS` of its valid pixels, their
measured surface points and the base's colour there without this frame (:func:`take_probe`). The
training thread (it owns the colour MLP) scores the composition at each gain of :data:`GAINS`
against the pixels' colours where the base knows one (:meth:`ResidualCheck.score`); the squared
errors are summed with each probe's weight decaying by :data:`FORGET` per probe (the residual
changes as training goes on), and the gain with the least sum is the one renders apply, once
:data:`MIN_SAMPLES` pixels have been scored (1 until then: the residual as trained).

Cost: a probe's base reads on the integration helper thread (2,048 points: well under a
millisecond); the colour MLP on those points on the training thread, every third frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from h3edge.geometry.camera import Intrinsics, pixels_to_camera
from h3edge.mapping.color_base import ColorBase, compose

GAINS = (0.0, 0.25, 0.5, 0.75, 1.0)  # gains on the residual scored (1: as trained)
PROBE_PIXELS = 2048  # pixels a probe scores
PROBE_EVERY = 3  # frames between probes
FORGET = 0.9  # the weight a probe's errors keep per later probe (about the last 10 probes count)
MIN_SAMPLES = 4096  # pixels scored (forgetting counted) before the gain may leave 1


@dataclass
class ResidualProbe:
    """A frame's pixels no training step has used, at their measured surface points: world points
    (N, 3) float32 metres, the pixels' colours (N, 3) float32 in [0, 1], and the colour base's colour
    there (N, 3) float32 before the frame was fused (only pixels where the base knew one)."""

    points: np.ndarray
    target: np.ndarray
    base: np.ndarray


def take_probe(base: ColorBase, color: np.ndarray, depth: np.ndarray, pix: np.ndarray, intr: Intrinsics,
               c2w: np.ndarray, frame_index: int) -> ResidualProbe | None:
    """A probe of a frame about to be fused into ``base``: up to :data:`PROBE_PIXELS` of its valid
    pixels ``pix`` (flat indices into the (H, W) images; an even spread, shifted frame to frame),
    colour uint8 (H, W, 3), depth float32 (H, W) metres, ``c2w`` camera-to-world (OpenCV optical).
    None where the base knows none of them."""
    if len(pix) == 0 or len(base) == 0:
        return None
    step = max(1, len(pix) // PROBE_PIXELS)
    pick = pix[(frame_index % step) + step * np.arange(min(PROBE_PIXELS, len(pix)))]
    pose = np.asarray(c2w, np.float64)
    v, u = np.divmod(pick, intr.width)
    cam = pixels_to_camera(u, v, depth.reshape(-1)[pick].astype(np.float64), intr)
    points = (cam @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
    rgb, known = base.sample(torch.from_numpy(points))
    known = known.numpy()
    if not known.any():
        return None
    target = color.reshape(-1, 3)[pick[known]].astype(np.float32) / 255.0
    return ResidualProbe(points[known], target, rgb.numpy()[known])


class ResidualCheck:
    """The squared colour errors of fresh frames' probes at each gain of :data:`GAINS` (forgetting
    older probes) and the gain with the least: :attr:`gain`."""

    def __init__(self):
        self.sse = np.zeros(len(GAINS))  # forgetting-weighted sums of squared errors, per gain
        self.samples = 0.0  # forgetting-weighted pixels scored
        self.probes = 0  # probes scored
        self.gain = 1.0

    @torch.no_grad()
    def score(self, field, probe: ResidualProbe, voxel_index: torch.Tensor) -> float:
        """Score ``probe`` with the colour MLP of ``field`` (:meth:`Field.color_field`, at each
        point's leaf voxel ``voxel_index`` (N,) int64, -1 outside the map; those points are left
        out) and update :attr:`gain`; returns it. Runs on the field's device."""
        keep = voxel_index >= 0
        if not bool(keep.any()):
            return self.gain
        dev = voxel_index.device
        pts = torch.from_numpy(probe.points).to(dev)[keep]
        target = torch.from_numpy(probe.target).to(dev)[keep]
        base = torch.from_numpy(probe.base).to(dev)[keep]
        rgb, neutral = field.color_field(pts, voxel_index[keep])
        rgb, neutral = rgb.to(torch.float32), neutral.to(torch.float32)
        known = torch.ones(len(pts), dtype=torch.bool, device=dev)
        sse = torch.stack([((compose(rgb, base, known, neutral, g) - target) ** 2).sum() for g in GAINS])
        self.sse = FORGET * self.sse + sse.cpu().numpy().astype(np.float64)
        self.samples = FORGET * self.samples + len(pts)
        self.probes += 1
        if self.samples >= MIN_SAMPLES:
            self.gain = float(GAINS[int(np.argmin(self.sse))])
        return self.gain

    def state_dict(self) -> dict:
        """JSON-able state (the sums, the count, the gain)."""
        return {"sse": self.sse.tolist(), "samples": self.samples, "probes": self.probes, "gain": self.gain}

    def load_state_dict(self, state: dict) -> None:
        """Take :meth:`state_dict`'s; ValueError where it does not fit :data:`GAINS` or its gain is not one of them."""
        sse = np.asarray(state["sse"], np.float64)
        gain = float(state["gain"])
        if sse.shape != (len(GAINS),) or not np.isfinite(sse).all() or gain not in GAINS:
            raise ValueError(f"residual check state does not fit the gains {GAINS}: {state}")
        self.sse, self.samples, self.probes, self.gain = sse, float(state["samples"]), int(state["probes"]), gain
