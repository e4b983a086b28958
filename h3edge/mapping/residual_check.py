"""How much of the colour field's trained residual over the colour base the views training does not
fit confirm: the gain renders apply to it.

Where the colour base (:mod:`h3edge.mapping.color_base`) knows a colour b, the field's colour is
sigmoid(logit(b) + g (z - z0)) (:func:`~h3edge.mapping.color_base.compose`): z - z0 the colour
MLP's residual, trained with g = 1 on the keyframes' pixels. Whether that residual carries to views
no step fits depends on the sequence: on the synthetic scenes it adds the detail a 1 cm cell cannot
hold (30 s still: +0.6 dB over the base alone); on the real Kinect set the keyframes disagree
(auto-exposure, registration) and the residual fits their disagreement, so held-out views render
worse with it than with the base alone (D53-8: 17.14 / 0.588 against 17.26 / 0.599).

The frames that arrive and do not become keyframes are such views (a training step draws a few
hundred rays from the newest frame once; nothing else trains on them). Before the colour base fuses
it, every :data:`PROBE_EVERY`-th frame leaves a probe (:func:`take_probe`): :data:`PROBE_PIXELS` of
its valid pixels, their measured surface points and the base's colour there without this frame; a
frame that becomes a keyframe gives its probe up. :class:`ResidualCheck` keeps :data:`RESERVOIR`
probes, an even sample of every probe so far (reservoir sampling: the views of the whole sequence,
not its last second), and every :data:`RESCORE_STEPS` training steps the training thread (it owns
the colour MLP) scores the composition at each gain of :data:`GAINS` against the kept pixels'
colours with the MLP as it stands (:meth:`ResidualCheck.score`): the gain with the least squared
error is the one renders apply, once :data:`MIN_SAMPLES` pixels are kept (1 until then: the
residual as trained). Standing still, the scores follow the training, which goes on.

Cost: a probe's base reads on the integration helper thread (1,024 points: well under a
millisecond); the colour MLP on the kept points (32,768 at most) every eighth step on the training
thread; 1.2 MB kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from h3edge.geometry.camera import Intrinsics, pixels_to_camera
from h3edge.mapping.color_base import ColorBase, compose

GAINS = (0.0, 0.25, 0.5, 0.75, 1.0)  # gains on the residual scored (1: as trained)
PROBE_PIXELS = 1024  # pixels a probe keeps
PROBE_EVERY = 3  # frames between probes
RESERVOIR = 32  # probes kept (an even sample of all so far)
RESCORE_STEPS = 8  # training steps between scorings
MIN_SAMPLES = 4096  # pixels kept before the gain may leave 1
KEPT_BYTES = RESERVOIR * PROBE_PIXELS * 9 * 4  # the kept probes at most: point, colour, base colour (float32)


@dataclass
class ResidualProbe:
    """A frame's pixels no training step fits, at their measured surface points: world points
    (N, 3) float32 metres, the pixels' colours (N, 3) float32 in [0, 1], and the colour base's colour
    there (N, 3) float32 before the frame was fused (only pixels where the base knew one)."""

    points: np.ndarray
    target: np.ndarray
    base: np.ndarray


def take_probe(base: ColorBase, color: np.ndarray, depth: np.ndarray, pix: np.ndarray, intr: Intrinsics,
               c2w: np.ndarray, frame_index: int) -> ResidualProbe | None:
    """A probe of a frame about to be fused into ``base``: up to :data:`PROBE_PIXELS` of its valid
    pixels ``pix`` (flat indices into the (H, W) images; an even spread, shifted by ``frame_index``),
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
    """The kept probes (reservoir sampling, seeded) and the gain of :data:`GAINS` whose composition
    reads them best: :attr:`gain`."""

    def __init__(self, seed: int = 0):
        self.probes: list[ResidualProbe] = []
        self.seen = 0  # probes offered
        self.scored = 0  # scorings
        self.sse = np.zeros(len(GAINS))  # the last scoring's sums of squared errors, per gain
        self.gain = 1.0
        self._rng = np.random.default_rng(seed)

    def add(self, probe: ResidualProbe) -> None:
        """Offer a probe: kept while fewer than :data:`RESERVOIR` are, then in place of a kept one
        with probability :data:`RESERVOIR` / probes offered (an even sample of every probe)."""
        self.seen += 1
        if len(self.probes) < RESERVOIR:
            self.probes.append(probe)
            return
        slot = int(self._rng.integers(0, self.seen))
        if slot < RESERVOIR:
            self.probes[slot] = probe

    @property
    def nbytes(self) -> int:
        """Host bytes of the kept probes (at most :data:`KEPT_BYTES`)."""
        return sum(p.points.nbytes + p.target.nbytes + p.base.nbytes for p in self.probes)

    def points(self, probes: list[ResidualProbe] | None = None) -> np.ndarray:
        """The points of ``probes`` (default: the kept ones) (N, 3) float32 world metres, in order."""
        probes = self.probes if probes is None else probes
        return np.concatenate([p.points for p in probes]) if probes else np.zeros((0, 3), np.float32)

    @torch.no_grad()
    def score(self, field, voxel_index: torch.Tensor, probes: list[ResidualProbe] | None = None) -> float:
        """Score ``probes`` (default: the kept ones) with the colour MLP of ``field``
        (:meth:`Field.color_field`) at their points' leaf voxels ``voxel_index`` (N,) int64 (the
        probes' points in order; -1 outside the map: left out) and update :attr:`gain` (kept as it is
        below :data:`MIN_SAMPLES` points); returns it. Runs on the field's device."""
        probes = self.probes if probes is None else probes
        keep = voxel_index >= 0
        n = int(keep.sum())
        if n < MIN_SAMPLES:
            return self.gain
        dev = voxel_index.device
        cat = lambda name: torch.from_numpy(np.concatenate([getattr(p, name) for p in probes])).to(dev)[keep]  # noqa: E731
        pts, target, base = cat("points"), cat("target"), cat("base")
        rgb, neutral = field.color_field(pts, voxel_index[keep])
        rgb, neutral = rgb.to(torch.float32), neutral.to(torch.float32)
        known = torch.ones(n, dtype=torch.bool, device=dev)
        sse = torch.stack([((compose(rgb, base, known, neutral, g) - target) ** 2).sum() for g in GAINS])
        self.sse = sse.cpu().numpy().astype(np.float64)
        self.scored += 1
        self.gain = float(GAINS[int(np.argmin(self.sse))])
        return self.gain

    def state_dict(self) -> tuple[dict, dict[str, np.ndarray]]:
        """JSON-able ``meta`` (counts, the last scoring, the gain, the sampler's state) and the kept
        probes as arrays (``points``, ``target``, ``base`` concatenated; ``sizes`` per probe)."""
        meta = {"seen": self.seen, "scored": self.scored, "sse": self.sse.tolist(), "gain": self.gain,
                "rng": self._rng.bit_generator.state}
        arrays = {"points": self.points(), "sizes": np.array([len(p.points) for p in self.probes], np.int64)}
        for name in ("target", "base"):
            arrays[name] = (np.concatenate([getattr(p, name) for p in self.probes]) if self.probes
                            else np.zeros((0, 3), np.float32))
        return meta, arrays

    def load_state_dict(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        """Take :meth:`state_dict`'s; ValueError where it does not fit (missing or malformed entries,
        a gain not of :data:`GAINS`, arrays of other lengths, more probes than :data:`RESERVOIR`);
        nothing is changed then."""
        try:
            sizes = np.asarray(arrays["sizes"], np.int64).reshape(-1)
            parts = [np.asarray(arrays[k], np.float32) for k in ("points", "target", "base")]
            gain, sse = float(meta["gain"]), np.asarray(meta["sse"], np.float64)
            seen, scored = int(meta["seen"]), int(meta["scored"])
            rng = np.random.default_rng()
            rng.bit_generator.state = meta["rng"]
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"residual check state is malformed: {e!r}") from e
        if (gain not in GAINS or sse.shape != (len(GAINS),) or len(sizes) > RESERVOIR or (sizes < 0).any()
                or any(p.shape != (int(sizes.sum()), 3) or not np.isfinite(p).all() for p in parts)):
            raise ValueError(f"residual check state does not fit {RESERVOIR} probes of the gains {GAINS}")
        cuts = np.cumsum(sizes)[:-1]
        self.probes = [ResidualProbe(*ps) for ps in zip(*(np.split(p, cuts) for p in parts))] if len(sizes) else []
        self.seen, self.scored, self.sse, self.gain, self._rng = seen, scored, sse, gain, rng
