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

Band samples behind the measured depth take a negative SDF target, except, with fine free-space
votes (:mod:`h3edge.mapping.cell_votes`, ``votes.cell`` > 0), in cells the majority of all mapped
frames saw through (behind a thin object those targets would fill free space), and ``votes.points`` points drawn in
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

:class:`Trainer` runs a step in stages, each a method: :meth:`~Trainer.sample` (depths along the
rays, located in the voxels; the seen-free points) -> :meth:`~Trainer.evaluate` (the SDF field at
every sample, one pass) -> :meth:`~Trainer.composite` (colour where it weighs, volume rendering)
-> :meth:`~Trainer.losses` (``LOSS_TERMS``: one small function a term, each with its weight in
:class:`~h3edge.mapping.losses.LossWeights`) -> :meth:`~Trainer.apply` (backward, the optimisers,
the trained-ray counts). The reported losses come back to the host in one transfer a step.
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
from h3edge.mapping.volume_rendering import color_samples, composite
from h3edge.mapping.voxels import PriorAdam, VoxelMap


@dataclass(frozen=True)
class TrainConfig:
    lr: float = 1e-2
    """one Adam learning rate for everything (authors)"""
    step: float = 0.01
    """m between band samples (the paper's 1 cm)"""
    band_samples: int = 11
    """covers +-5 cm = the truncation band"""
    band_behind: float = 0.05
    """m behind the measured depth the band's samples reach (the paper: the truncation, a symmetric band); behind a thin
    object the negative targets of a deep band lie in free space"""
    sdf_behind: float = 0.05
    """m behind the measured depth band samples still take an SDF target (the paper: the truncation); deeper band
    samples only carry the colour and depth rendering losses"""
    free_samples: int = 8
    """stratified free-space samples per ray between near and depth - truncation (paper: 8)"""
    free_in_voxels: bool = True
    """free-space samples inside the allocated voxels a ray crosses (false: stratified along the ray); paper true;
    D0-5"""
    free_candidates: int = 64
    """stratified candidates per ray the in-voxel free samples are drawn from"""
    color_weight_floor: float = 0.0
    """colour only at band samples whose normalised render weight exceeds this; paper 0 (every band sample); D0-6"""
    surface_aware: bool = True
    """the paper's surface-aware SDF rule: no negative targets past the second sign change along a ray"""
    surface_color_points: int = 0
    """pixels per iteration whose colour trains the colour field at their measured surface point, besides the rays;
    paper 0 (colour only through volume rendering); D0-6"""
    weights: LossWeights = field(default_factory=LossWeights)
    """the loss weights: set by the profile's [losses] table (LossWeights)"""


@dataclass
class RayBatch:
    origins: torch.Tensor  # (R, 3)
    dirs: torch.Tensor  # (R, 3) world directions with camera z = 1
    depth: torch.Tensor  # (R,) measured z-depth, 0 = invalid
    color: torch.Tensor  # (R, 3) in [0, 1]
    surface_points: torch.Tensor | None = None  # (P, 3) world points at measured depths (surface colour)
    surface_color: torch.Tensor | None = None  # (P, 3) their pixels' colours in [0, 1]


def sample_depths(depth: torch.Tensor, cfg: TrainConfig, truncation: float, near: float,
                  generator: torch.Generator | None = None) -> tuple[torch.Tensor, int]:
    """Sample z-depths (R, free + band), sorted along each row, the free ones from ``near`` (m,
    :attr:`RenderConfig.near`); returns them and where the band starts."""
    r = len(depth)
    half = (cfg.band_samples - 1) / 2
    kept = sum(cfg.step * (k - half) <= cfg.band_behind + 1e-6 for k in range(cfg.band_samples))  # on the host
    offsets = cfg.step * (torch.arange(kept, dtype=depth.dtype, device=depth.device) - half)
    band = depth[:, None] + offsets
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
    depth = rays.depth
    r, m, k = len(depth), cfg.free_candidates, cfg.free_samples
    dev, dt = depth.device, depth.dtype
    far = (depth - truncation).clamp(min=near)
    u = torch.arange(m, device=dev, dtype=dt) + torch.rand(r, m, generator=generator, device=dev, dtype=dt)
    cand = near + (far - near)[:, None] * u / m  # (R, M)
    pts = rays.origins[:, None, :] + rays.dirs[:, None, :] * cand[..., None]
    inside = voxels.locate_points(pts.reshape(-1, 3))[0].reshape(r, m) >= 0
    key = torch.rand(r, m, generator=generator, device=dev, dtype=dt) + (~inside).to(dt)  # inside first
    pick = torch.topk(key, k, dim=1, largest=False).indices
    return torch.sort(cand.gather(1, pick), dim=1).values


