"""Keyframe policy: insertion, coverage-maximising selection, adaptive pruning (Sec. IV-B).

Insertion: a frame becomes a keyframe when the IoU of its observed voxel set with the last
keyframe's drops below ``insert_iou`` (0.85) or ``max_interval`` (10) frames have passed.

Selection, per training iteration: greedily pick up to K keyframes, each time the one whose
still-unobserved voxels carry the highest score sum; its voxels become observed. The observed
state persists across iterations; once every voxel is observed it resets, and with adaptive
pruning the keyframes not selected during that round are removed. Each keyframe carries a score
per observed voxel: 1 everywhere gives H2-Mapping's voxel-count coverage; H3's gradient-aided
score max(cnt^2 * g, 1) plugs in through the same array.

Caps bound the set: a count (``max_keyframes``) and the stored frames' bytes (``max_bytes``, set by
the service from its memory budget); past either, the keyframe with the smallest total score (the
least coverage it can add) is evicted.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from h3edge.geometry.camera import Intrinsics
from h3edge.geometry.depth_edges import far_side_of_edges
from h3edge.mapping.texture_patterns import voxel_gradient_stats

DEPTH_LEVELS = 65535  # uint16 steps a stored depth image is quantised to (0 = invalid)


@dataclass
class StoredFrame:
    """What a keyframe keeps for training to draw rays from: its whole colour image and its cleaned
    depth quantised to uint16 in a per-frame unit (max depth / 65535: <= 0.08 mm error at 10 m),
    5 bytes per pixel (1.5 MB at 640x480). Whole images, not a fixed subset of pixels: a subset
    drawn once is all that training between frames sees of the view for the rest of the run, and on
    real Kinect data the texture grids over-fit it (held-out SSIM 0.59 -> 0.49 after 900 keyframe
    iterations with a 32k-pixel subset; 0.61 -> 0.61 with whole images, research/continuous_training.md).

    Example::

        kf = StoredFrame.of(color, depth, pose, intrinsics)
        pix, rgb, z = kf.draw(256, np.random.default_rng(0))  # 256 valid pixels, with replacement
    """

    color: np.ndarray  # uint8 (H, W, 3)
    depth_q: np.ndarray  # uint16 (H, W): depth / depth_unit, 0 = invalid
    depth_unit: float  # metres per step
    n_valid: int  # pixels with depth
    pose: np.ndarray
    intrinsics: Intrinsics
    # flat indices of the far side of the depth edges, per setting: computed on first use
    # (:meth:`edge_pixels`), not stored in checkpoints
    _edges: dict = field(default_factory=dict, repr=False, compare=False)
    # torch device -> the images there for training's ray draw (h3edge.mapping.device_frames, the torch
    # backend): uploaded on first use, not stored in checkpoints
    _on_device: dict = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def of(cls, color: np.ndarray, depth: np.ndarray, pose: np.ndarray, intrinsics: Intrinsics) -> StoredFrame:
        """Store a frame's colour (uint8 H, W, 3) and cleaned depth (float32 metres, 0 = invalid)."""
        depth = np.asarray(depth, np.float32)
        top = float(depth.max(initial=0.0))
        unit = top / DEPTH_LEVELS if top > 0 else 1.0
        q = np.rint(depth / np.float32(unit)).astype(np.uint16)
        q[(depth > 0) & (q == 0)] = 1  # a valid depth stays valid
        return cls.frozen(np.array(color, np.uint8), q, unit, np.asarray(pose, np.float64), intrinsics)

    @classmethod
    def frozen(cls, color: np.ndarray, depth_q: np.ndarray, depth_unit: float, pose: np.ndarray,
               intrinsics: Intrinsics) -> StoredFrame:
        """Take ``color`` and ``depth_q`` as they are and make them read-only: a stored frame never
        changes, so a checkpoint capture can hold the arrays themselves."""
        color, depth_q = np.ascontiguousarray(color), np.ascontiguousarray(depth_q)
        color.flags.writeable = depth_q.flags.writeable = False
        return cls(color, depth_q, depth_unit, int(np.count_nonzero(depth_q)), pose, intrinsics)

    def draw(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``n`` pixels drawn uniformly, with replacement, among the valid ones (rejection from all
        pixels): their flat indices (int64), colours (uint8 (n, 3)) and depths (float32 metres)."""
        flat = self.depth_q.reshape(-1)
        if self.n_valid == 0 or n <= 0:
            return np.zeros(0, np.int64), np.zeros((0, 3), np.uint8), np.zeros(0, np.float32)
        share = self.n_valid / flat.size
        got: list[np.ndarray] = []
        need = n
        while need > 0:
            cand = rng.integers(0, flat.size, int(need / share * 1.2) + 16)
            cand = cand[flat[cand] > 0][:need]
            got.append(cand)
            need -= len(cand)
        return self.at(np.concatenate(got))

    def at(self, pix: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Flat pixel indices ``pix`` with their colours (uint8 (n, 3)) and depths (float32 metres)."""
        return pix, self.color.reshape(-1, 3)[pix], self.depth_q.reshape(-1)[pix].astype(np.float32) * np.float32(
            self.depth_unit)

    def edge_pixels(self, radius: int, jump: float, step: int, near_too: bool = False) -> np.ndarray:
        """As :func:`edge_pixels` on the stored depth, computed once per setting."""
        return edge_pixels(self._edges, self.depth, radius, jump, step, near_too)

    @property
    def depth(self) -> np.ndarray:
        """The stored depth, float32 metres (H, W), 0 = invalid."""
        return self.depth_q.astype(np.float32) * np.float32(self.depth_unit)

    @property
    def nbytes(self) -> int:
        edges = sum(e.nbytes for e in self._edges.values())
        on_device = sum(d.own_bytes for d in self._on_device.values())
        return self.color.nbytes + self.depth_q.nbytes + 8 * 16 + edges + on_device


def edge_pixels(cache: dict, depth: np.ndarray, radius: int, jump: float, step: int, near_too: bool) -> np.ndarray:
    """Flat indices (int32) of the valid pixels of ``depth`` beside a depth edge
    (:func:`~h3edge.geometry.depth_edges.far_side_of_edges`), taken from / kept in ``cache`` (a
    frame's, keyed by the setting)."""
    key = (int(radius), float(jump), int(step), bool(near_too))
    if key not in cache:
        cache[key] = np.flatnonzero(far_side_of_edges(depth, radius, jump, step, near_too)).astype(np.int32)
    return cache[key]


def gradient_scores(vox: np.ndarray, gradient: np.ndarray, stride: int) -> np.ndarray:
    """H3's gradient-aided voxel scores max(cnt^2 g, 1) for the voxels of points sampled every
    ``stride``-th valid pixel: ``vox`` their voxel ids (-1 outside), ``gradient`` their colour
    gradients; cnt counts pixels (samples times ``stride``), g is the voxel's mean gradient. One
    score per voxel, in the order of ``np.unique(vox[vox >= 0])``."""
    _, cnt, g = voxel_gradient_stats(vox, gradient, float(stride))
    return np.maximum(cnt * cnt * g, 1.0)


@dataclass(frozen=True)
class KeyframeConfig:
    insert_iou: float = 0.85
    """a frame whose observed voxels overlap the last keyframe's less than this (IoU) is a keyframe (paper: 0.85)"""
    max_interval: int = 10
    """frames at most between two keyframes (paper: 10)"""
    per_iteration: int = 8
    """K"""
    adaptive_pruning: bool = True
    """H3's adaptive pruning: when a selection round has covered every voxel, keyframes it never selected go"""
    gradient_aided: bool = True
    """H3's voxel score max(cnt^2 g, 1); False: H2's voxel count"""
    max_keyframes: int = 0
    """cap (0: none); past it the least informative keyframe is evicted"""
    max_bytes: int = 0
    """cap on the stored frames' bytes (0: none; the service sets it from its budget)"""


@dataclass(eq=False)  # identity: frame ids may repeat (a publisher restarting its counter)
class Keyframe:
    frame_id: int
    voxels: np.ndarray  # unique voxel ids the frame observes
    scores: np.ndarray  # score per voxel (same order)
    payload: object = None  # the stored frame (compressed by the caller)
    selected_this_round: bool = False


@dataclass
class KeyframeSet:
    cfg: KeyframeConfig = field(default_factory=KeyframeConfig)
    keyframes: list[Keyframe] = field(default_factory=list)
    observed: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    frames_since_insert: int = 0
    pruned: int = 0
    evicted: int = 0

    def state_dict(self) -> tuple[dict, dict[str, np.ndarray]]:
        """(meta, arrays): every keyframe (its voxels and scores concatenated with offsets; its
        stored images as ``color/<i>`` and ``depth_q/<i>``, the read-only arrays themselves, not
        copies: a checkpoint capture holds no second copy of the keyframes), the selection round's
        observed voxels and the policy's counters."""
        kfs = self.keyframes
        meta = {"keyframes": [{"frame_id": k.frame_id, "selected": k.selected_this_round,
                               "intrinsics": k.payload.intrinsics.to_dict(), "pose": k.payload.pose.tolist(),
                               "image": list(k.payload.depth_q.shape), "depth_unit": k.payload.depth_unit}
                              for k in kfs],
                "keyframe_policy": {"frames_since_insert": self.frames_since_insert, "pruned": self.pruned}}
        arrays: dict[str, np.ndarray] = {}
        for name, get, dt, w in (("voxels", lambda k: k.voxels, np.int64, ()),
                                 ("scores", lambda k: k.scores, np.float64, ())):
            parts = [get(k) for k in kfs]
            arrays[f"{name}_offsets"] = np.cumsum([0] + [len(p) for p in parts]).astype(np.int64)
            arrays[name] = np.concatenate(parts).astype(dt) if parts else np.zeros((0, *w), dt)
        for i, k in enumerate(kfs):
            arrays[f"color/{i}"], arrays[f"depth_q/{i}"] = k.payload.color, k.payload.depth_q
        arrays["observed"] = self.observed.copy()
        return meta, arrays

    def load_state_dict(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        def split(name: str) -> list[np.ndarray]:
            data, off = arrays[name], arrays[f"{name}_offsets"]
            return [data[off[i]:off[i + 1]] for i in range(len(off) - 1)]

        # (maps saved before the cross-view test's removal also hold each keyframe's pooled depth:
        # not read)
        parts = {n: split(n) for n in ("voxels", "scores")}

        def stored(i: int, km: dict) -> StoredFrame:
            h, w = km["image"]
            color = np.asarray(arrays[f"color/{i}"], np.uint8)
            depth_q = np.asarray(arrays[f"depth_q/{i}"], np.uint16)
            if color.shape != (h, w, 3) or depth_q.shape != (h, w):
                raise ValueError(f"keyframe {i}: stored images {color.shape} / {depth_q.shape}, expected {h}x{w}")
            return StoredFrame.frozen(color, depth_q, float(km["depth_unit"]), np.asarray(km["pose"], np.float64),
                                      Intrinsics(**km["intrinsics"]))

        self.keyframes = [Keyframe(km["frame_id"], parts["voxels"][i], parts["scores"][i], stored(i, km),
                                   km["selected"])
                          for i, km in enumerate(meta["keyframes"])]
        self.observed = arrays["observed"].astype(bool)
        self.frames_since_insert = int(meta["keyframe_policy"]["frames_since_insert"])
        self.pruned = int(meta["keyframe_policy"]["pruned"])

    def should_insert(self, voxels: np.ndarray) -> bool:
        """Insertion rule for a frame observing ``voxels`` (unique ids); counts the interval."""
        self.frames_since_insert += 1
        if not self.keyframes:
            return True
        last = self.keyframes[-1].voxels
        inter = len(np.intersect1d(voxels, last, assume_unique=True))
        union = len(voxels) + len(last) - inter
        iou = inter / union if union else 1.0
        return iou < self.cfg.insert_iou or self.frames_since_insert >= self.cfg.max_interval

    def insert(self, frame_id: int, voxels: np.ndarray, scores: np.ndarray | None = None, payload=None) -> None:
        scores = np.ones(len(voxels)) if scores is None else np.asarray(scores, float)
        if scores.shape != voxels.shape:
            raise ValueError("one score per voxel")
        self.keyframes.append(Keyframe(frame_id, voxels, scores, payload))
        self.frames_since_insert = 0
        while len(self.keyframes) > 2 and self._over_cap():
            # evict the keyframe with the smallest total score (never the newest: insertion compares to it)
            worst = int(np.argmin([k.scores.sum() for k in self.keyframes[:-1]]))
            del self.keyframes[worst]
            self.evicted += 1

    def _over_cap(self) -> bool:
        cap, cap_bytes = self.cfg.max_keyframes, self.cfg.max_bytes
        if cap and len(self.keyframes) > cap:
            return True
        return bool(cap_bytes) and sum(getattr(k.payload, "nbytes", 0) for k in self.keyframes) > cap_bytes

    def _grow(self, n_voxels: int) -> None:
        if len(self.observed) < n_voxels:
            self.observed = np.concatenate([self.observed, np.zeros(n_voxels - len(self.observed), bool)])

    def select(self) -> list[Keyframe]:
        """Up to K keyframes covering the highest-scoring unobserved voxels (see module doc)."""
        if not self.keyframes:
            return []
        self._grow(1 + max(int(k.voxels.max(initial=-1)) for k in self.keyframes))
        known = np.zeros(len(self.observed), bool)
        for k in self.keyframes:
            known[k.voxels] = True
        if self.observed[known].all():
            self._end_round()
            known[:] = False
            for k in self.keyframes:
                known[k.voxels] = True
        chosen: list[Keyframe] = []
        for _ in range(min(self.cfg.per_iteration, len(self.keyframes))):
            gains = [0.0 if k in chosen else float(k.scores[~self.observed[k.voxels]].sum()) for k in self.keyframes]
            best = int(np.argmax(gains))
            if gains[best] <= 0:
                break
            kf = self.keyframes[best]
            chosen.append(kf)
            kf.selected_this_round = True
            self.observed[kf.voxels] = True
        return chosen

    def _end_round(self) -> None:
        """All voxels observed: reset, and prune the keyframes the round never selected."""
        if self.cfg.adaptive_pruning:
            keep = [k for k in self.keyframes if k.selected_this_round]
            keep_last = self.keyframes[-1]  # the insertion rule compares against it
            if keep_last not in keep:
                keep.append(keep_last)
            self.pruned += len(self.keyframes) - len(keep)
            self.keyframes = keep
        for k in self.keyframes:
            k.selected_this_round = False
        self.observed[:] = False
