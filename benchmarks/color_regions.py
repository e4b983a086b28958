"""Where a map's colour error lies: per image region, against TSDF fusion and the texture field itself.

    python -m benchmarks.color_regions [--dataset replica|real|sim|studio] [--profile x86-cpu]
        [--set section.key=value ...] [--views 20] [--out research/color_regions]

Maps the dataset (as :mod:`benchmarks.mapping` opens it) and fuses the TSDF peer from the same
frames, then on the held-out views splits each method's squared colour error by region:
- ``edge band``: pixels within 5 px of the near side of a depth edge of the sensor depth (a
  neighbour within 2 px more than 5 % farther, :func:`~h3edge.geometry.depth_edges.near_side_of_edges`):
  both sides of every silhouette;
- ``depth off``: off the band, pixels whose rendered depth is more than 1 cm off the sensor's;
- ``texture``: off the band, the top 20 % of the sensor colour's Laplacian (high frequencies);
- ``rest``: the smooth remainder.
Beside them the **oracle**: the colour field read at each pixel's *sensor* surface point (its
depth back-projected), which scores the texture field without the geometry and the renderer. In
the edge band the share of pixels each method renders within 2 cm, > 2 cm in front and behind.
Prints a markdown table and writes OUT.json / OUT.md; the JSON also holds each view's PSNR,
whole and per region (``per_view``): the table's last row is a mean over views, its regions pool
the pixels of all views.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import cv2
import numpy as np

from benchmarks.tables import markdown_table
from h3edge.apps.offline import map_sequence
from h3edge.config import apply_overrides, load_profile
from h3edge.eval.evaluate import MeshRenderer
from h3edge.eval.tsdf import fuse_tsdf
from h3edge.geometry.camera import backproject
from h3edge.geometry.depth_edges import near_side_of_edges
from h3edge.mapping.engine import MapEngine

log = logging.getLogger("benchmarks.color_regions")
DEPTH_OFF = 0.01  # m: off the edge band, a render this far off the sensor depth is a geometry error
EDGE_OK = 0.02  # m: in the edge band, a render within this of the sensor depth is right


def db(mse: float) -> float:
    return float("nan") if not mse > 0 else float(-10 * np.log10(mse))


def regions(color: np.ndarray, depth: np.ndarray, rendered_depth: np.ndarray) -> dict[str, np.ndarray]:
    """Boolean (H, W) masks of the valid pixels: ``edge``, ``depth_off``, ``texture``, ``rest``."""
    valid = depth > 0
    edge = cv2.dilate(near_side_of_edges(depth, 2, 0.05).astype(np.uint8), np.ones((11, 11), np.uint8)).astype(bool)
    edge &= valid
    gray = cv2.GaussianBlur(color.astype(np.float32).mean(-1) / 255, (0, 0), 1.0)
    lap = np.abs(cv2.Laplacian(gray, cv2.CV_32F, ksize=3))
    off = valid & ~edge & (np.abs(rendered_depth - depth) > DEPTH_OFF)
    tex = valid & ~edge & ~off & (lap > np.quantile(lap[valid], 0.8)) if valid.any() else valid
    return {"edge": edge, "depth_off": off, "texture": tex, "rest": valid & ~edge & ~off & ~tex}


def view_errors(frame, h3_view, tsdf: MeshRenderer) -> dict:
    """Squared-error sums and pixel counts per region, for h3edge, TSDF and the oracle, on one view."""
    gt = frame.color.astype(np.float64) / 255
    ch, dh = h3_view.render(frame.intrinsics, frame.pose)
    ct, dt = tsdf.render(frame.intrinsics, frame.pose)
    valid = frame.depth > 0
    oracle = np.zeros_like(gt)
    if valid.any():
        pts = backproject(np.where(valid, frame.depth, 0.0), frame.intrinsics, frame.pose).reshape(-1, 3)
        oracle.reshape(-1, 3)[valid.ravel()] = h3_view.color_np(pts[valid.ravel()])
    err = {k: ((c / (255 if k != "oracle" else 1) - gt) ** 2).mean(-1)
           for k, c in (("h3edge", ch), ("tsdf", ct), ("oracle", oracle))}
    out = {"pixels": int(gt.shape[0] * gt.shape[1]), "sse_all": {k: float(e.sum()) for k, e in err.items()}}
    masks = regions(frame.color, frame.depth, dh)
    out["count"] = {r: int(m.sum()) for r, m in masks.items()}
    out["sse"] = {r: {k: float(e[m].sum()) for k, e in err.items()} for r, m in masks.items()}
    edge = masks["edge"]
    for k, d in (("h3edge", dh), ("tsdf", dt)):
        e = np.where(d > 0, d, np.inf) - frame.depth
        out[f"edge_{k}"] = {"right": int((edge & (np.abs(e) <= EDGE_OK)).sum()),
                            "front": int((edge & (e < -EDGE_OK)).sum()), "behind": int((edge & (e > EDGE_OK)).sum())}
    return out


def psnr(sse: float, n: int) -> float | None:
    """PSNR of ``n`` pixels with squared error sum ``sse``; None for no pixels."""
    return db(sse / n) if n else None


def view_psnrs(v: dict) -> dict:
    """One view's whole-image PSNR and each region's (share of the view, PSNR), h3edge and TSDF."""
    out: dict = {"psnr_db": {k: psnr(v["sse_all"][k], v["pixels"]) for k in ("h3edge", "tsdf")}}
    for r in ("edge", "depth_off", "texture", "rest"):
        n = v["count"][r]
        out[r] = {"pixel_share": n / v["pixels"], **{f"psnr_{k}": psnr(v["sse"][r][k], n) for k in ("h3edge", "tsdf")}}
    return out


def summarise(views: list[dict]) -> dict:
    """PSNR per method over all pixels and per region, each region's share of the squared error,
    and the edge band's depth classes (pooled over views)."""
    tot = lambda f: float(sum(f(v) for v in views))  # noqa: E731
    px = tot(lambda v: v["pixels"])
    res: dict = {"views": len(views), "psnr_db": {k: float(np.mean([db(v["sse_all"][k] / v["pixels"]) for v in views]))
                                                 for k in ("h3edge", "tsdf", "oracle")}}
    for r in ("edge", "depth_off", "texture", "rest"):
        n = tot(lambda v: v["count"][r])
        res[r] = {"pixel_share": n / px}
        for k in ("h3edge", "tsdf", "oracle"):
            sse = tot(lambda v: v["sse"][r][k])
            res[r][f"psnr_{k}"] = psnr(sse, n)
            res[r][f"error_share_{k}"] = sse / max(tot(lambda v: v["sse_all"][k]), 1e-12)
    res["per_view"] = [view_psnrs(v) for v in views]
    n_edge = tot(lambda v: v["count"]["edge"])
    for k in ("h3edge", "tsdf"):
        res[f"edge_depth_{k}"] = {c: tot(lambda v: v[f"edge_{k}"][c]) / max(n_edge, 1)
                                  for c in ("right", "front", "behind")}
    return res


