"""Texture pattern determination (H3-Mapping Sec. III-A): what kind of texture each leaf voxel holds.

Per voxel the map tracks
- up to M low-frequency directions ``DIR_m`` with weights ``W_m``: line segments are detected in
  the colour image (OpenCV's LSD; its -log10(NFA) is the confidence weight), segments that cross
  a depth step are discarded, and the paper's plane check keeps a segment only when 5 points
  sampled along its 3D segment lie on the depth surface (summed distance to their back-projections
  < ``tr_plane``). Each frame, the 3D directions crossing a voxel are fused around the best-scored
  one (sign-free: |cos| >= ``tr_near``), up to M per voxel; across frames a fused direction
  updates the matching ``DIR_m`` by weight, or becomes a new one while fewer than M are known;
- the fused colour gradient ``G`` and pixel count ``CNT`` (``h3edge.mapping.gradient`` states the
  operator and scale that make ``tr_weak = 0.2`` meaningful).

The class follows the paper's priority: rich texture with low-frequency directions (``RICH``,
affine warps), else weak texture (``WEAK``, G < tr_weak, the scaling warp), else unstructured rich
texture (``PLAIN``, identity only). :func:`line_rotation` is the paper's R(DIR).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from h3edge.geometry.camera import Intrinsics, pixels_to_camera, project

PLAIN, WEAK, RICH = 0, 1, 2
CLASS_NAMES = {PLAIN: "unstructured rich", WEAK: "weak", RICH: "rich with low-frequency directions"}


@dataclass(frozen=True)
class TextureConfig:
    quasi_heterogeneous: bool = True
    """False: H2-Mapping's uniform texture grid"""
    warp_rich: bool = True
    """"w.R": affine warps for rich texture with low-frequency directions"""
    warp_weak: bool = True
    """"w.W": the scaling warp for weak texture"""
    scaling_everywhere: bool = False
    """the scaling-warped (low-frequency) features for every classified voxel; paper false (weak voxels only); D0-7"""
    update_interval: int = 10
    """frames between texture pattern determinations (authors)"""
    max_directions: int = 2
    """M"""
    tr_near: float = 0.95
    """|cos| above which two line directions are the same direction"""
    tr_plane: float = 0.01
    """m, summed distance of the plane check"""
    tr_weak: float = 0.2
    """fused colour gradient below which a voxel is weak texture"""
    compression: float = 0.1
    """C, of the affine and the scaling warps"""
    anchor_scale: float = 1.0
    """a voxel's affine-warped region is anchored at anchor_scale x its centre (normalised coordinates); paper 1
    ("about the centre": oblique neighbours with the same direction share features); > sqrt(3) keeps them apart; D0-7"""
    line_depth_jump: float = 0.05
    """m, a segment whose depth steps more than this between pixels is dropped"""
    min_line_length: float = 10.0
    """px, shorter segments are ignored"""
    stride: int = 2
    """pixel stride for the per-voxel gradient statistics (counts scaled back)"""
    identity_levels: int = 0
    """levels of the identity-space texture block, coarsest first; paper 0 (all of field.tex_levels); D0-1"""