def locate_surface_points(voxels: VoxelMap, rays: RayBatch) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:meth:`VoxelMap.locate_points` of ``rays.surface_points`` (once a step for the losses that
    read them), or None when the batch has none."""
    if rays.surface_points is None or len(rays.surface_points) == 0:
        return None
    return voxels.locate_points(rays.surface_points)


def surface_color_loss(neural_field: Field, voxels: VoxelMap, rays: RayBatch,
                       located: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor | None:
    """Mean L1 between the colour field at ``rays.surface_points`` and their pixels' colours, over
    the points inside allocated voxels (0 when there are none: a masked mean, no host transfer);
    None when the batch has no surface points. ``located``: the points'
    :func:`locate_surface_points`, when already known."""
    located = locate_surface_points(voxels, rays) if located is None else located
    if located is None:
        return None
    vox = located[0]
    keep = vox >= 0
    pred = neural_field.color(rays.surface_points, vox, residual=1.0).to(torch.float32)
    err = torch.where(keep[:, None], (pred - rays.surface_color).abs(), 0.0)
    return err.sum() / (3 * keep.sum()).clamp(min=1)


def seen_free_loss(sdf: torch.Tensor, inside: torch.Tensor, truncation: float,
                   count: int | torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared negative part of the SDF ``sdf`` (truncation units; in metres, as L_sdf) at
    points drawn in cells the frames voted free (:meth:`CellVotes.sample_free`), over those in a
    voxel (``inside``): space most views saw through must not read inside. ``count``: how many
    points the mean is over, when the points that read outside (zero loss, zero gradient) were left
    out of ``sdf`` (:func:`reading_inside`); default: those ``inside``. 0 when there are none (a
    masked mean: no host transfer)."""
    n = inside.sum() if count is None else torch.as_tensor(count, device=sdf.device)
    hinge = torch.where(inside, (truncation * torch.relu(-sdf)) ** 2, 0.0)
    return hinge.sum() / n.clamp(min=1)


