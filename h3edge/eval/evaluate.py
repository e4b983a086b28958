"""Evaluation of a map against a sequence: geometry (Acc / Comp) and views (Depth L1, PSNR, SSIM).

Anything that can render colour + depth at a pose (:class:`ViewRenderer`) can be evaluated: the
mapper, a TSDF peer, or a plain mesh (:class:`MeshRenderer`). Training views (every
``view_stride``-th input frame) and held-out views (the own format's ``heldout/``, between
training views) are reported separately. Point sampling follows the authors' protocol (200k
area-uniform points per mesh, nearest neighbours); note that this protocol has a floor: two
independent samplings of the *same* mesh are about a centimetre apart on a room-sized mesh,
which ``sampling_floor_cm`` reports beside the scores.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from typing import Protocol

import numpy as np
import trimesh

from h3edge.eval.cull import cull_mesh
from h3edge.eval.metrics import (
    accuracy_completion,
    depth_error_shares,
    depth_l1,
    mesh_to_mesh,
    psnr,
    sample_surface,
    ssim,
)
from h3edge.geometry.camera import Intrinsics
from h3edge.geometry.raycast import MeshRaycaster
from h3edge.io.sequence import Sequence
from h3edge.profiling.progress import progress

log = logging.getLogger(__name__)


class ViewRenderer(Protocol):
    def render(self, intr: Intrinsics, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Colour uint8 (H, W, 3) RGB and z-depth float32 (H, W) metres, 0 where empty."""
        ...


