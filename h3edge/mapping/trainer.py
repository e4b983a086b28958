"""One optimisation step of the map on a batch of rays with measured depth and colour.

Training samples (per ray, z-depth units since ray directions have camera z = 1):
- ``band_samples`` evenly spaced at ``step`` around the measured depth (the truncation band,
  where the render weights live: colour and depth are rendered from these; those more than
  ``band_behind`` behind it are left out, and those more than ``sdf_behind`` take no SDF target);
- ``free_samples`` between ``near`` and depth - truncation (free-space loss): with
  ``free_in_voxels`` drawn among ``free_candidates`` stratified candidates that fall inside
  allocated leaf voxels (where the field exists and a phantom surface could be), otherwise
  stratified over the whole range.
Only samples inside allocated leaf voxels count, as in the paper. This concentrates the paper's
budget (1 cm steps through every voxel the ray crosses) where the losses act. Drawn over the whole
range, most free-space samples miss every voxel (6 % land in one on the tiny simulated scene,
48 % with ``free_in_voxels``), yet on real Kinect data the in-voxel draw measured no better, so it
is off by default. The full-ray sampling is what novel-view rendering uses.

Band samples behind the measured depth take a negative SDF target, except (``carve_behind``) where
another view of the batch measured a depth more than ``carve_margin`` beyond them
(:mod:`h3edge.mapping.visibility`): behind a thin object those targets would fill free space.
With fine free-space votes (:mod:`h3edge.mapping.cell_votes`, ``votes.cell`` > 0), they also take
none in cells the majority of all mapped frames saw through, and ``votes.points`` points drawn in
such cells near a surface the priors put there take the sign term relu(-s)^2 (weight
``weights.seen_free``): space most views saw through must not read inside. The term is flat
wherever s >= 0, and few drawn points read inside (0.9 % on the real set), so a forward pass
without autograd picks those first (:func:`reading_inside`), and only they join the step's
forward and backward passes: the same loss and gradient for a fraction of the cost.

Surface colour points (``surface_color_points``, a departure from the paper, which trains colour
only through volume rendering): more pixels of the same frames, back-projected with their
measured depth; the colour field at that point takes the pixel's colour (L1, weight
``weights.surface_rgb``). A point costs one texture lookup and the colour MLP, against a ray's
~20 samples of the SDF field, so a step sees several times more of each frame's colour.
With ``weights.surface_sdf`` > 0 the same points also take SDF = 0 (the measured surface pins the
zero level at more pixels than the rays reach; off in every profile: it sharpens clean depth but
fits Kinect noise, docs/continuous_training.md).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from h3edge.mapping.cell_votes import CellVotes
from h3edge.mapping.field import Field
from h3edge.mapping.losses import LossWeights, depth_l1, free_space_and_sdf, rgb_l1, s3im
from h3edge.mapping.visibility import PooledDepth, seen_through
from h3edge.mapping.volume_rendering import color_samples, composite
from h3edge.mapping.voxels import PriorAdam, VoxelMap


@dataclass(frozen=True)
class TrainConfig:
    lr: float = 1e-2  # one Adam learning rate for everything (authors)
    step: float = 0.01  # m between band samples (the paper's 1 cm)
    band_samples: int = 11  # covers +-5 cm = the truncation band
    # m behind the measured depth the band's samples reach (the paper: the truncation, a symmetric
    # band); behind a thin object the negative targets of a deep band lie in free space
    band_behind: float = 0.05
    # m behind the measured depth band samples still take an SDF target (the paper: the truncation);
    # deeper band samples only carry the colour and depth rendering losses
    sdf_behind: float = 0.05
    free_samples: int = 8
    # free-space samples where the field lives, inside allocated voxels (as the paper's sampler):
    # measured no better than stratified samples on real Kinect data (docs/silhouettes.md), off
    free_in_voxels: bool = False
    free_candidates: int = 64  # stratified candidates per ray the in-voxel free samples are drawn from
    # colour only at band samples whose normalised render weight exceeds this (0: at every in-voxel
    # band sample, the paper's); the skipped samples carry < floor of a ray's colour each
    color_weight_floor: float = 1e-3
    surface_aware: bool = True
    # band samples behind the measured depth take no SDF target where another view of the batch
    # (its keyframes and the current frame) measured more than carve_margin beyond them: behind a
    # thin object the negative targets would fill the free space other views saw. A departure from
    # the paper (false), measured on real Kinect data: pixels rendered > 5 cm in front 4.9 -> 3.8 %,
    # Depth L1 -10 % (docs/silhouettes.md)
    carve_behind: bool = True
    carve_margin: float = 0.03  # m: depth noise and pose error a view must see past
    carve_stride: int = 4  # pixels per side of the pooled depth blocks a view keeps for the test
    # pixels per iteration whose colour trains the colour field at their measured surface point,
    # besides the rays (0: the paper's, colour only through volume rendering; the Orin profiles set
    # 2048: sim +0.8 dB, studio +0.6 dB, real and Replica unchanged; x86-cpu 8192 with its third
    # iteration: Replica +0.44 dB, sim +0.3-0.5, real -0.09; docs/continuous_training.md)
    surface_color_points: int = 0
    weights: LossWeights = field(default_factory=LossWeights)


@dataclass
class RayBatch:
    origins: torch.Tensor  # (R, 3)
    dirs: torch.Tensor  # (R, 3) world directions with camera z = 1
    depth: torch.Tensor  # (R,) measured z-depth, 0 = invalid
    color: torch.Tensor  # (R, 3) in [0, 1]
    views: list[PooledDepth] = field(default_factory=list)  # the frames the rays came from (carve_behind)
    surface_points: torch.Tensor | None = None  # (P, 3) world points at measured depths (surface colour)
    surface_color: torch.Tensor | None = None  # (P, 3) their pixels' colours in [0, 1]


def sample_depths(depth: torch.Tensor, cfg: TrainConfig, truncation: float, near: float,
                  generator: torch.Generator | None = None) -> tuple[torch.Tensor, int]:
    """Sample z-depths (R, free + band), sorted along each row, the free ones from ``near`` (m,
    :attr:`RenderConfig.near`); returns them and where the band starts."""
    r = len(depth)
    half = (cfg.band_samples - 1) / 2
    offsets = cfg.step * (torch.arange(cfg.band_samples, dtype=depth.dtype, device=depth.device) - half)
    band = depth[:, None] + offsets[offsets <= cfg.band_behind + 1e-6]
    far = (depth - truncation).clamp(min=near)
    u = (torch.arange(cfg.free_samples, device=depth.device, dtype=depth.dtype)
         + torch.rand(r, cfg.free_samples, generator=generator, device=depth.device, dtype=depth.dtype))
    free = near + (far - near)[:, None] * u / cfg.free_samples
    return torch.cat([free, band], 1), cfg.free_samples


def free_depths_in_voxels(rays: RayBatch, voxels: VoxelMap, cfg: TrainConfig, truncation: float, near: float,
                          generator: torch.Generator | None = None) -> torch.Tensor:
    """``cfg.free_samples`` z-depths per ray (R, F), sorted, between ``near`` and depth - truncation,
    inside allocated voxels where the ray has enough of them: picked at random among
    ``cfg.free_candidates`` stratified candidates that fall in a voxel (rays with fewer keep some
    candidates outside, which the voxel mask drops)."""
    from h3edge.mapping.raymarch import PriorLookup

    depth = rays.depth
    r, m, k = len(depth), cfg.free_candidates, cfg.free_samples
    dev, dt = depth.device, depth.dtype
    far = (depth - truncation).clamp(min=near)
    u = torch.arange(m, device=dev, dtype=dt) + torch.rand(r, m, generator=generator, device=dev, dtype=dt)
    cand = near + (far - near)[:, None] * u / m  # (R, M)
    pts = rays.origins[:, None, :] + rays.dirs[:, None, :] * cand[..., None]
    _, vox = PriorLookup(voxels)(pts.reshape(-1, 3).detach().cpu().numpy())
    inside = torch.from_numpy(vox.reshape(r, m) >= 0).to(dev)
    key = torch.rand(r, m, generator=generator, device=dev, dtype=dt) + (~inside).to(dt)  # inside first
    pick = torch.topk(key, k, dim=1, largest=False).indices
    return torch.sort(cand.gather(1, pick), dim=1).values


def locate_surface_points(voxels: VoxelMap, rays: RayBatch) -> tuple[np.ndarray, np.ndarray] | None:
    """:meth:`VoxelMap.locate` of ``rays.surface_points`` (once a step for the losses that read
    them), or None when the batch has none."""
    if rays.surface_points is None or len(rays.surface_points) == 0:
        return None
    return voxels.locate(rays.surface_points.detach().cpu().numpy())


def surface_color_loss(neural_field: Field, voxels: VoxelMap, rays: RayBatch,
                       located: tuple[np.ndarray, np.ndarray] | None = None) -> torch.Tensor | None:
    """Mean L1 between the colour field at ``rays.surface_points`` and their pixels' colours, over
    the points inside allocated voxels; None when there are none. ``located``: the points'
    :func:`locate_surface_points`, when already known."""
    located = locate_surface_points(voxels, rays) if located is None else located
    if located is None:
        return None
    vox = located[0]
    keep = torch.from_numpy(vox >= 0).to(rays.surface_points.device)
    if not keep.any():
        return None
    idx = torch.from_numpy(vox).to(rays.surface_points.device)[keep]
    pred = neural_field.color(rays.surface_points[keep], idx).to(torch.float32)
    return rgb_l1(pred, rays.surface_color[keep])


def surface_sdf_loss(neural_field: Field, voxels: VoxelMap, rays: RayBatch, truncation: float,
                     located: tuple[np.ndarray, np.ndarray] | None = None) -> torch.Tensor | None:
    """Mean squared SDF (in metres, as the band's L_sdf) of the field at ``rays.surface_points``, the
    measured surface, over the points inside allocated voxels; None when there are none.
    ``located``: the points' :func:`locate_surface_points`, when already known."""
    located = locate_surface_points(voxels, rays) if located is None else located
    if located is None or not (located[0] >= 0).any():
        return None
    sdf, inside = neural_field.sdf(rays.surface_points, voxels, located)
    return ((truncation * sdf[inside]) ** 2).mean()


def seen_free_loss(sdf: torch.Tensor, inside: torch.Tensor, truncation: float, count: int | None = None
                   ) -> torch.Tensor | None:
    """Mean squared negative part of the SDF ``sdf`` (truncation units; in metres, as L_sdf) at
    points drawn in cells the frames voted free (:meth:`CellVotes.sample_free`), over those in a
    voxel (``inside``): space most views saw through must not read inside. ``count``: how many
    points the mean is over, when the points that read outside (zero loss, zero gradient) were left
    out of ``sdf`` (:func:`reading_inside`); default: those ``inside``. None when there are none."""
    n = int(inside.sum()) if count is None else count
    if n == 0 or not inside.any():
        return None
    return ((truncation * torch.relu(-sdf[inside])) ** 2).sum() / n


def reading_inside(neural_field: Field, voxels: VoxelMap, points: tuple[np.ndarray, np.ndarray, np.ndarray],
                   device: torch.device) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], int]:
    """The seen-free points (world, voxel ids, positions in the voxel) whose SDF reads inside (< 0),
    from a forward pass without autograd, and how many of all of them lie in a voxel. The others
    add nothing to :func:`seen_free_loss` (its hinge is flat at s >= 0), so leaving them out of the
    training step's forward and backward passes gives the same gradient at a fraction of the cost."""
    p, vox, frac = points
    if len(p) == 0:
        return points, 0
    with torch.no_grad():
        sdf, inside = neural_field.sdf(torch.from_numpy(p.astype(np.float32)).to(device), voxels, (vox, frac))
    keep = (inside & (sdf < 0)).cpu().numpy()
    return (p[keep], vox[keep], frac[keep]), int(inside.sum())