def format_summary(title: str, s: dict) -> str:
    rows = []
    for r, label in (("edge", "depth-edge band"), ("depth_off", "off the band, depth > 1 cm off"),
                     ("texture", "off the band, high-frequency texture"), ("rest", "smooth rest")):
        rows.append({"region": label, "pixels": 100 * s[r]["pixel_share"], **{f"{m}_db": s[r][f"psnr_{m}"]
                     for m in ("h3edge", "tsdf", "oracle")}, **{f"{m}_share": 100 * s[r][f"error_share_{m}"]
                                                                 for m in ("h3edge", "tsdf")}})
    rows.append({"region": "all (mean over views)", "pixels": 100.0,
                 **{f"{m}_db": s["psnr_db"][m] for m in ("h3edge", "tsdf", "oracle")}})
    cols = [("region", lambda r: r["region"], None), ("pixels [%]", lambda r: r["pixels"], 1),
            ("h3edge PSNR", lambda r: r["h3edge_db"], 2), ("TSDF PSNR", lambda r: r["tsdf_db"], 2),
            ("oracle PSNR", lambda r: r["oracle_db"], 2),
            ("h3edge error share [%]", lambda r: r.get("h3edge_share"), 1),
            ("TSDF error share [%]", lambda r: r.get("tsdf_share"), 1)]
    eh, et = s["edge_depth_h3edge"], s["edge_depth_tsdf"]
    tail = (f"\n\nEdge band depth within 2 cm / > 2 cm in front / behind: h3edge {100 * eh['right']:.1f} / "
            f"{100 * eh['front']:.1f} / {100 * eh['behind']:.1f} %, TSDF {100 * et['right']:.1f} / "
            f"{100 * et['front']:.1f} / {100 * et['behind']:.1f} %")
    return markdown_table(title, cols, rows) + tail


def main(argv=None) -> int:
    from benchmarks.mapping import REPLICA, open_dataset, render_replica
    from h3edge.io.replica import ReplicaSequence

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default="replica", choices=["replica", "real", "sim", "studio"])
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--frames", type=int, help="map only the first N frames (smoke runs)")
    ap.add_argument("--views", type=int, default=20, help="held-out views, evenly spread")
    ap.add_argument("--replica-stride", type=int, default=5)
    ap.add_argument("--work", default="out/bench_mapping", help="the mapping benchmark's cache")
    ap.add_argument("--out", default="out/color_regions", help="writes OUT.json and OUT.md")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    work = Path(args.work)
    if args.dataset == "replica":
        seq = ReplicaSequence(render_replica(REPLICA, work / "replica_office0", args.replica_stride))
    else:
        seq = open_dataset({"sim": "default"}.get(args.dataset, args.dataset), work)
    profile = load_profile(args.profile)
    mapper = MapEngine(apply_overrides(profile.map_settings(), args.set))
    map_sequence(seq, mapper, args.frames)
    tsdf = MeshRenderer(fuse_tsdf(seq, 0.01, args.frames)[0])
    held = seq.heldout if seq.heldout is not None and len(seq.heldout) else seq
    idx = np.linspace(0, len(held) - 1, min(args.views, len(held))).round().astype(int)
    view = mapper.view()
    s = summarise([view_errors(held[int(i)], view, tsdf) for i in idx])
    s.update(dataset=args.dataset, profile=profile.name, set=args.set)
    changed = " " + " ".join(args.set) if args.set else ""
    table = format_summary(f"colour error by region, {args.dataset} ({profile.name}{changed})", s)
    print(table, flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(s, indent=1) + "\n")
    out.with_suffix(".md").write_text(table + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
