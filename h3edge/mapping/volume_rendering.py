"""SDF-based volume rendering (H3-Mapping, Sec. IV-C) over padded per-ray samples.

    alpha_j = sigmoid(s_j / beta) * sigmoid(-s_j / beta)
    C = sum_j alpha_j c_j / sum_j alpha_j,     D = sum_j alpha_j d_j / sum_j alpha_j

Samples come as (R, S) tensors with a validity mask (samples exist only inside leaf voxels the ray
crosses). ``s`` and ``beta`` must share a unit: the mapper passes SDF in truncation units with the
authors' beta = 0.05, an effective kernel of 0.05 * 0.05 m = 2.5 mm. A ray whose weights sum to
(almost) nothing renders as empty: depth 0 and colour 0, with ``hit`` False.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


def render_weights(sdf: torch.Tensor, beta: float, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Unnormalised weights alpha (R, S); masked-out samples weigh 0."""
    a = torch.sigmoid(sdf / beta) * torch.sigmoid(-sdf / beta)
    return a if mask is None else a * mask


@dataclass
class RenderedRays:
    depth: torch.Tensor  # (R,)
    color: torch.Tensor  # (R, 3)
    hit: torch.Tensor  # (R,) bool


def composite(sdf: torch.Tensor, depth: torch.Tensor, color: torch.Tensor | None, beta: float,
              mask: torch.Tensor | None = None, min_weight: float = 1e-6,
              color_mask: torch.Tensor | None = None) -> RenderedRays:
    """Normalised weighted depth (and colour) per ray from per-sample SDF, depth and colour.

    ``color_mask`` (R, S): the samples whose colour was evaluated (a subset of ``mask``); the colour
    is normalised over their weights alone, so skipping samples of negligible weight does not darken
    the ray (see :func:`color_samples`)."""
    a = render_weights(sdf, beta, mask)
    wsum = a.sum(-1)
    hit = wsum > min_weight
    norm = torch.where(hit, wsum, torch.ones_like(wsum))
    d = (a * depth).sum(-1) / norm * hit
    if color is None:
        c = torch.zeros(sdf.shape[0], 3, dtype=sdf.dtype, device=sdf.device)
    else:  # normalised over the weights of the samples whose colour is known (all of them by default)
        ac, csum = (a, norm) if color_mask is None else (a * color_mask, (a * color_mask).sum(-1))
        c = (ac[..., None] * color).sum(-2) / torch.where(csum > 0, csum, torch.ones_like(csum))[:, None] * hit[:, None]
    return RenderedRays(d, c, hit)


def color_samples(sdf: torch.Tensor, beta: float, mask: torch.Tensor, floor: float) -> torch.Tensor:
    """Samples (R, S) worth evaluating colour at: inside ``mask`` with a normalised weight
    alpha_j / sum_k alpha_k above ``floor`` (all of ``mask`` for floor 0). With the paper's beta the
    weight sits within a few mm of the zero crossing, so on 1 cm band samples most weigh ~0."""
    if floor <= 0:
        return mask
    with torch.no_grad():
        a = render_weights(sdf, beta, mask)
        return mask & (a > floor * a.sum(-1, keepdim=True))