def reading_inside(neural_field: Field, voxels: VoxelMap,
                   points: tuple[torch.Tensor, torch.Tensor, torch.Tensor]
                   ) -> tuple[tuple[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]:
    """The seen-free points (world (P, 3), voxel ids (P,), positions in the voxel (P, 3), tensors on
    the map's device) whose SDF reads inside (< 0), from a forward pass without autograd, and how
    many of all of them lie in a voxel (a 0-d tensor). The others add nothing to
    :func:`seen_free_loss` (its hinge is flat at s >= 0), so leaving them out of the training step's
    forward and backward passes gives the same gradient at a fraction of the cost. The selection is
    a boolean-mask index (on CUDA a sync for its size, no copy of the data)."""
    p, vox, frac = points
    if len(p) == 0:
        return points, torch.zeros((), dtype=torch.long, device=p.device)
    with torch.no_grad():
        sdf, inside = neural_field.sdf(p, voxels, (vox, frac))
    keep = inside & (sdf < 0)
    return (p[keep], vox[keep], frac[keep]), inside.sum()


@dataclass
class Samples:
    """What :meth:`Trainer.sample` draws for one step."""

    t: torch.Tensor  # (R, S) z-depths along each ray, the free samples first
    band_start: int  # column where the band samples start
    pts: torch.Tensor  # (R, S, 3) world points
    vox: torch.Tensor  # (R * S,) int64 voxel id of each point (-1: none)
    frac: torch.Tensor  # (R * S, 3) its position in the voxel
    free_pts: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None  # seen-free points that read inside
    free_count: torch.Tensor | int  # seen-free points drawn inside a voxel (the mean's denominator)


@dataclass
class FieldEval:
    """The SDF field at a step's samples (truncation units) and which count (in a voxel, valid depth)."""

    sdf: torch.Tensor  # (R, S)
    inside: torch.Tensor  # (R, S) bool
    free_sdf: torch.Tensor | None  # at the seen-free points
    free_in: torch.Tensor | None


@dataclass
class Rendered:
    """A step's volume rendering and the SDF mask its losses use."""

    color: torch.Tensor  # (R, 3)
    depth: torch.Tensor  # (R,)
    hit: torch.Tensor  # (R,) bool: rays whose render weights reached the surface
    sdf_mask: torch.Tensor  # (R, S) bool: samples that take an SDF / free-space target
    carved: torch.Tensor  # () share of the band samples behind the depth that lost their target to the votes


@dataclass
class StepInputs:
    """Everything a loss term reads."""

    rays: RayBatch
    samples: Samples
    field_eval: FieldEval
    rendered: Rendered
    truncation: float
    cfg: TrainConfig
    surface_located: tuple[torch.Tensor, torch.Tensor] | None
    generator: torch.Generator | None
    fs_sdf: tuple[torch.Tensor, torch.Tensor] | None = None  # (L_fs, L_sdf), once both terms asked


def _rgb_term(neural_field: Field, voxels: VoxelMap, x: StepInputs) -> torch.Tensor:
    """L1 on the rendered colour of the rays that hit (a masked mean: 0 when none do) + S3IM over
    them (their indices from ``nonzero``: on CUDA a sync for the count, no copy of the data)."""
    hit, w = x.rendered.hit, x.cfg.weights
    loss = rgb_l1(x.rendered.color, x.rays.color, hit)
    if w.s3im:
        idx = torch.nonzero(hit).squeeze(1)
        if len(idx) >= w.s3im_patch_width:
            loss = loss + s3im(x.rendered.color[idx], x.rays.color[idx], w.s3im_kernel, w.s3im_stride,
                               w.s3im_repeats, w.s3im_patch_width, x.generator)
    return loss


def _depth_term(neural_field: Field, voxels: VoxelMap, x: StepInputs) -> torch.Tensor:
    """L1 on the rendered depth of the rays that hit (a masked mean: 0 when none do)."""
    return depth_l1(x.rendered.depth, torch.where(x.rendered.hit, x.rays.depth, 0.0))


def _free_space_and_sdf(x: StepInputs) -> tuple[torch.Tensor, torch.Tensor]:
    """(L_fs, L_sdf) over the masked samples, packed to the front of each row (order kept) for the
    surface-aware rule; computed once a step for both terms."""
    if x.fs_sdf is None:
        s, mask = x.field_eval.sdf, x.rendered.sdf_mask
        order = torch.sort((~mask).to(torch.int8), dim=1, stable=True).indices
        x.fs_sdf = free_space_and_sdf(s.gather(1, order), x.samples.t.gather(1, order), x.rays.depth,
                                      mask.gather(1, order), x.truncation, x.cfg.surface_aware,
                                      x.cfg.sdf_behind / x.truncation)
    return x.fs_sdf


def _free_space_term(neural_field: Field, voxels: VoxelMap, x: StepInputs) -> torch.Tensor:
    """Free-space samples pushed to the truncation value."""
    return _free_space_and_sdf(x)[0]


def _sdf_term(neural_field: Field, voxels: VoxelMap, x: StepInputs) -> torch.Tensor:
    """Band samples fitted to the measured signed distance."""
    return _free_space_and_sdf(x)[1]


def _surface_rgb_term(neural_field: Field, voxels: VoxelMap, x: StepInputs) -> torch.Tensor | None:
    """The colour field at the surface colour points (:func:`surface_color_loss`)."""
    return surface_color_loss(neural_field, voxels, x.rays, x.surface_located)


def _seen_free_term(neural_field: Field, voxels: VoxelMap, x: StepInputs) -> torch.Tensor | None:
    """SDF >= 0 at points in cells the frames voted free (:func:`seen_free_loss`)."""
    if x.samples.free_pts is None:
        return None
    return seen_free_loss(x.field_eval.free_sdf, x.field_eval.free_in, x.truncation, x.samples.free_count)


# (name: the LossWeights field that weighs it and the key it is reported under, term); summed in this
# order. A term that returns None (nothing to fit this step) adds nothing and reports 0.
LOSS_TERMS: tuple[tuple[str, Callable[[Field, VoxelMap, StepInputs], torch.Tensor | None]], ...] = (
    ("rgb", _rgb_term),
    ("depth", _depth_term),
    ("free_space", _free_space_term),
    ("sdf", _sdf_term),
    ("surface_rgb", _surface_rgb_term),
    ("seen_free", _seen_free_term),
)


class Trainer:
    """One optimisation step of a map on a :class:`RayBatch`, in stages (module docstring).

    ``cfg`` (its ``weights`` the loss weights), ``near`` (m: free-space samples start there),
    the map's ``neural_field`` and ``voxels``, ``optimizer`` (Adam on the MLPs), ``prior_opt`` (lazy
    Adam on the SDF priors), ``votes`` (fine free-space votes, or None), ``generator`` (the map's
    torch generator: every random draw of a step comes from it)."""

    def __init__(self, cfg: TrainConfig, near: float, neural_field: Field, voxels: VoxelMap,
                 optimizer: torch.optim.Optimizer, prior_opt: PriorAdam | None = None,
                 votes: CellVotes | None = None, generator: torch.Generator | None = None):
        self.cfg, self.near = cfg, near
        self.field, self.voxels, self.optimizer, self.prior_opt = neural_field, voxels, optimizer, prior_opt
        self.votes, self.generator = votes, generator

    def step(self, rays: RayBatch,
             commit: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext) -> dict[str, float]:
        """Sample, evaluate, composite, losses, apply; the losses (floats: ``loss``, each term,
        ``hit_ratio``, ``carved``). ``commit``: a context the updates run in (the map lock, when
        integration runs on another thread meanwhile: the forward and backward passes only read the
        map, and a prior tensor that integration grew meanwhile takes the gradient the step
        computed)."""
        priors_used = self.voxels.priors
        samples = self.sample(rays)
        field_eval = self.evaluate(rays, samples)
        rendered = self.composite(rays, samples, field_eval)
        inputs = StepInputs(rays, samples, field_eval, rendered, self.voxels.cfg.truncation, self.cfg,
                            locate_surface_points(self.voxels, rays), self.generator)
        loss, terms = self.losses(inputs)
        self.apply(loss, rays, priors_used, commit)
        names = ["loss", *terms, "hit_ratio", "carved"]
        values = torch.stack([loss.detach(), *(v.detach().reshape(()).to(loss.dtype) for v in terms.values()),
                              rendered.hit.float().mean().to(loss.dtype), rendered.carved.to(loss.dtype)])
        return dict(zip(names, values.tolist()))  # the step's one host transfer of its losses

    def sample(self, rays: RayBatch) -> Samples:
        """Depths along each ray (free + band; :func:`sample_depths`, in voxels with
        ``free_in_voxels``), their world points located in the voxels, and the seen-free points that
        read inside (:func:`reading_inside`)."""
        cfg, voxels, tr = self.cfg, self.voxels, self.voxels.cfg.truncation
        t, b0 = sample_depths(rays.depth, cfg, tr, self.near, self.generator)
        if cfg.free_in_voxels and cfg.free_samples > 0 and len(voxels):
            t = torch.cat([free_depths_in_voxels(rays, voxels, cfg, tr, self.near, self.generator), t[:, b0:]], 1)
        pts = rays.origins[:, None, :] + rays.dirs[:, None, :] * t[..., None]
        vox, frac = voxels.locate_points(pts.reshape(-1, 3))
        free_pts, free_count = None, 0
        votes = self.votes
        if votes is not None and votes.cfg.points > 0 and cfg.weights.seen_free > 0:
            if voxels.device_lookup:
                drawn = votes.sample_free_tensor(votes.cfg.points, voxels, self.generator)
            else:
                p, v, f = votes.sample_free(votes.cfg.points, voxels, self.generator)
                drawn = (torch.from_numpy(p.astype(np.float32)).to(pts.device), torch.from_numpy(v).to(pts.device),
                         torch.from_numpy(f.astype(np.float32)).to(pts.device))
            free_pts, free_count = reading_inside(self.field, voxels, drawn)
        return Samples(t, b0, pts, vox, frac, free_pts, free_count)

    def evaluate(self, rays: RayBatch, smp: Samples) -> FieldEval:
        """The SDF field at every sample and seen-free point, in one pass."""
        r, s = smp.t.shape
        flat = smp.pts.reshape(-1, 3)
        free_sdf = free_in = None
        if smp.free_pts is not None:
            p, pv, pf = smp.free_pts
            located = (torch.cat([smp.vox, pv]), torch.cat([smp.frac, pf]))
            both, both_in = self.field.sdf(torch.cat([flat, p]), self.voxels, located)
            sdf, inside, free_sdf, free_in = both[:r * s], both_in[:r * s], both[r * s:], both_in[r * s:]
        else:
            sdf, inside = self.field.sdf(flat, self.voxels, (smp.vox, smp.frac))
        inside = inside.reshape(r, s) & (rays.depth > 0)[:, None]
        return FieldEval(sdf.reshape(r, s), inside, free_sdf, free_in)

    def composite(self, rays: RayBatch, smp: Samples, ev: FieldEval) -> Rendered:
        """Colour at the band samples whose render weight counts, volume rendering of the band, and
        the SDF mask: every sample in a voxel, less the band samples behind the depth in cells the
        votes call free."""
        r, s = smp.t.shape
        b0, dev = smp.band_start, smp.pts.device
        band_pts = smp.pts[:, b0:].reshape(-1, 3)
        band_vox = smp.vox.reshape(r, s)[:, b0:].reshape(-1)
        need = color_samples(ev.sdf[:, b0:], self.field.cfg.beta, ev.inside[:, b0:], self.cfg.color_weight_floor)
        band_in = torch.nonzero(need.reshape(-1)).squeeze(1)  # colour only where it weighs
        band_col = self.field.color(band_pts[band_in], band_vox[band_in], residual=1.0).to(torch.float32)
        col = torch.zeros(len(band_pts), 3, device=dev).index_copy(0, band_in, band_col).reshape(r, s - b0, 3)
        out = composite(ev.sdf[:, b0:], smp.t[:, b0:], col, self.field.cfg.beta, ev.inside[:, b0:], color_mask=need)
        sdf_mask, carved = ev.inside, torch.zeros((), device=dev)
        if self.votes is not None:
            behind = ev.inside & (smp.t > rays.depth[:, None])
            free = self.votes.seen_free_tensor(self.votes.on_device(dev), smp.vox, smp.frac).reshape(r, s) & behind
            sdf_mask = ev.inside & ~free
            carved = free.sum() / behind.sum().clamp(min=1)
        return Rendered(out.color, out.depth, out.hit, sdf_mask, carved)

    def losses(self, x: StepInputs) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The weighted sum of ``LOSS_TERMS`` and each term's value (0 for a term with nothing to fit)."""
        w = self.cfg.weights
        loss, terms = None, {}
        for name, term in LOSS_TERMS:
            value = term(self.field, self.voxels, x)
            terms[name] = value if value is not None else torch.zeros((), device=x.field_eval.sdf.device)
            if value is not None:
                loss = getattr(w, name) * value if loss is None else loss + getattr(w, name) * value
        return loss, terms

    def apply(self, loss: torch.Tensor, rays: RayBatch, priors_used: torch.Tensor,
              commit: Callable[[], contextlib.AbstractContextManager]) -> None:
        """Backward, then inside ``commit``: Adam on the MLPs, lazy Adam on the priors and the
        touched hash-table rows, and the step's rays counted in the voxels their measured surface
        points fall in (:meth:`VoxelMap.count_trained`)."""
        measured = rays.depth > 0
        ends = self.voxels.locate_points(rays.origins + rays.dirs * rays.depth[:, None])[0]
        ends = torch.where(measured, ends, -1)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        with commit():
            self.optimizer.step()
            if self.prior_opt is not None:
                self.prior_opt.step(self.voxels, priors_used)
            self.field.sparse_step(self.cfg.lr)
            self.voxels.count_trained(ends)