def train_step(neural_field: Field, voxels: VoxelMap, rays: RayBatch, optimizer: torch.optim.Optimizer,
               cfg: TrainConfig, near: float, generator: torch.Generator | None = None,
               prior_opt: PriorAdam | None = None, votes: CellVotes | None = None,
               commit: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext) -> dict[str, float]:
    """Forward, losses, backward; Adam on the MLPs (``optimizer``, which may also hold the priors),
    lazy Adam on the SDF priors (``prior_opt``) and on the touched hash-table rows. Free-space
    samples start at ``near`` (m). ``votes``: band samples behind the depth in cells the frames
    voted free take no SDF target (:mod:`h3edge.mapping.cell_votes`). ``commit``: a context the
    optimiser updates run in (the map lock, when integration runs on another thread meanwhile:
    the forward and backward passes only read the map, and a prior tensor that integration grew
    meanwhile takes the gradient the step computed). The step's rays count in the voxels their
    measured surface points fall in (:meth:`VoxelMap.count_trained`)."""
    tr = voxels.cfg.truncation
    priors_used = voxels.priors
    t, b0 = sample_depths(rays.depth, cfg, tr, near, generator)
    if cfg.free_in_voxels and cfg.free_samples > 0 and len(voxels):
        t = torch.cat([free_depths_in_voxels(rays, voxels, cfg, tr, near, generator), t[:, b0:]], 1)
    r, s = t.shape
    pts = rays.origins[:, None, :] + rays.dirs[:, None, :] * t[..., None]
    flat = pts.reshape(-1, 3)
    vox, frac = voxels.locate(flat.detach().cpu().numpy())
    free_pts = None  # points in cells voted free, (world, voxel ids, positions in the voxel)
    if votes is not None and votes.cfg.points > 0 and cfg.weights.seen_free > 0:
        free_pts, free_count = reading_inside(neural_field, voxels,
                                              votes.sample_free(votes.cfg.points, voxels, generator), flat.device)
        free_pts = free_pts if len(free_pts[0]) else None
    if free_pts is not None:  # one field evaluation for the ray samples and the seen-free points
        p, pv, pf = free_pts
        both_located = (np.concatenate([vox, pv]), np.concatenate([frac, pf]))
        both, both_in = neural_field.sdf(torch.cat([flat, torch.from_numpy(p.astype(np.float32)).to(flat.device)]),
                                         voxels, both_located)
        sdf, inside, free_sdf, free_in = both[:r * s], both_in[:r * s], both[r * s:], both_in[r * s:]
    else:
        sdf, inside = neural_field.sdf(flat, voxels, (vox, frac))
    sdf, inside = sdf.reshape(r, s), inside.reshape(r, s) & (rays.depth > 0)[:, None]
    band_pts = pts[:, b0:].reshape(-1, 3)
    band_vox = torch.from_numpy(vox.reshape(r, s)[:, b0:].reshape(-1)).to(flat.device)
    need = color_samples(sdf[:, b0:], neural_field.cfg.beta, inside[:, b0:], cfg.color_weight_floor)
    band_in = torch.nonzero(need.reshape(-1)).squeeze(1)  # colour only where it weighs
    col = torch.zeros(len(band_pts), 3, device=flat.device).index_copy(
        0, band_in, neural_field.color(band_pts[band_in], band_vox[band_in]).to(torch.float32)).reshape(r, s - b0, 3)
    out = composite(sdf[:, b0:], t[:, b0:], col, neural_field.cfg.beta, inside[:, b0:], color_mask=need)
    sdf_mask, carved = inside, 0.0
    use_views, use_votes = cfg.carve_behind and bool(rays.views), votes is not None
    if use_views or use_votes:
        behind = inside & (t > rays.depth[:, None])
        free = torch.zeros(int(behind.sum()), dtype=torch.bool, device=flat.device)
        if use_views:
            free |= seen_through(pts[behind].detach(), rays.views, cfg.carve_margin)
        if use_votes:
            mask = behind.reshape(-1).cpu().numpy()
            free |= torch.from_numpy(votes.seen_free(vox[mask], frac[mask])).to(flat.device)
        sdf_mask = inside.clone()
        sdf_mask[behind] = ~free
        carved = float(free.float().mean()) if len(free) else 0.0
    # pack valid samples to the front of each row (order kept) for the surface-aware rule
    order = torch.sort((~sdf_mask).to(torch.int8), dim=1, stable=True).indices
    fs, sdf_loss = free_space_and_sdf(sdf.gather(1, order), t.gather(1, order), rays.depth,
                                      sdf_mask.gather(1, order), tr, cfg.surface_aware, cfg.sdf_behind / tr)
    w = cfg.weights
    hit = out.hit
    l_rgb = rgb_l1(out.color[hit], rays.color[hit]) if hit.any() else sdf.sum() * 0
    if w.s3im and hit.sum() >= w.s3im_patch_width:
        l_rgb = l_rgb + s3im(out.color[hit], rays.color[hit], w.s3im_kernel, w.s3im_stride, w.s3im_repeats,
                             w.s3im_patch_width, generator)
    l_d = depth_l1(out.depth[hit], rays.depth[hit]) if hit.any() else sdf.sum() * 0
    loss = w.rgb * l_rgb + w.depth * l_d + w.free_space * fs + w.sdf * sdf_loss
    located = locate_surface_points(voxels, rays)  # one lookup for both surface-point losses
    measured = rays.depth > 0  # the voxels this step's rays ended in, counted once it commits
    ends = voxels.locate((rays.origins[measured] + rays.dirs[measured] * rays.depth[measured, None])
                         .detach().cpu().numpy())[0]
    l_surf = surface_color_loss(neural_field, voxels, rays, located)
    if l_surf is not None:
        loss = loss + w.surface_rgb * l_surf
    l_surf_sdf = surface_sdf_loss(neural_field, voxels, rays, tr, located) if w.surface_sdf > 0 else None
    if l_surf_sdf is not None:
        loss = loss + w.surface_sdf * l_surf_sdf
    l_free_cells = seen_free_loss(free_sdf, free_in, tr, free_count) if free_pts is not None else None
    if l_free_cells is not None:
        loss = loss + w.seen_free * l_free_cells
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    with commit():
        optimizer.step()
        if prior_opt is not None:
            prior_opt.step(voxels, priors_used)
        neural_field.sparse_step(cfg.lr)
        voxels.count_trained(ends)
    return {"loss": float(loss.detach()), "rgb": float(l_rgb.detach()), "depth": float(l_d.detach()),
            "free_space": float(fs.detach()), "sdf": float(sdf_loss.detach()), "hit_ratio": float(hit.float().mean()),
            "carved": carved, "surface_rgb": float(l_surf.detach()) if l_surf is not None else 0.0,
            "surface_sdf": float(l_surf_sdf.detach()) if l_surf_sdf is not None else 0.0,
            "seen_free": float(l_free_cells.detach()) if l_free_cells is not None else 0.0}
