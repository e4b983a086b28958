"""Render colour + depth from the map at any pose and intrinsics (novel views, queries, evaluation).

Two stages per ray, both restricted to allocated leaf voxels:
1. coarse: march the ray through the voxel grid at ``coarse_step`` evaluating only the octree
   SDF priors (trilinear, cheap), and take the first + to - crossing (linear interpolation); where
   the ray enters the allocated region the entry point is found by bisection and its prior used,
   so a surface just inside the region's face is not stepped over (an entry prior just below zero,
   within ``exit_tolerance``, is a hit at the face); likewise where it leaves the region with the
   prior still positive (the exit point's prior decides, and a prior just short of zero is
   extrapolated to its crossing); a fused numba kernel over a
   hash table of the voxel ids (memory proportional to the voxels, wherever they are), parallel
   over rays;
   then, in front of that crossing, the full SDF (prior + residual) at ``field_step`` through the
   allocated voxels, up to and overlapping the fine window: its first crossing there wins, since
   the residual carries surfaces the priors' 10 cm lattice cannot hold (thin edges, legs);
2. fine: ``fine_samples`` samples ``fine_step`` apart centred on that crossing, full SDF (prior
   + residual): the window's first + to - crossing (linear interpolation) is the depth; a window
   without one renders at the paper's volume rendering weights sigma(s/beta) sigma(-s/beta) where
   they sum to ``min_weight``. (Weights alone miss a crossing between two samples of a field
   steeper than the unit slope: the kernel is 2.5 mm wide, the samples 1 cm apart.) Colour is the
   colour field at the rendered surface point. With the paper's kernel
   (2.5 mm wide) the weights sit on the zero crossing, so one colour evaluation per ray stands
   in for the weighted sum at a ninth of the cost.
A window without a surface sends its ray on: the full SDF is searched from the window's last
sample to the next prior crossing's window, and the ray renders at the first crossing of the two.
Rays still empty search the full SDF from ``near`` (``fallback_step``), where a ray that leaves
the allocated voxels with the field falling and within ``exit_tolerance`` of zero also counts as
reaching the surface; rays with none of these render as depth 0, colour black.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from h3edge.geometry.camera import Intrinsics, pixel_rays_world
from h3edge.mapping.volume_rendering import composite


@dataclass(frozen=True)
class RenderConfig:
    near: float = 0.05
    """the z-depth range along a ray where the map is sampled: by the renderer, and from ``near`` by the trainer's
    free-space samples m"""
    far: float = 10.0
    """m, the sensor's max depth (authors: 10 m)"""
    coarse_step: float = 0.02
    """m, prior march step along z"""
    exit_tolerance: float = 0.1
    """|prior| (truncation units) within which a ray leaving (entering) the allocated region counts as reaching the
    surface just behind (in front of) its face: voxels end where depth points end measured: 0.1 best on the sim
    scene, near-best on Replica (0.5 lets grazing rays hit)"""
    fine_samples: int = 9
    """samples of a fine window around a prior crossing, fine_step apart (9: +-4 cm)"""
    fine_step: float = 0.01
    """m, the paper's 1 cm sample spacing"""
    chunk: int = 65536
    """rays per fine-stage batch"""
    retries: int = 2
    """marches past a crossing that got no rendering weight"""
    min_weight: float = 0.05
    """a fine window renders only where its weights sum to this: the field comes within ~7 mm of a zero crossing (alpha
    = sigma(s/beta) sigma(-s/beta) is 0.25 at s = 0 and 0.045 at s/beta = 3). Windows with no surface in them (a
    prior crossing the residual moved away) march on instead of rendering at their weighted mean depth."""
    window_crossing: bool = True
    """a fine window's first + to - crossing of the full SDF is a surface, rendered at the crossing, whatever the
    weights (false: the weights alone decide): a field steeper than the unit slope leaves the 2.5 mm kernel between
    two 1 cm samples (Replica: 1.4 % of a view rendered through chair seats; held-out PSNR +0.74 dB and Depth L1 -15
    % with it, research/silhouettes.md)"""
    field_step: float = 0.01
    """in front of each ray's prior crossing the full SDF (prior + residual) is searched at this step through the
    allocated voxels: a surface the residual carries where the prior has no crossing (a table's edge in a voxel whose
    priors all read free) is rendered instead of stepped through to the floor behind it (0: prior crossings only);
    also behind a fine window that held no surface, up to the next prior crossing. The paper's 1 cm: 2 cm steps miss
    thin negative shells (sim Depth L1 0.87 vs 0.78 cm on 6 views) for 25 % less render time"""
    fallback_step: float = 0.01
    """rays the prior march leaves without a weighted surface (the residual moved it where the prior has no crossing)
    search the full SDF at this step through the allocated voxels they cross, then render the window at its first
    crossing (0: off, such rays render empty)"""
    search_chunk: int = 4096
    """rays per full-SDF search batch, times their allocated samples (median 15 in front of a surface on the real map; a
    fallback ray through a room ~100-300): ~70 bytes a sample of scratch"""
    max_pixels: int = 1280 * 960
    """render requests (queries, offline) above this are refused"""
    free_floor: float = 0.0
    """truncation units: the least SDF a render or mesh reads in cells the frames voted free
    (:mod:`h3edge.mapping.cell_votes`), far enough from 0 that a fine window at it carries no rendering weight
    (:func:`floor_window_weight`); paper 0 (the field as trained); D53-4, D53-7"""
    base_surface: float = 0.0
    """m: renders take the fused colour base's zero crossing (:mod:`h3edge.mapping.color_base`) where the field's lies
    farther than this from it or is missing; paper 0 (the field alone); D53-4"""
    base_trained_rays: float = float("inf")
    """training rays: the base's surface is read only in voxels where fewer training rays than this have ended; paper:
    no base (inf: every voxel); D53-5"""
    checked_residual: bool = False
    """renders apply to the colour field's residual over the colour base the gain (0-1) that the frames no training
    step fits confirm (:mod:`h3edge.mapping.residual_check`: pixels of every third frame that is not a keyframe, kept
    before the base fuses it and scored every 8 steps; false: the residual as trained); paper: no base (false);
    D53-14"""


