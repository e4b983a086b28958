"""The paper's metrics as pure functions: Depth L1, Accuracy / Completion, PSNR, SSIM.

Units: depth and distances in metres in, reported in centimetres by :mod:`h3edge.eval.evaluate`.
Images are uint8 RGB or float; ``data_range`` is 255 for uint8 input, 1 for float.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from skimage.metrics import structural_similarity


def _range(img: np.ndarray) -> float:
    return 255.0 if img.dtype == np.uint8 else 1.0


def psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Peak signal-to-noise ratio in dB, over ``mask`` (H, W) pixels when given."""
    if pred.shape != gt.shape:
        raise ValueError(f"shape mismatch {pred.shape} vs {gt.shape}")
    r = _range(gt)
    diff = pred.astype(np.float64) / r - gt.astype(np.float64) / r
    if mask is not None:
        diff = diff[mask]
    mse = float(np.mean(diff ** 2)) if diff.size else float("nan")
    return float("inf") if mse == 0 else float(-10.0 * np.log10(mse))


def ssim(pred: np.ndarray, gt: np.ndarray) -> float:
    """Standard 2-D SSIM (Wang et al. 2004: 11x11 Gaussian window, sigma 1.5), mean over channels."""
    if pred.shape != gt.shape:
        raise ValueError(f"shape mismatch {pred.shape} vs {gt.shape}")
    r = _range(gt)
    return float(structural_similarity(pred.astype(np.float64) / r, gt.astype(np.float64) / r, data_range=1.0,
                                       channel_axis=-1 if gt.ndim == 3 else None, gaussian_weights=True,
                                       sigma=1.5, use_sample_covariance=False))


def depth_l1(pred: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """Mean |pred - gt| (metres) over valid GT pixels (gt > 0), and the fraction of them rendered.

    A GT-valid pixel the prediction left empty (0) counts with its full depth as error, so holes
    in a map are not hidden by the mask.
    """
    valid = (gt > 0) & np.isfinite(gt)
    if not valid.any():
        return float("nan"), 0.0
    p = np.where(np.isfinite(pred), pred, 0.0)
    return float(np.mean(np.abs(p[valid] - gt[valid]))), float(np.mean(p[valid] > 0))


def sample_surface(mesh: trimesh.Trimesh, n: int, seed: int = 0) -> np.ndarray:
    """``n`` points uniformly by area on the mesh surface (deterministic for a seed)."""
    if len(mesh.faces) == 0:
        return np.zeros((0, 3))
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts)


def accuracy_completion(recon_pts: np.ndarray, gt_pts: np.ndarray, ratio_threshold: float = 0.05
                        ) -> dict[str, float]:
    """Accuracy: mean distance recon -> GT; Completion: mean distance GT -> recon (metres).

    Also the completion ratio: the fraction of GT points within ``ratio_threshold`` of the recon.
    """
    if len(recon_pts) == 0 or len(gt_pts) == 0:
        return {"accuracy": float("inf"), "completion": float("inf"), "completion_ratio": 0.0}
    d_acc, _ = cKDTree(gt_pts).query(recon_pts, workers=-1)
    d_comp, _ = cKDTree(recon_pts).query(gt_pts, workers=-1)
    return {"accuracy": float(np.mean(d_acc)), "completion": float(np.mean(d_comp)),
            "completion_ratio": float(np.mean(d_comp < ratio_threshold))}


def _depth_error_classes(pred: np.ndarray, gt: np.ndarray, threshold: float):
    """(valid sensor depth, rendered, > threshold in front, > threshold behind, error), all (H, W)."""
    valid = (gt > 0) & np.isfinite(gt)
    p = np.where(np.isfinite(pred), pred, 0.0)
    hit = valid & (p > 0)
    err = p - gt
    return valid, hit, hit & (err < -threshold), hit & (err > threshold), err


def depth_error_shares(pred: np.ndarray, gt: np.ndarray, threshold: float = 0.05) -> dict[str, float]:
    """Where a render's depth goes wrong, over valid GT pixels (gt > 0): the share rendered more
    than ``threshold`` metres *in front of* the sensor depth (inflated silhouettes, phantom surfaces),
    the share more than ``threshold`` *behind* it (holes seen through, eroded objects), the share not
    rendered at all, and the median |error| (metres) over the pixels rendered."""
    valid, hit, front, behind, err = _depth_error_classes(pred, gt, threshold)
    n = int(valid.sum())
    if n == 0:
        return {"front_share": float("nan"), "behind_share": float("nan"), "missing_share": float("nan"),
                "median_abs_m": float("nan")}
    return {"front_share": float(front.sum() / n), "behind_share": float(behind.sum() / n),
            "missing_share": float((valid & ~hit).sum() / n),
            "median_abs_m": float(np.median(np.abs(err[hit]))) if hit.any() else float("nan")}


