"""Diagnosis of inflated silhouettes: the renderer against the field, along the rays that go wrong.

    python -m benchmarks.silhouettes [--sequence ../shared/data/7scenes_redkitchen_dev]
        [--profile x86-cpu] [--frames N] [--out research/silhouettes]

Maps the sequence (or reuses ``--work``'s checkpoint of the same settings), then on its held-out
views, for every valid pixel the render puts more than 5 cm in front of the sensor depth ("red"):
- the first + to - zero crossing of the full SDF (prior + residual) by dense 5 mm sampling through
  the allocated voxels, and of the prior alone: does the *field* carry the phantom surface, or
  only the renderer's march?
- whether the rendered point lies in a voxel whose 8 priors are all unset, or some of them;
- how far the pixel lies from the nearest depth discontinuity of the held-out sensor depth (a rim
  on a silhouette, or space away from every edge);
- for every valid pixel rendered > 5 cm behind the sensor depth or not at all ("blue"): whether the
  full SDF's first crossing lies at the sensor depth (the renderer missed it) and the prior's behind;
and the map's prior coverage (vertices with a prior, voxels with all / any corners unset). One ray
that grazes an object edge is plotted: prior, residual, full SDF and the sensor depth along it.
Writes OUT.json, OUT.md and OUT_ray.png (needs matplotlib: the ``bench`` extra).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from pathlib import Path

import cv2
import numpy as np
import torch

from h3edge.config import apply_overrides, load_profile
from h3edge.geometry.camera import pixel_rays_world
from h3edge.geometry.depth_edges import depth_discontinuities
from h3edge.io import open_sequence
from h3edge.mapping.engine import MapEngine
from h3edge.mapping.raymarch import PriorLookup, window_crossing

log = logging.getLogger(__name__)
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "7scenes_redkitchen_dev"


def prior_coverage(voxels) -> dict:
    """Share of vertices with a prior, of voxels with all 8 / at least one corner unset."""
    if len(voxels) == 0:
        return {}
    unset = ~voxels.prior_set[voxels.voxel_vertices]
    return {"vertices_set": float(voxels.prior_set.mean()), "voxels_all_unset": float(unset.all(1).mean()),
            "voxels_any_unset": float(unset.any(1).mean())}


def first_crossing(values: np.ndarray, ts: np.ndarray) -> np.ndarray:
    """Per row of ``values`` (R, S) sampled at the evenly spaced ``ts`` (NaN where undefined), the
    first + to - crossing by linear interpolation between the two samples around it; -1 where none
    (the renderer's :func:`~h3edge.mapping.raymarch.window_crossing`)."""
    valid = np.isfinite(values)
    t, found = window_crossing(torch.from_numpy(np.where(valid, values, 0.0)),
                               torch.from_numpy(np.broadcast_to(np.asarray(ts, np.float64), values.shape).copy()),
                               torch.from_numpy(valid))
    return np.where(found.numpy(), t.numpy(), -1.0)


@torch.no_grad()
def dense_crossings(neural_field, voxels, origin: np.ndarray, dirs: np.ndarray, near: float, far: float,
                    step: float = 0.005, chunk: int = 2048) -> tuple[np.ndarray, np.ndarray]:
    """First + to - crossing (z-depth, -1 none) of the full SDF and of the prior alone along each
    ray, sampling every ``step`` from ``near`` to ``far`` inside allocated voxels."""
    lookup = PriorLookup(voxels)
    ts = np.arange(near, far, step, dtype=np.float64)
    full_t = np.full(len(dirs), -1.0)
    prior_t = np.full(len(dirs), -1.0)
    dev = neural_field.geo_grid.table.device
    for s in range(0, len(dirs), chunk):
        d = dirs[s:s + chunk].astype(np.float64)
        pts = (origin[None, None, :] + d[:, None, :] * ts[None, :, None]).reshape(-1, 3)
        prior, vox = lookup(pts)
        inside = vox >= 0
        prior = np.where(inside, prior, np.nan)
        full = prior.copy()
        if inside.any():
            p = torch.from_numpy(pts[inside].astype(np.float32)).to(dev)
            full[inside] += neural_field.sdf_mlp(neural_field.geo_grid(p))[:, 0].cpu().numpy()
        full_t[s:s + len(d)] = first_crossing(full.reshape(len(d), len(ts)), ts)
        prior_t[s:s + len(d)] = first_crossing(prior.reshape(len(d), len(ts)), ts)
    return full_t, prior_t


def diagnose_view(m: MapEngine, f, threshold: float = 0.05) -> dict:
    from h3edge.eval.metrics import depth_error_shares, depth_l1, psnr, ssim

    rgb, depth = m.render(f.intrinsics, f.pose)
    gt = f.depth
    red = (gt > 0) & (depth > 0) & (depth < gt - threshold)
    o, d = pixel_rays_world(f.intrinsics, np.asarray(f.pose, np.float64))
    d = d.reshape(-1, 3)
    idx = np.flatnonzero(red.reshape(-1))
    sh = depth_error_shares(depth, gt, threshold)
    out = {"valid": int((gt > 0).sum()), "red": int(len(idx)), "behind_share": sh["behind_share"],
           "depth_l1_cm": 100 * depth_l1(depth, gt)[0], "median_cm": 100 * sh["median_abs_m"],
           "psnr_db": psnr(rgb, f.color), "ssim": ssim(rgb, f.color)}
    # "blue": rendered > threshold behind the sensor depth, or not at all; is the surface in the field?
    blue = np.flatnonzero(((gt > 0) & ((depth == 0) | (depth > gt + threshold))).reshape(-1))
    if len(blue):
        g = gt.reshape(-1)[blue]
        full_t, prior_t = dense_crossings(m.field, m.voxels, o, d[blue], m.settings.render.near,
                                          float(np.maximum(depth.reshape(-1)[blue], g).max()) + 0.2)
        out.update({"behind_field_crossing_at_sensor": float(np.mean((full_t > 0) & (np.abs(full_t - g) <= threshold))),
                    "behind_prior_crossing_behind": float(np.mean((prior_t > 0) & (prior_t > g + threshold)))})
    if len(idx) == 0:
        return out
    full_t, prior_t = dense_crossings(m.field, m.voxels, o, d[idx], m.settings.render.near,
                                      float(gt.reshape(-1)[idx].max()) + 0.1)
    g = gt.reshape(-1)[idx]
    pts = o[None] + d[idx] * depth.reshape(-1)[idx, None]
    _, vox = PriorLookup(m.voxels)(pts)
    unset = ~m.voxels.prior_set[m.voxels.voxel_vertices[np.maximum(vox, 0)]]
    # where they are: pixels from the nearest depth discontinuity (the mapper's 3x3 edge jump, 5 %
    # for the benchmark cameras) or hole of the sensor's view
    edges = depth_discontinuities(gt, m.gradient_jump(f.intrinsics))
    px = cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2, 3).reshape(-1)[idx]
    out.update({
        "at_most_2px_from_a_sensor_edge_or_hole": float(np.mean(px <= 2)),
        "3_to_8px_from_a_sensor_edge_or_hole": float(np.mean((px > 2) & (px <= 8))),
        "over_8px_from_a_sensor_edge_or_hole": float(np.mean(px > 8)),
    })
    out.update({
        "field_crossing_in_front": float(np.mean((full_t > 0) & (full_t < g - threshold))),
        "prior_crossing_in_front": float(np.mean((prior_t > 0) & (prior_t < g - threshold))),
        "render_vs_field_first_crossing_median_cm": float(100 * np.median(np.abs(depth.reshape(-1)[idx][full_t > 0]
                                                                                  - full_t[full_t > 0])))
        if (full_t > 0).any() else None,
        "point_in_all_unset_voxel": float(np.mean(unset.all(1) & (vox >= 0))),
        "point_in_any_unset_voxel": float(np.mean(unset.any(1) & (vox >= 0))),
    })
    return out


