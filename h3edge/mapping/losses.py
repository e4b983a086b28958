"""The training losses of H3-Mapping (Sec. IV-D), as pure functions of per-ray / per-sample tensors.

- RGB: L1 + S3IM (stochastic structural similarity over randomly re-patched ray batches);
- depth: L1 over rays with valid measured depth;
- free space: samples between the camera and the truncation band pushed to the truncation
  value (L2), averaged per ray then over rays;
- SDF: samples inside the truncation band fitted to the measured signed distance (L2), with the
  paper's surface-aware rule: negative targets are dropped for samples past the second sign
  change of the predicted SDF along the ray (objects thinner than the band).

SDF values are in truncation units (metres / truncation), so the truncation value is 1 and a
sample's target is (measured depth - sample depth) / truncation.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F


@dataclass(frozen=True)
class LossWeights:
    rgb: float = 0.5
    """alpha_rgb (authors' config)"""
    depth: float = 1.0
    """alpha_d"""
    sdf: float = 50000.0
    """alpha_sdf"""
    free_space: float = 10.0
    """alpha_fs"""
    surface_rgb: float = 0.5
    """surface colour points (TrainConfig.surface_color_points; not in the paper)"""
    seen_free: float = 50000.0
    """SDF >= 0 in cells the frames voted free (votes.points; not in the paper), on L_sdf's scale"""
    s3im: bool = True
    """S3IM (stochastic structural similarity of re-patched ray batches) added to the RGB loss (paper: on)"""
    s3im_kernel: int = 4
    """S3IM's SSIM window, pixels of the pseudo-image (paper: 4)"""
    s3im_stride: int = 4
    """S3IM's window stride (paper: 4)"""
    s3im_repeats: int = 10
    """S3IM's random re-patchings of the batch (paper: 10)"""
    s3im_patch_width: int = 64
    """rays per column of S3IM's pseudo-image (paper: 64)"""


def depth_l1(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean |pred - gt| (R,) over the rays with measured depth (gt > 0); 0 when none (a masked mean,
    no host transfer)."""
    valid = gt > 0
    return torch.where(valid, (pred - gt).abs(), 0.0).sum() / valid.sum().clamp(min=1)


def rgb_l1(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean |pred - gt| over colours (R, 3), or over the rows in ``mask`` (R,) bool (0 when none)."""
    if mask is None:
        return (pred - gt).abs().mean()
    return torch.where(mask[:, None], (pred - gt).abs(), 0.0).sum() / (3 * mask.sum()).clamp(min=1)


def _gaussian_window(k: int, sigma: float = 1.5, device=None, dtype=None) -> torch.Tensor:
    x = torch.arange(k, device=device, dtype=dtype) - (k - 1) / 2
    g = torch.exp(-x ** 2 / (2 * sigma ** 2))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(3, 1, k, k).contiguous()


def _ssim_map(x: torch.Tensor, y: torch.Tensor, win: torch.Tensor, stride: int) -> torch.Tensor:
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    conv = lambda t: F.conv2d(t, win, stride=stride, groups=3)  # noqa: E731
    mx, my = conv(x), conv(y)
    sxx = conv(x * x) - mx * mx
    syy = conv(y * y) - my * my
    sxy = conv(x * y) - mx * my
    return ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))


def s3im(pred: torch.Tensor, gt: torch.Tensor, kernel: int = 4, stride: int = 4, repeats: int = 10,
         patch_width: int = 64, generator: torch.Generator | None = None) -> torch.Tensor:
    """S3IM loss (Xie et al., ICCV 2023): 1 - SSIM of ray batches re-arranged into pseudo-images.

    The first arrangement keeps the batch order, the other ``repeats - 1`` are random
    permutations; they are laid side by side as one image ``patch_width`` rays tall.
    Colours (R, 3) in [0, 1]; R is truncated to a multiple of ``patch_width``.
    """
    r = (len(pred) // patch_width) * patch_width
    if r == 0:
        return pred.sum() * 0
    idx = [torch.arange(r, device=pred.device)]
    for _ in range(repeats - 1):
        idx.append(torch.randperm(r, device=pred.device, generator=generator))
    idx = torch.cat(idx)

    def image(c):  # (R*repeats, 3) -> (1, 3, patch_width, R*repeats/patch_width)
        return c[idx].T.reshape(1, 3, -1, patch_width).transpose(2, 3)

    win = _gaussian_window(kernel, device=pred.device, dtype=pred.dtype)
    return 1 - _ssim_map(image(pred), image(gt), win, stride).mean()


def sdf_targets(sample_depth: torch.Tensor, gt_depth: torch.Tensor, truncation: float) -> torch.Tensor:
    """Target SDF (truncation units) of each sample: (measured depth - sample depth) / truncation."""
    return (gt_depth[:, None] - sample_depth) / truncation


def free_space_and_sdf(sdf: torch.Tensor, sample_depth: torch.Tensor, gt_depth: torch.Tensor,
                       mask: torch.Tensor, truncation: float, surface_aware: bool = True, behind: float = 1.0
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """(L_fs, L_sdf) over rays with valid depth; sdf (R, S) in truncation units, depths in metres.

    Units as the authors' code (Vox-Fusion / H2-Mapping ``get_sdf_loss``) has them, which their
    loss weights (sdf 50000, free space 10) assume: L_fs on the SDF in truncation units,
    (s - 1)^2; L_sdf on the implied surface depth in metres, (z + s * tr - D)^2 = tr^2 (s - t)^2.
    Taken in truncation units, L_sdf would weigh 1 / tr^2 = 400 times more against free space,
    rendering and depth than the authors' settings do, and free-space carving would not count.

    Samples are in ray order and the valid ones (``mask``) form a prefix of each row, as the
    sampler packs them, so a sign change is a change between neighbouring samples. ``behind``
    (truncation units, at most 1): how far behind the measured depth band samples take an SDF
    target; deeper ones only carry the rendering losses.
    """
    valid_ray = gt_depth > 0
    target = sdf_targets(sample_depth, gt_depth, truncation)
    m = mask & valid_ray[:, None]
    fs = m & (target > 1.0)  # in front of the band: between the camera and D - truncation
    tr = m & (target.abs() <= 1.0) & (target >= -behind)
    if surface_aware:
        sgn = sdf.detach() >= 0
        change = (sgn[:, 1:] != sgn[:, :-1]) & m[:, 1:] & m[:, :-1]
        n_changes = torch.cat([torch.zeros_like(change[:, :1], dtype=torch.long), torch.cumsum(change.long(), 1)], 1)
        tr = tr & ~((n_changes >= 2) & (target < 0))

    def per_ray_mean(err, sel):  # masked means: no host transfer
        cnt = sel.sum(1)
        per_ray = torch.where(sel, err, 0.0).sum(1) / cnt.clamp(min=1)
        return per_ray.sum() / (cnt > 0).sum().clamp(min=1)

    return per_ray_mean((sdf - 1.0) ** 2, fs), per_ray_mean((truncation * (sdf - target)) ** 2, tr)