def depth_error_map(pred: np.ndarray, gt: np.ndarray, threshold: float = 0.05) -> np.ndarray:
    """Picture of :func:`depth_error_shares` (H, W, 3) uint8: red = rendered > ``threshold`` in front
    of the sensor depth, blue = > ``threshold`` behind it, grey = within, white = valid depth not
    rendered, black = no sensor depth."""
    valid, hit, front, behind, _ = _depth_error_classes(pred, gt, threshold)
    out = np.zeros(gt.shape + (3,), np.uint8)
    out[valid & ~hit] = (255, 255, 255)
    out[hit] = (190, 190, 190)
    out[front] = (220, 30, 30)
    out[behind] = (30, 60, 230)
    return out


TARGET_SPACING = 0.2  # of the threshold: the spacing of the samples a distance is measured to
MAX_TARGET_POINTS = 4_000_000  # cap on those samples (400 m^2 at 1 cm spacing)


def _target_samples(mesh: trimesh.Trimesh, n: int, threshold: float, seed: int) -> np.ndarray:
    """Samples of ``mesh`` to measure distances to: at least ``n``, and dense enough (one per
    (``TARGET_SPACING`` * threshold)^2 of area, up to ``MAX_TARGET_POINTS``) that the gaps between
    samples stay far below the threshold; a sparse sampling counts covered surface as far."""
    spacing = TARGET_SPACING * threshold
    dense = int(np.ceil(mesh.area / spacing ** 2)) if len(mesh.faces) and spacing > 0 else 0
    return sample_surface(mesh, max(n, min(dense, MAX_TARGET_POINTS)), seed)


def far_share_from(reference: trimesh.Trimesh, n: int = 200_000, threshold: float = 0.05,
                   seed: int = 0) -> Callable[[trimesh.Trimesh], float]:
    """``f(mesh) ->`` the share of ``n`` area-uniform samples of ``mesh`` farther than ``threshold``
    (m) from ``reference``, measured as :func:`mesh_to_mesh` measures ``a_to_b_far_share`` (the same
    dense sampling of the reference), with one sampling and search tree for every mesh scored."""
    tree = cKDTree(_target_samples(reference, n, threshold, seed + 3))

    def far_share(mesh: trimesh.Trimesh) -> float:
        p = sample_surface(mesh, n, seed)
        return float(np.mean(tree.query(p, workers=-1)[0] > threshold)) if len(p) else 1.0

    return far_share


def mesh_to_mesh(a: trimesh.Trimesh, b: trimesh.Trimesh, n: int = 200_000, threshold: float = 0.05,
                 seed: int = 0) -> dict[str, float]:
    """Surface distances between two meshes, both directions (metres): from ``n`` area-uniform
    samples of each to a dense sampling of the other (:func:`_target_samples`: 1 cm apart at a
    5 cm threshold; ``n`` samples of a 100 m^2 room lie ~2 cm apart at 200,000 and ~4.5 cm at 50,000,
    which alone made 5 % of a covered surface read as farther than 5 cm); mean and share farther
    than ``threshold``. ``a_to_b`` is the accuracy-like direction when ``b`` is the reference."""
    pa, pb = sample_surface(a, n, seed), sample_surface(b, n, seed + 1)
    if len(pa) == 0 or len(pb) == 0:
        return {"a_to_b_mean": float("inf"), "b_to_a_mean": float("inf"), "a_to_b_far_share": 1.0,
                "b_to_a_far_share": 1.0}
    d_ab, _ = cKDTree(_target_samples(b, n, threshold, seed + 3)).query(pa, workers=-1)
    d_ba, _ = cKDTree(_target_samples(a, n, threshold, seed + 2)).query(pb, workers=-1)
    return {"a_to_b_mean": float(np.mean(d_ab)), "b_to_a_mean": float(np.mean(d_ba)),
            "a_to_b_far_share": float(np.mean(d_ab > threshold)), "b_to_a_far_share": float(np.mean(d_ba > threshold))}