def line_rotation(d: np.ndarray) -> np.ndarray:
    """The paper's R(DIR) (..., 3, 3) for directions d (..., 3): a rotation taking e_z to DIR, so
    ``R(DIR).T @ DIR = e_z``. A line direction has no sign, so d is flipped to b_z >= 0 first: the
    formula's 1 + b_z then stays >= 1 (at DIR = -z the paper's formula divides by zero)."""
    d = np.asarray(d, np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    d = np.where(d[..., 2:3] < 0, -d, d)
    bx, by, bz = d[..., 0], d[..., 1], d[..., 2]
    k = 1.0 / (1.0 + bz)
    R = np.empty(d.shape[:-1] + (3, 3))
    R[..., 0, 0] = bz + by * by * k
    R[..., 0, 1] = -bx * by * k
    R[..., 0, 2] = bx
    R[..., 1, 0] = -bx * by * k
    R[..., 1, 1] = 1.0 - by * by * k
    R[..., 1, 2] = by
    R[..., 2, 0] = -bx
    R[..., 2, 1] = -by
    R[..., 2, 2] = bz
    return R


def affine_matrix(d: np.ndarray, compression: float) -> np.ndarray:
    """A_m = diag(1, 1, C) R(DIR)^T (..., 3, 3): rotate DIR onto z, then compress along z."""
    R = line_rotation(d)
    A = np.swapaxes(R, -1, -2).copy()
    A[..., 2, :] *= compression
    return A


class LineDetector:
    """Line segments (K, 4) [x0, y0, x1, y1] in pixels and confidence weights (K,) = -log10(NFA)."""

    def __init__(self) -> None:
        self._lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_ADV)

    def __call__(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        lines, _, _, nfa = self._lsd.detect(gray)
        if lines is None or nfa is None:
            return np.zeros((0, 4), np.float32), np.zeros(0, np.float32)
        return lines.reshape(-1, 4), np.maximum(nfa.reshape(-1), 0.0).astype(np.float32)


def lift_segments(segs: np.ndarray, weights: np.ndarray, depth: np.ndarray, intr: Intrinsics, c2w: np.ndarray,
                  cfg: TextureConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Valid 3D segments: world endpoints (K, 2, 3) and weights (K,), plus the keep mask over the input.

    Dropped: shorter than ``min_line_length``, zero weight, an endpoint without depth, a depth step
    above ``line_depth_jump`` between consecutive pixels along the segment (occlusion edges), and
    failing the plane check (5 points on the 3D segment vs their back-projections, sum < tr_plane)."""
    h, w = depth.shape
    keep = np.zeros(len(segs), bool)
    if len(segs) == 0:
        return np.zeros((0, 2, 3)), np.zeros(0), keep
    p0, p1 = segs[:, :2].astype(np.float64), segs[:, 2:].astype(np.float64)
    length = np.linalg.norm(p1 - p0, axis=1)
    cand = (length >= cfg.min_line_length) & (weights > 0)
    # depth along the 2D segment, one sample per pixel of length (capped)
    n = int(min(max(length.max(initial=2), 2), 256))
    t = np.linspace(0.0, 1.0, n)
    uv = p0[:, None, :] + t[None, :, None] * (p1 - p0)[:, None, :]
    ui = np.clip(np.rint(uv[..., 0]).astype(np.int64), 0, w - 1)
    vi = np.clip(np.rint(uv[..., 1]).astype(np.int64), 0, h - 1)
    z = depth[vi, ui]  # (K, n)
    cand &= (z[:, 0] > 0) & (z[:, -1] > 0)
    cand &= np.all(np.abs(np.diff(z, axis=1)) <= cfg.line_depth_jump, axis=1) & np.all(z > 0, axis=1)
    # 3D endpoints (camera frame) from the end pixels' depth
    P0 = pixels_to_camera(ui[:, 0], vi[:, 0], z[:, 0], intr)
    P1 = pixels_to_camera(ui[:, -1], vi[:, -1], z[:, -1], intr)
    # plane check: 5 points along the 3D segment, projected, read depth there, back-projected
    s = np.linspace(0.0, 1.0, 5)
    Q = P0[:, None, :] + s[None, :, None] * (P1 - P0)[:, None, :]  # (K, 5, 3)
    qz = np.where(Q[..., 2] > 1e-6, Q[..., 2], 1e-6)
    quv, _ = project(np.stack([Q[..., 0], Q[..., 1], qz], -1).reshape(-1, 3), intr, np.eye(4))
    qu = np.clip(np.floor(np.nan_to_num(quv[:, 0])).astype(np.int64), 0, w - 1).reshape(qz.shape)
    qv = np.clip(np.floor(np.nan_to_num(quv[:, 1])).astype(np.int64), 0, h - 1).reshape(qz.shape)
    dq = depth[qv, qu]
    B = Q * (dq / qz)[..., None]  # the measured surface point on the ray through Q
    dist = np.linalg.norm(Q - B, axis=-1).sum(1)
    cand &= np.all(dq > 0, axis=1) & (dist < cfg.tr_plane) & (np.linalg.norm(P1 - P0, axis=1) > 1e-6)
    keep = cand
    R, tr = c2w[:3, :3], c2w[:3, 3]
    ends = np.stack([P0[keep] @ R.T + tr, P1[keep] @ R.T + tr], 1)
    return ends, weights[keep].astype(np.float64), keep


def segment_voxels(ends: np.ndarray, locate, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """(segment index, voxel id) pairs, unique: the allocated voxels each 3D segment crosses
    (sampled every quarter voxel). ``locate(points) -> (voxel ids, ...)``."""
    if len(ends) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    seg_len = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    n = np.maximum(2, np.ceil(seg_len / (voxel_size / 4)).astype(np.int64) + 1)
    seg = np.repeat(np.arange(len(ends)), n)
    start = np.cumsum(n) - n
    t = (np.arange(len(seg)) - start[seg]) / (n[seg] - 1)
    pts = ends[seg, 0] + t[:, None] * (ends[seg, 1] - ends[seg, 0])
    vox = locate(pts)[0]
    ok = vox >= 0
    pairs = np.unique(np.stack([seg[ok], vox[ok]], 1), axis=0)
    return pairs[:, 0], pairs[:, 1]


def fuse_frame_directions(vox: np.ndarray, dirs: np.ndarray, weights: np.ndarray, max_dirs: int, tr_near: float
                          ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The paper's per-frame fusion. For each voxel, repeatedly: take the best-scored remaining
    direction d_max, fuse (weighted mean, signs aligned to d_max) every remaining direction with
    |cos| >= tr_near, remove them; at most ``max_dirs`` rounds. Returns per round n
    (voxel ids (unique), dir_n (k, 3) unit, w_n (k,))."""
    out = []
    vox, dirs, weights = np.asarray(vox), np.asarray(dirs, np.float64), np.asarray(weights, np.float64)
    for _ in range(max_dirs):
        if len(vox) == 0:
            break
        order = np.lexsort((-weights, vox))
        v, d, w = vox[order], dirs[order], weights[order]
        first = np.r_[True, v[1:] != v[:-1]]
        group = np.cumsum(first) - 1
        lead = np.flatnonzero(first)[group]
        cos = (d * d[lead]).sum(1)
        near = np.abs(cos) >= tr_near
        sgn = np.where(cos < 0, -1.0, 1.0)
        acc = np.zeros((int(group[-1]) + 1, 3))
        np.add.at(acc, group[near], (w * sgn)[near, None] * d[near])
        wsum = np.bincount(group[near], weights=w[near], minlength=len(acc))
        norm = np.linalg.norm(acc, axis=1, keepdims=True)
        fused = np.where(norm > 0, acc / np.maximum(norm, 1e-12), d[first])
        out.append((v[first], fused, wsum))
        vox, dirs, weights = v[~near], d[~near], w[~near]
    return out


def voxel_gradient_stats(
    vox: np.ndarray, g: np.ndarray, scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per voxel of a frame: (voxel ids, cnt = pixel count (x ``scale`` for strided pixels), mean g)."""
    ok = vox >= 0
    ids, inv = np.unique(vox[ok], return_inverse=True)
    cnt = np.bincount(inv, minlength=len(ids)).astype(np.float64)
    gsum = np.bincount(inv, weights=g[ok].astype(np.float64), minlength=len(ids))
    return ids, cnt * scale, gsum / np.maximum(cnt, 1)


class TexturePatterns:
    """Per-voxel texture state, grown with the voxel map; :meth:`update` runs one determination."""

    def __init__(self, cfg: TextureConfig = TextureConfig()):
        if cfg.max_directions < 0:
            raise ValueError("max_directions must be >= 0")
        self.cfg = cfg
        m = cfg.max_directions
        self.dirs = np.zeros((0, m, 3))
        self.dir_weights = np.zeros((0, m))
        self.n_dirs = np.zeros(0, np.int64)
        self.G = np.zeros(0)
        self.CNT = np.zeros(0)
        self._detector: LineDetector | None = None
        self.updates = 0

    STATE = ("dirs", "dir_weights", "n_dirs", "G", "CNT")

    def state_dict(self) -> tuple[dict, dict[str, np.ndarray]]:
        """(meta, arrays): the per-voxel directions, weights, gradients and counts."""
        return {"updates": self.updates}, {name: getattr(self, name).copy() for name in self.STATE}

    def load_state_dict(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        for name in self.STATE:
            setattr(self, name, arrays[name].copy())
        self.updates = int(meta["updates"])

    def __len__(self) -> int:
        return len(self.G)

    @property
    def nbytes(self) -> int:
        return self.dirs.nbytes + self.dir_weights.nbytes + self.n_dirs.nbytes + self.G.nbytes + self.CNT.nbytes

    def grow(self, n_voxels: int) -> None:
        k = n_voxels - len(self)
        if k <= 0:
            return
        m = self.cfg.max_directions
        self.dirs = np.concatenate([self.dirs, np.zeros((k, m, 3))])
        self.dir_weights = np.concatenate([self.dir_weights, np.zeros((k, m))])
        self.n_dirs = np.concatenate([self.n_dirs, np.zeros(k, np.int64)])
        self.G = np.concatenate([self.G, np.zeros(k)])
        self.CNT = np.concatenate([self.CNT, np.zeros(k)])

    # ------------------------------------------------------------------ fusion
    def fuse_gradient(self, ids: np.ndarray, cnt: np.ndarray, g: np.ndarray) -> None:
        """G <- (CNT G + cnt g) / (CNT + cnt); CNT <- CNT + cnt."""
        self.grow(int(ids.max(initial=-1)) + 1)
        C = self.CNT[ids]
        self.G[ids] = (C * self.G[ids] + cnt * g) / np.maximum(C + cnt, 1e-12)
        self.CNT[ids] = C + cnt

    def fuse_directions(self, ids: np.ndarray, dirn: np.ndarray, wn: np.ndarray) -> None:
        """Across-frame update with one fused direction per voxel (``ids`` unique)."""
        if len(ids) == 0 or self.cfg.max_directions == 0:
            return
        self.grow(int(ids.max()) + 1)
        M = self.cfg.max_directions
        D, W, n = self.dirs[ids], self.dir_weights[ids], self.n_dirs[ids]
        cos = np.einsum("kmc,kc->km", D, dirn)
        known = np.arange(M)[None, :] < n[:, None]
        score = np.where(known, np.abs(cos), -1.0)
        best = np.argmax(score, axis=1)
        rows = np.arange(len(ids))
        match = score[rows, best] >= self.cfg.tr_near
        sgn = np.where(cos[rows, best] < 0, -1.0, 1.0)
        r, b = rows[match], best[match]
        new = W[r, b, None] * D[r, b] + (wn[match] * sgn[match])[:, None] * dirn[match]
        D[r, b] = new / np.maximum(np.linalg.norm(new, axis=1, keepdims=True), 1e-12)
        W[r, b] += wn[match]
        add = ~match & (n < M)
        r, slot = rows[add], n[add]
        D[r, slot], W[r, slot], n[r] = dirn[add], wn[add], slot + 1
        self.dirs[ids], self.dir_weights[ids], self.n_dirs[ids] = D, W, n

    # ------------------------------------------------------------------ update
    def observe(self, rgb: np.ndarray, depth: np.ndarray, intr: Intrinsics, c2w: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """The frame's line segments lifted to world space (ends (N, 2, 3) m, weights (N,)): the
        part of :meth:`update` that reads only the frame (no pattern or map state), so that it can
        run where the map is not held."""
        if self._detector is None:
            self._detector = LineDetector()
        segs, w = self._detector(rgb)
        ends, w, _ = lift_segments(segs, w, depth, intr, c2w, self.cfg)
        return ends, w

    def update(self, rgb: np.ndarray, depth: np.ndarray, intr: Intrinsics, c2w: np.ndarray, points: np.ndarray,
               locate, voxel_size: float, g: np.ndarray, lifted: tuple[np.ndarray, np.ndarray] | None = None
               ) -> dict:
        """One determination on a frame: colour-gradient fusion, lines, direction fusion.

        ``points``: the frame's back-projected world points (H, W, 3) (NaN where invalid);
        ``locate(points) -> (voxel ids, ...)`` maps points to allocated voxels; ``g``: the frame's
        per-pixel colour gradient (:func:`~h3edge.mapping.gradient.color_gradient`, occlusion edges
        zeroed with the mapper's depth-edge jump); ``lifted``: :meth:`observe` of this frame, when
        already known."""
        cfg = self.cfg
        s = max(1, cfg.stride)
        sub = (slice(None, None, s), slice(None, None, s))
        valid = depth[sub] > 0
        vox = locate(points[sub][valid])[0]
        ids, cnt, gm = voxel_gradient_stats(vox, g[sub][valid], float(s * s))
        self.fuse_gradient(ids, cnt, gm)
        lines = 0
        if cfg.max_directions > 0:
            ends, w = self.observe(rgb, depth, intr, c2w) if lifted is None else lifted
            lines = len(ends)
            seg, vx = segment_voxels(ends, locate, voxel_size)
            if len(seg):
                d = ends[:, 1] - ends[:, 0]
                d /= np.linalg.norm(d, axis=1, keepdims=True)
                for ids_n, dir_n, w_n in fuse_frame_directions(vx, d[seg], w[seg], cfg.max_directions, cfg.tr_near):
                    self.fuse_directions(ids_n, dir_n, w_n)
        self.updates += 1
        return {"lines": lines, "voxels_seen": len(ids)}

    # ----------------------------------------------------------------- classes
    def classes(self, n_voxels: int | None = None) -> np.ndarray:
        """Class per voxel (int8): RICH, else WEAK, else PLAIN (the paper's priority)."""
        self.grow(n_voxels or 0)
        cls = np.full(len(self), PLAIN, np.int8)
        cls[(self.CNT > 0) & (self.G < self.cfg.tr_weak)] = WEAK
        cls[self.n_dirs > 0] = RICH
        return cls

    def counts(self, n_voxels: int | None = None) -> dict[str, int]:
        c = self.classes(n_voxels)
        return {CLASS_NAMES[k]: int((c == k).sum()) for k in (RICH, WEAK, PLAIN)}