class MeshRenderer:
    """Renders a vertex-coloured mesh (no colours -> mid grey)."""

    def __init__(self, mesh: trimesh.Trimesh):
        self.raycaster = MeshRaycaster(mesh.vertices, mesh.faces)
        vc = getattr(mesh.visual, "vertex_colors", None)
        self.colors = np.asarray(vc)[:, :3] if vc is not None and len(vc) == len(mesh.vertices) \
            else np.full((len(mesh.vertices), 3), 128, np.uint8)

    def render(self, intr: Intrinsics, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.raycaster.render_vertex_colors(intr, c2w, self.colors)


@dataclass(frozen=True)
class EvalConfig:
    n_points: int = 200_000
    """surface samples per mesh (the authors' protocol)"""
    cull_eps: float = 0.03
    """occlusion tolerance for culling, metres"""
    cull_views: int = 60
    """poses used for culling (evenly spread over the sequence)"""
    completion_threshold: float = 0.05
    """completion ratio: GT points within this of the recon, metres"""
    view_stride: int = 10
    """every n-th training frame is an evaluation view"""
    max_views: int = 50
    """cap per split"""
    depth_error_threshold: float = 0.05
    """m: a pixel this far in front of / behind the sensor depth is "off" """


def evaluate_geometry(recon: trimesh.Trimesh, gt: trimesh.Trimesh, poses: np.ndarray, intr: Intrinsics,
                      cfg: EvalConfig = EvalConfig()) -> dict[str, float]:
    """Accuracy, Completion (cm) and completion ratio of ``recon`` vs ``gt``, both culled to the views."""
    gt_c = cull_mesh(gt, poses, intr, cfg.cull_eps, cfg.cull_views)
    rc_c = cull_mesh(recon, poses, intr, cfg.cull_eps, cfg.cull_views)
    gt_pts = sample_surface(gt_c, cfg.n_points, seed=0)
    rc_pts = sample_surface(rc_c, cfg.n_points, seed=1)
    m = accuracy_completion(rc_pts, gt_pts, cfg.completion_threshold)
    floor = accuracy_completion(sample_surface(gt_c, cfg.n_points, seed=2), gt_pts, cfg.completion_threshold)
    return {"accuracy_cm": 100 * m["accuracy"], "completion_cm": 100 * m["completion"],
            "completion_ratio": m["completion_ratio"], "sampling_floor_cm": 100 * floor["accuracy"],
            "gt_area_m2": float(gt_c.area), "recon_area_m2": float(rc_c.area)}


def evaluate_views(renderer: ViewRenderer, seq: Sequence, stride: int = 1, max_views: int = 50,
                   threshold: float = 0.05) -> dict[str, float]:
    """Mean PSNR [dB], SSIM and Depth L1 [cm] of ``renderer`` over every ``stride``-th frame of ``seq``,
    and where the depth goes wrong (:func:`~h3edge.eval.metrics.depth_error_shares`, mean over views):
    the share of valid pixels more than ``threshold`` in front of / behind the sensor depth, not
    rendered, and the median |error| [cm]."""
    idx = np.arange(0, len(seq), max(1, stride))
    if len(idx) > max_views:
        idx = idx[np.linspace(0, len(idx) - 1, max_views).round().astype(int)]
    ps, ss, dl, cov, times, shares = [], [], [], [], [], []
    for i in progress(idx, len(idx), "render views", unit="view"):
        f = seq[int(i)]
        t0 = time.perf_counter()
        rgb, depth = renderer.render(f.intrinsics, f.pose)
        times.append(time.perf_counter() - t0)
        ps.append(psnr(rgb, f.color))
        ss.append(ssim(rgb, f.color))
        e, c = depth_l1(depth, f.depth)
        dl.append(e)
        cov.append(c)
        shares.append(depth_error_shares(depth, f.depth, threshold))
    mean = {k: float(np.nanmean([sh[k] for sh in shares])) for k in shares[0]} if shares else {}
    return {"views": len(idx), "psnr_db": float(np.mean(ps)), "ssim": float(np.mean(ss)),
            "depth_l1_cm": 100 * float(np.nanmean(dl)), "depth_coverage": float(np.mean(cov)),
            "front_share": mean.get("front_share"), "behind_share": mean.get("behind_share"),
            "missing_share": mean.get("missing_share"),
            "depth_median_cm": 100 * mean["median_abs_m"] if mean else None,
            "render_ms_median": 1000 * float(np.median(times))}


def evaluate_against_reference(mesh: trimesh.Trimesh, reference: trimesh.Trimesh, cfg: EvalConfig = EvalConfig()
                               ) -> dict[str, float]:
    """Mesh vs a reference mesh fused from the same frames (a TSDF), for data without a GT mesh:
    mean distance [cm] both ways and the share of each surface farther than the threshold. No
    culling either side: both meshes come from the same views."""
    d = mesh_to_mesh(mesh, reference, cfg.n_points, cfg.depth_error_threshold)
    return {"to_reference_cm": 100 * d["a_to_b_mean"], "from_reference_cm": 100 * d["b_to_a_mean"],
            "far_from_reference_share": d["a_to_b_far_share"], "reference_not_covered_share": d["b_to_a_far_share"]}


def evaluate(seq: Sequence, renderer: ViewRenderer | None = None, mesh: trimesh.Trimesh | None = None,
             cfg: EvalConfig = EvalConfig(), reference: trimesh.Trimesh | None = None) -> dict:
    """All metrics that the inputs allow: geometry needs ``mesh`` and a GT mesh, views a renderer;
    with a ``reference`` mesh (e.g. TSDF fusion of the same frames) ``mesh`` is also compared to it."""
    out: dict = {"config": asdict(cfg)}
    if mesh is not None and reference is not None:
        out["vs_reference"] = evaluate_against_reference(mesh, reference, cfg)
    if mesh is not None:
        gt_path = seq.gt_mesh_path
        if gt_path is None:
            log.warning("%s has no gt_mesh.ply: skipping accuracy / completion", seq.root)
        else:
            gt = trimesh.load(gt_path, process=False)
            out["geometry"] = evaluate_geometry(mesh, gt, seq.poses, seq.intrinsics, cfg)
    if renderer is None and mesh is not None:
        renderer = MeshRenderer(mesh)
    if renderer is not None:
        out["train_views"] = evaluate_views(renderer, seq, cfg.view_stride, cfg.max_views, cfg.depth_error_threshold)
        held = getattr(seq, "heldout", None)
        if held is not None:
            out["heldout_views"] = evaluate_views(renderer, held, 1, cfg.max_views, cfg.depth_error_threshold)
    return out


def format_table(results: dict, title: str = "metrics") -> str:
    """Markdown table of an :func:`evaluate` result."""
    rows = [f"### {title}", "", "| metric | value |", "|---|---|"]
    thr = 100 * results["config"].get("depth_error_threshold", 0.05)
    g = results.get("geometry")
    if g:
        rows += [f"| Accuracy [cm] | {g['accuracy_cm']:.3f} |", f"| Completion [cm] | {g['completion_cm']:.3f} |",
                 f"| Completion ratio (< {100 * results['config']['completion_threshold']:.0f} cm) | "
                 f"{100 * g['completion_ratio']:.1f} % |",
                 f"| Sampling floor (GT vs GT resampled) [cm] | {g['sampling_floor_cm']:.3f} |"]
    for split in ("train_views", "heldout_views"):
        v = results.get(split)
        if v:
            name = "training" if split == "train_views" else "held-out"
            rows += [f"| PSNR {name} ({v['views']} views) [dB] | {v['psnr_db']:.2f} |",
                     f"| SSIM {name} | {v['ssim']:.4f} |",
                     f"| Depth L1 {name} [cm] | {v['depth_l1_cm']:.3f} |",
                     f"| Depth median error {name} [cm] | {v['depth_median_cm']:.3f} |",
                     f"| Pixels > {thr:.0f} cm in front / behind the sensor depth, {name} | "
                     f"{100 * v['front_share']:.2f} % / {100 * v['behind_share']:.2f} % |",
                     f"| Depth coverage {name} | {100 * v['depth_coverage']:.1f} % |"]
    r = results.get("vs_reference")
    if r:
        rows += [f"| Mesh -> reference mesh, mean [cm] | {r['to_reference_cm']:.3f} |",
                 f"| Reference mesh -> mesh, mean [cm] | {r['from_reference_cm']:.3f} |",
                 f"| Mesh surface > {thr:.0f} cm from the reference | {100 * r['far_from_reference_share']:.1f} % |",
                 f"| Reference surface > {thr:.0f} cm from the mesh | {100 * r['reference_not_covered_share']:.1f} % |"]
    return "\n".join(rows)