def plot_ray(m: MapEngine, f, path: Path, threshold: float = 0.05) -> dict | None:
    """Prior, residual, full SDF along the red pixel nearest an object edge (largest depth jump)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    _, depth = m.render(f.intrinsics, f.pose)
    gt = f.depth
    red = (gt > 0) & (depth > 0) & (depth < gt - threshold)
    if not red.any():
        return None
    err = np.where(red, gt - depth, 0)
    v, u = np.unravel_index(np.argmax(err), err.shape)
    o, d = pixel_rays_world(f.intrinsics, np.asarray(f.pose, np.float64))
    ray = d[v, u]
    ts = np.arange(m.settings.render.near, gt[v, u] + 0.3, 0.002)
    pts = o[None] + ray[None] * ts[:, None]
    prior, vox = PriorLookup(m.voxels)(pts)
    with torch.no_grad():
        res = m.field.sdf_mlp(m.field.geo_grid(torch.from_numpy(pts.astype(np.float32)).to(m.device)))[:, 0]
    res = np.where(vox >= 0, res.cpu().numpy(), np.nan)
    prior = np.where(vox >= 0, prior, np.nan)
    unset = np.array([(~m.voxels.prior_set[m.voxels.voxel_vertices[x]]).sum() if x >= 0 else 0 for x in vox])
    tr = m.voxels.cfg.truncation
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(ts, prior * tr * 100, label="prior [cm]")
    ax.plot(ts, res * tr * 100, label="residual [cm]")
    ax.plot(ts, (prior + res) * tr * 100, label="prior + residual [cm]", lw=2)
    ax.axvline(gt[v, u], color="k", ls="--", label=f"sensor depth {gt[v, u]:.3f} m")
    ax.axvline(depth[v, u], color="r", ls=":", label=f"render {depth[v, u]:.3f} m")
    ax2 = ax.twinx()
    ax2.fill_between(ts, 0, unset, color="grey", alpha=0.2, step="mid", label="unset corners of the voxel")
    ax2.set_ylim(0, 16)
    ax2.set_ylabel("unset corners (of 8)")
    ax.axhline(0, color="grey", lw=0.5)
    ax.set_xlabel("z-depth along the ray [m]")
    ax.set_ylabel("SDF [cm]")
    ax.set_title(f"pixel ({u}, {v}): render {100 * (gt[v, u] - depth[v, u]):.1f} cm in front of the sensor")
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return {"pixel": [int(u), int(v)], "sensor_m": float(gt[v, u]), "render_m": float(depth[v, u])}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default=str(REAL))
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--frames", type=int)
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override a profile setting, e.g. voxels.prior_retry=false")
    ap.add_argument("--out", default="research/silhouettes")
    ap.add_argument("--work", default="out/silhouettes", help="map checkpoints, keyed by the mapping settings "
                                                             "(render.* overrides reuse a map)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    seq = open_sequence(args.sequence)
    settings = apply_overrides(load_profile(args.profile).map_settings(), args.set)
    n = len(seq) if args.frames is None else min(args.frames, len(seq))
    m = mapped(seq, settings, n, Path(args.work))
    held = seq.heldout if getattr(seq, "heldout", None) is not None and len(seq.heldout) else seq
    last_t = seq.timestamps[n - 1]
    cand = [j for j in range(len(held)) if held.timestamps[j] <= last_t] or list(range(len(held)))
    views = [cand[int(k)] for k in np.linspace(0, len(cand) - 1, min(args.views, len(cand))).round()]
    per_view = [diagnose_view(m, held[j]) for j in views]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    ray = plot_ray(m, held[views[len(views) // 2]], out.with_name(out.name + "_ray.png"))
    quality = ("behind_share", "depth_l1_cm", "median_cm", "psnr_db", "ssim")
    keys = sorted({k for v in per_view for k in v if k not in ("valid", "red") + quality})
    summary = {"sequence": args.sequence, "profile": args.profile, "overrides": args.set, "frames": n,
               "coverage": prior_coverage(m.voxels),
               "red_share": float(np.mean([v["red"] / max(v["valid"], 1) for v in per_view])),
               **{q: float(np.mean([v[q] for v in per_view])) for q in quality},
               **{k: float(np.nanmean([v[k] for v in per_view if v.get(k) is not None] or [np.nan])) for k in keys},
               "views": per_view, "ray": ray}
    out.with_suffix(".json").write_text(json.dumps(summary, indent=1) + "\n")
    lines = [f"### silhouettes: {Path(args.sequence).name}, {n} frames, {args.profile} {' '.join(args.set)}", "",
             "| measure | value |", "|---|---|",
             f"| vertices with a prior | {100 * summary['coverage']['vertices_set']:.1f} % |",
             f"| voxels with all 8 / any corner unset | {100 * summary['coverage']['voxels_all_unset']:.1f} % / "
             f"{100 * summary['coverage']['voxels_any_unset']:.1f} % |",
             f"| held-out valid pixels rendered > 5 cm in front / behind | {100 * summary['red_share']:.2f} % / "
             f"{100 * summary['behind_share']:.2f} % |",
             f"| held-out Depth L1 / median error [cm] | {summary['depth_l1_cm']:.2f} / {summary['median_cm']:.2f} |",
             f"| held-out PSNR [dB] / SSIM | {summary['psnr_db']:.2f} / {summary['ssim']:.3f} |"]
    lines += [f"| of the {'behind / unrendered' if k.startswith('behind_') else 'in front'} pixels: "
              f"{k.removeprefix('behind_').replace('_', ' ')} | {summary[k]:.3f} |" for k in keys]
    text = "\n".join(lines)
    out.with_suffix(".md").write_text(text + "\n")
    print(text)
    return 0


def mapped(seq, settings, n: int, work: Path) -> MapEngine:
    """``seq``'s first ``n`` frames mapped with ``settings``, from a checkpoint of the same mapping
    settings (everything but ``render``) and sequence when ``work`` has one."""
    import hashlib

    from h3edge.mapping.engine import MapEngine
    from h3edge.mapping.map_file import read_checkpoint, write_checkpoint

    key = {k: v for k, v in dataclasses.asdict(settings).items() if k != "render"}
    digest = hashlib.sha256(json.dumps([str(seq.root), n, key], sort_keys=True, default=str).encode()).hexdigest()[:16]
    ckpt = work / f"map-{digest}.h3ckpt"
    if ckpt.is_file():
        header, arrays = read_checkpoint(ckpt)
        return MapEngine.from_state_dict(settings, header["state"], arrays)
    m = MapEngine(settings)
    for i in range(n):
        m.process(seq[i])
    meta, arrays = m.state_dict()
    work.mkdir(parents=True, exist_ok=True)
    write_checkpoint(ckpt, {"state": meta}, arrays)
    return m


if __name__ == "__main__":
    raise SystemExit(main())