def _march_kernel():
    from h3edge.mapping import _march_kernels as k

    return k.march, k.locate_prior


def _samples_kernel():
    from h3edge.mapping import _march_kernels as k

    return k.allocated_samples


def prior_crossings(origin: np.ndarray, dirs: np.ndarray, lookup: PriorLookup, cfg: RenderConfig,
                    near: np.ndarray | None = None) -> np.ndarray:
    """Ray parameter (= z-depth for camera-z-normalised ``dirs``) of each ray's first + to -
    crossing of the prior SDF inside allocated voxels (those of ``lookup``), searched from ``near``
    (per ray; default ``cfg.near``); -1 where there is none."""
    out = np.empty(len(dirs), np.float64)
    if len(lookup.vv) == 0:
        out[:] = -1
        return out
    nears = np.full(len(dirs), cfg.near) if near is None else np.ascontiguousarray(near, np.float64)
    tab = lookup.table
    return _march_kernel()[0](np.asarray(origin, np.float64), np.ascontiguousarray(dirs, np.float64), nears,
                              cfg.far, cfg.coarse_step, tab.hkeys, tab.hids, tab.box_lo, tab.box_hi,
                              lookup.vs, lookup.vv, lookup.priors, cfg.exit_tolerance, out)


class PriorLookup:
    """No-grad prior SDF (truncation units) and voxel ids at points through the voxel hash table:
    constant time per point, one fused parallel pass, the same answer as :meth:`VoxelMap.locate`
    + :meth:`VoxelMap.coarse_sdf` (points on a face of the allocated region included), which
    training uses with its searchsorted lookups."""

    def __init__(self, voxels, eps: float = 1e-5):
        self.eps = eps
        self.table = voxels.table()
        self.vs = voxels.cfg.voxel_size
        self.vv = voxels.voxel_vertices
        self.priors = voxels.priors.detach().cpu().numpy().astype(np.float64)
        self.prior_set, self.seen_behind = voxels.prior_set, voxels.seen_behind
        self.trained = voxels.trained
        self.observed_behind = voxels.cfg.observed_behind
        self._observed: tuple[np.ndarray, ...] | None = None  # per-vertex values support interpolates

    def __call__(self, pts: np.ndarray, values: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(trilinear prior, voxel id) at ``pts``; ``values``: interpolate these per-vertex values
        instead of the priors."""
        sdf = np.empty(len(pts), np.float64)
        vox = np.empty(len(pts), np.int64)
        if len(self.vv):
            _march_kernel()[1](
                np.ascontiguousarray(pts, np.float64),
                self.table.hkeys,
                self.table.hids,
                self.vs,
                self.vv,
                self.priors if values is None else values,
                self.eps,
                sdf,
                vox,
            )
        else:
            sdf[:], vox[:] = 0, -1
        return sdf, vox

    def support(self, pts: np.ndarray) -> np.ndarray:
        """Share of the trilinear weight at ``pts`` that falls on vertices whose prior was set from
        a depth observation: where the map has evidence. 0 outside the allocated voxels, and where
        every frame saw the point more than ``observed_behind`` behind its measured surface (the
        vertices' ``seen_behind`` interpolated over those some frame saw; none seen: 0)."""
        if self._observed is None:
            seen = self.seen_behind < np.inf  # -inf: a state from before the record, seen
            # seen farther in front than a voxel: as a voxel (free space), so the interpolation stays local
            behind_m = np.maximum(np.where(seen, self.seen_behind, 0.0), -self.vs)
            self._observed = (self.prior_set.astype(np.float64), seen.astype(np.float64), behind_m.astype(np.float64))
        set_share, vox = self(pts, self._observed[0])
        support = np.where(vox >= 0, set_share, 0.0)
        if np.isfinite(self.observed_behind):
            seen_share, _ = self(pts, self._observed[1])
            behind, _ = self(pts, self._observed[2])
            with np.errstate(invalid="ignore", divide="ignore"):
                deep = (seen_share <= 0) | (behind > self.observed_behind * seen_share)
            support[deep] = 0.0
        return support


FloorFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
_FREE_DISTANCE = 1e-3  # m: the base's signed distance in cells the floor lifts (seen free: no crossing there)


def _base_distance(base, pts: np.ndarray, vox: np.ndarray, lookup: PriorLookup, lift: np.ndarray | None,
                   trained_rays: float) -> tuple[np.ndarray, np.ndarray]:
    """The base's signed distance at ``pts`` (in voxels ``vox``) and where a render reads it: where
    the base knows one inside an allocated voxel that has trained on fewer than ``trained_rays``
    rays. Raised to just above zero where the floor ``lift`` applies (the frames saw through: no
    surface there)."""
    dist, known = base.sample_distance(pts)
    known &= (vox >= 0) & (lookup.trained[np.maximum(vox, 0)] < trained_rays)
    if lift is not None:
        dist = np.where(lift > 0, np.maximum(dist, _FREE_DISTANCE), dist)
    return dist, known


def floor_window_weight(cfg: RenderConfig, beta: float) -> float:
    """The rendering weight of a fine window whose every sample sits at ``cfg.free_floor``
    (``beta``: the field's kernel width, truncation units). At or above ``cfg.min_weight`` a run of
    seen-free cells renders as a surface: at 0.1 with the paper's beta each sample weighs 0.105 and
    a window 0.94, which drew phantom surfaces wherever the camera had seen through (D53-7)."""
    a = 1.0 / (1.0 + np.exp(-cfg.free_floor / beta))
    return float(cfg.fine_samples * a * (1.0 - a))


def free_floor_fn(votes, voxels, floor: float) -> FloorFn | None:
    """``f(points (N, 3) m, voxel ids (N,)) -> (N,)`` lower bounds of the SDF (truncation units):
    ``floor`` in the cells ``votes`` (a :class:`~h3edge.mapping.cell_votes.CellVotes`) hold seen
    free, -inf elsewhere; None when there are no votes or ``floor`` is 0."""
    if votes is None or not votes.enabled or floor <= 0:
        return None

    def floor_at(pts: np.ndarray, vox: np.ndarray) -> np.ndarray:
        return np.where(votes.seen_free_points(voxels, pts, vox), floor, -np.inf)

    return floor_at


@torch.no_grad()
def render_rays(neural_field, voxels, origin: np.ndarray, dirs: np.ndarray, cfg: RenderConfig,
                floor: FloorFn | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Colour (N, 3) float in [0, 1] and z-depth (N,) for rays ``origin + t * dirs``. A ray renders
    at the full SDF's first crossing in front of its prior crossing where the search
    (``cfg.field_step``) finds one, else at the prior crossing. A ray whose window
    gets no rendering weight (the residual moved the surface away from it) marches
    on past that window, up to ``cfg.retries`` times: to the full SDF's first crossing behind the
    window, else to the next prior crossing. The searches and windows leave no gap along a ray.
    ``floor``: lower bounds of the full SDF (:func:`free_floor_fn`), applied wherever it is read."""
    dev = neural_field.geo_grid.table.device
    n = len(dirs)
    base = neural_field.color_base if cfg.base_surface > 0 else None
    base = base if base is not None and len(base) else None  # the fused surface the searches and windows read
    snap = ({"base": base, "base_surface": cfg.base_surface, "base_trained_rays": cfg.base_trained_rays}
            if base is not None else {})
    depth = np.zeros(n, np.float32)
    color = np.zeros((n, 3), np.float32)
    lookup = PriorLookup(voxels)  # one voxel table and prior copy for every stage of this render
    t_hit = prior_crossings(origin, dirs, lookup, cfg)
    todo = np.flatnonzero(t_hit > 0)
    if cfg.field_step > 0 and len(todo):
        # the field's own first crossing in front of the prior's (the window covers the prior's)
        t_field = field_crossings(neural_field, lookup, origin, dirs[todo], np.full(len(todo), cfg.near),
                                  _search_end(t_hit[todo], cfg), cfg.field_step, dev, cfg.search_chunk, floor=floor,
                                  **snap)
        t_hit[todo] = np.where(t_field > 0, t_field, t_hit[todo])
    for attempt in range(cfg.retries + 1):
        missed = _fine_stage(neural_field, voxels, lookup, origin, dirs, t_hit, todo, cfg, dev, depth, color, floor,
                             base)
        if attempt == cfg.retries or len(missed) == 0:
            break
        t_from = t_hit[missed] + _window_reach(cfg)  # the empty window's last sample
        t_new = prior_crossings(origin, dirs[missed], lookup, cfg, near=t_from)
        if cfg.field_step > 0:
            # the field's first crossing between the empty window and the next prior crossing's
            t_field = field_crossings(neural_field, lookup, origin, dirs[missed], t_from,
                                      np.where(t_new > 0, _search_end(t_new, cfg), cfg.far), cfg.field_step, dev,
                                      cfg.search_chunk, floor=floor, **snap)
            t_new = np.where(t_field > 0, t_field, t_new)
        t_hit[missed] = t_new
        todo = missed[t_new > 0]
    if cfg.fallback_step > 0:
        # every ray still empty: no prior crossing at all, or none that carried weight
        empty = np.flatnonzero(depth == 0)
        if len(empty):
            # a surface the residual carries just past the allocated region's face counts, as in the
            # prior march (studio: black specks along concave corners, where the field leaves the
            # voxels at +0.04-0.08 with the wall a few millimetres behind the face)
            t_hit[empty] = field_crossings(neural_field, lookup, origin, dirs[empty], np.full(len(empty), cfg.near),
                                           np.full(len(empty), cfg.far), cfg.fallback_step, dev, cfg.search_chunk,
                                           cfg.exit_tolerance, floor, **snap)
            found = empty[t_hit[empty] > 0]
            if len(found):
                missed = _fine_stage(neural_field, voxels, lookup, origin, dirs, t_hit, found, cfg, dev, depth, color,
                                     floor, base)
                if len(missed):  # a window short of weight (mostly an exit's): the found point is the surface
                    _render_at(neural_field, lookup, origin, dirs, t_hit, missed, cfg.fallback_step, dev, depth, color,
                               residual_gain(cfg))
    return color, depth


def residual_gain(cfg: RenderConfig) -> float | None:
    """The ``residual`` a render passes to :meth:`Field.color`: None (the field's checked gain) where
    ``cfg.checked_residual``, else 1 (the residual as trained)."""
    return None if cfg.checked_residual else 1.0


def _render_at(neural_field, lookup, origin, dirs, t_hit, rays, back: float, dev, depth, color,
               residual: float | None = 1.0) -> None:
    """Render ``rays`` at ``t_hit`` itself: that depth, and the colour field there, read in the voxel
    of the point (or of the point ``back`` in front of it, for a surface just past the allocated
    voxels); rays with neither point in a voxel stay empty."""
    pts = np.asarray(origin, np.float64)[None] + dirs[rays] * t_hit[rays, None]
    vox = lookup(pts)[1]
    out = vox < 0
    vox[out] = lookup(pts[out] - dirs[rays[out]] * back)[1]
    ok = vox >= 0
    if not ok.any():
        return
    col = neural_field.color(torch.from_numpy(pts[ok].astype(np.float32)).to(dev), torch.from_numpy(vox[ok]).to(dev),
                             residual)
    depth[rays[ok]] = t_hit[rays[ok]]
    color[rays[ok]] = col.float().cpu().numpy()


def _window_reach(cfg: RenderConfig) -> float:
    """Ray-parameter distance from a fine window's centre to its first (last) sample."""
    return (cfg.fine_samples // 2) * cfg.fine_step


def _search_end(t_centre: np.ndarray, cfg: RenderConfig) -> np.ndarray:
    """Where a full-SDF search in front of a fine window centred at ``t_centre`` stops: one search
    step past the window's first sample, so that every point in front of the window lies between
    two neighbouring search samples (a crossing between the search's last sample and the window's
    first one is found, not stepped over)."""
    return t_centre - _window_reach(cfg) + cfg.field_step


@torch.no_grad()
def field_crossings(neural_field, lookup: PriorLookup, origin: np.ndarray, dirs: np.ndarray, t_lo: np.ndarray,
                    t_hi: np.ndarray, step: float, dev, chunk: int = 4096, exit_tolerance: float = 0.0,
                    floor: FloorFn | None = None, base=None, base_surface: float = 0.0,
                    base_trained_rays: float = float("inf")) -> np.ndarray:
    """First + to - crossing (z-depth, -1 where none) of the full SDF (prior + residual) along each
    ray between ``t_lo`` and ``t_hi`` (per ray), sampled every ``step`` where the samples lie in
    allocated voxels (only those are evaluated); a crossing lies between two neighbouring samples.
    With ``exit_tolerance`` > 0, a ray that leaves the allocated voxels with the full SDF falling
    and within (0, exit_tolerance] reaches the surface just behind the region's face, as in the
    prior march: at its last sample plus the falling SDF's linear extrapolation to zero, at most one
    step. ``chunk`` rays are searched at a time; ``floor``: lower bounds of the SDF (:func:`free_floor_fn`).
    ``base``: a fused base (:class:`~h3edge.mapping.color_base.ColorBase`) whose first crossing
    of its signed distance is taken instead where it lies more than ``base_surface`` (m) in front
    of the field's, or the field has none, in voxels trained on fewer than ``base_trained_rays`` rays."""
    out = np.full(len(dirs), -1.0)
    if len(lookup.vv) == 0 or len(dirs) == 0:
        return out
    tab = lookup.table
    o = np.asarray(origin, np.float64)
    kernel = _samples_kernel()
    for s in range(0, len(dirs), chunk):
        d = np.ascontiguousarray(dirs[s:s + chunk], np.float64)
        lo = np.ascontiguousarray(t_lo[s:s + chunk], np.float64)
        hi = np.ascontiguousarray(t_hi[s:s + chunk], np.float64)
        offsets = np.zeros(len(d) + 1, np.int64)
        empty = np.zeros(0, np.float64)
        kernel(o, d, lo, hi, step, tab.hkeys, tab.hids, tab.box_lo, tab.box_hi, lookup.vs, lookup.vv, lookup.priors,
               offsets, empty, empty, False)
        np.cumsum(offsets, out=offsets)
        if offsets[-1] == 0:
            continue
        ts, prior = np.empty(offsets[-1]), np.empty(offsets[-1])
        kernel(o, d, lo, hi, step, tab.hkeys, tab.hids, tab.box_lo, tab.box_hi, lookup.vs, lookup.vv, lookup.priors,
               offsets, ts, prior, True)
        ray = np.repeat(np.arange(len(d)), np.diff(offsets))
        pts = o[None, :] + d[ray] * ts[:, None]
        sdf = prior.copy()
        for a in range(0, len(pts), 1 << 18):  # bounded activations
            p = torch.from_numpy(pts[a:a + (1 << 18)].astype(np.float32)).to(dev)
            sdf[a:a + len(p)] += neural_field.sdf_mlp(neural_field.geo_grid(p))[:, 0].float().cpu().numpy()
        vox = lookup(pts)[1] if floor is not None or base is not None else None
        lift = floor(pts, vox) if floor is not None else None
        if lift is not None:
            sdf = np.maximum(sdf, lift)
        pair = (ray[1:] == ray[:-1]) & (np.abs(ts[1:] - ts[:-1] - step) < 0.5 * step)  # neighbours
        cross = np.flatnonzero(pair & (sdf[:-1] > 0) & (sdf[1:] <= 0))
        t_event = ts[cross] + (ts[cross + 1] - ts[cross]) * sdf[cross] / (sdf[cross] - sdf[cross + 1])
        if exit_tolerance > 0:
            # the last sample of a run of neighbours, the field falling into it and not yet at zero
            j = np.flatnonzero(~np.append(pair, False) & np.insert(pair, 0, False)
                               & (sdf > 0) & (sdf <= exit_tolerance))
            j = j[sdf[j - 1] > sdf[j]]
            reach = np.minimum(step, step * sdf[j] / (sdf[j - 1] - sdf[j]))
            order = np.argsort(np.concatenate([cross, j]), kind="stable")  # along each ray
            cross = np.concatenate([cross, j])[order]
            t_event = np.concatenate([t_event, ts[j] + reach])[order]
        rays, first = np.unique(ray[cross], return_index=True)
        out[s + rays] = t_event[first]
        if base is not None:  # the base's first crossing, where it lies in front of the field's
            dist, known = _base_distance(base, pts, vox, lookup, lift, base_trained_rays)
            bc = np.flatnonzero(pair & known[:-1] & known[1:] & (dist[:-1] > 0) & (dist[1:] <= 0))
            if len(bc):
                t_b = ts[bc] + (ts[bc + 1] - ts[bc]) * dist[bc] / (dist[bc] - dist[bc + 1])
                rays, first = np.unique(ray[bc], return_index=True)
                t_f = out[s + rays]
                ahead = (t_f < 0) | (t_b[first] < t_f - base_surface)
                out[s + rays[ahead]] = t_b[first][ahead]
    return out


def window_crossing(sdf: torch.Tensor, t: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per ray of (R, S) samples: the ray parameter of the first + to - sign change of ``sdf``
    between two neighbouring valid samples (linear interpolation), and whether there is one."""
    pair = mask[:, :-1] & mask[:, 1:] & (sdf[:, :-1] > 0) & (sdf[:, 1:] <= 0)
    found = pair.any(-1)
    j = torch.argmax(pair.float(), -1, keepdim=True)  # the first True (argmax returns the first maximum)
    s0, s1 = sdf.gather(1, j)[:, 0], sdf.gather(1, j + 1)[:, 0]
    t0, t1 = t.gather(1, j)[:, 0], t.gather(1, j + 1)[:, 0]
    return t0 + (t1 - t0) * s0 / torch.where(found, s0 - s1, torch.ones_like(s0)), found


def _fine_stage(neural_field, voxels, lookup, origin, dirs, t_hit, rays, cfg, dev, depth, color,
                floor: FloorFn | None = None, base=None) -> np.ndarray:
    """Render ``rays`` around their crossings into ``depth`` / ``color``; returns the rays whose window
    holds no surface (no zero crossing, too little weight). ``floor``: lower bounds of the SDF;
    ``base``: the fused base whose crossing a window renders at (``cfg.base_surface``)."""
    offs = torch.arange(cfg.fine_samples, device=dev, dtype=torch.float32) - (cfg.fine_samples - 1) / 2
    o = torch.as_tensor(np.asarray(origin, np.float32), device=dev)
    missed = []
    for s in range(0, len(rays), cfg.chunk):
        idx = rays[s:s + cfg.chunk]
        d = torch.from_numpy(dirs[idx].astype(np.float32)).to(dev)
        t = torch.from_numpy(t_hit[idx].astype(np.float32)).to(dev)[:, None] + cfg.fine_step * offs[None]
        pts = (o + d[:, None, :] * t[..., None]).reshape(-1, 3)
        pts_np = pts.cpu().numpy()
        prior, vox = lookup(pts_np)
        sdf, inside = neural_field.sdf(pts, voxels, prior=(torch.from_numpy(prior.astype(np.float32)).to(dev),
                                                     torch.from_numpy(vox >= 0).to(dev)))
        lift = floor(pts_np, vox) if floor is not None else None
        if lift is not None:
            sdf = torch.maximum(sdf, torch.from_numpy(lift.astype(np.float32)).to(dev))
        sdf, inside = sdf.reshape(t.shape), inside.reshape(t.shape)
        out = composite(sdf, t, None, neural_field.cfg.beta, inside, cfg.min_weight)
        # a window the field crosses zero in holds a surface whatever its weights, and the surface is
        # at the crossing: where the field is steeper than 1 (truncation units per truncation) the
        # 2.5 mm kernel can fall between two 1 cm samples and leave the weights near 0
        t_zero, crossed = window_crossing(sdf, t, inside)
        crossed &= cfg.window_crossing
        depth_r = torch.where(crossed, t_zero, out.depth)
        hit = out.hit | crossed
        if base is not None:
            dist, known = _base_distance(base, pts_np, vox, lookup, lift, cfg.base_trained_rays)
            t_base, on_base = window_crossing(torch.from_numpy(dist.reshape(t.shape)).to(t), t,
                                              torch.from_numpy(known.reshape(t.shape)).to(dev))
            snap = on_base & (~hit | ((t_base - depth_r).abs() > cfg.base_surface))
            depth_r = torch.where(snap, t_base, depth_r)
            hit = hit | on_base
        surf = o + d[hit] * depth_r[hit, None]
        col = (neural_field.color(surf, torch.from_numpy(lookup(surf.cpu().numpy())[1]).to(dev), residual_gain(cfg))
               if len(surf) else surf)
        hit_np = hit.cpu().numpy()
        depth[idx[hit_np]] = depth_r[hit].cpu().numpy()
        color[idx[hit_np]] = col.float().cpu().numpy()
        missed.append(idx[~hit_np])
    return np.concatenate(missed) if missed else np.zeros(0, np.int64)


class MapRenderer:
    """:class:`~h3edge.eval.evaluate.ViewRenderer` over a field and its voxel map."""

    def __init__(self, neural_field, voxels, cfg: RenderConfig = RenderConfig(), votes=None):
        self.field, self.voxels, self.cfg = neural_field, voxels, cfg
        self.floor = free_floor_fn(votes, voxels, cfg.free_floor)  # votes: the map's CellVotes, if any

    def render(self, intr: Intrinsics, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Colour uint8 (H, W, 3) and z-depth float32 (H, W) metres, 0 where nothing is mapped."""
        if intr.width * intr.height > self.cfg.max_pixels:
            raise ValueError(f"render of {intr.width}x{intr.height} exceeds the cap of {self.cfg.max_pixels} pixels")
        o, d = pixel_rays_world(intr, np.asarray(c2w, np.float64))
        color, depth = render_rays(self.field, self.voxels, o, d.reshape(-1, 3), self.cfg, self.floor)
        rgb = np.clip(color * 255 + 0.5, 0, 255).astype(np.uint8).reshape(intr.height, intr.width, 3)
        return rgb, depth.reshape(intr.height, intr.width)
