"""Experiment (D53-12): where a colour base cell takes its colour, scored on the colour alone.

Fuses every frame of a dataset into a colour base (the x86-cpu settings) and into an Open3D TSDF
(1 cm, every frame) offline, then renders the held-out views with the base's colour read at the
TSDF mesh's depth (so that both have the same geometry and only the colours differ), against the
TSDF's own render. Each base is fused with ``normal_px`` 0 (a cell takes the colour of the pixel
its centre projects into, as TSDF fusion) and 2, 4 (the colour where the surface point nearest its
centre projects, D53-12), and with the world shifted by 0, 1/4 and 1/2 cell before fusing (the
read shifted with it): the scenes' walls lie on round coordinates, which put the TSDF's voxel
centres (at multiples of the voxel) on them and ours (at half-cell offsets) 5 mm off them. The
TSDF's voxel colours read with the base's reader are scored as well (the reader against the mesh).

    PYTHONPATH=. python research/scripts/base_foot_point.py --datasets loft real --out research/base_foot_point
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks import anytime
from benchmarks.mapping import open_dataset
from h3edge.config import load_profile
from h3edge.eval.evaluate import MeshRenderer
from h3edge.eval.metrics import psnr, ssim
from h3edge.eval.tsdf import TsdfFusion
from h3edge.geometry.camera import pixel_rays_world
from h3edge.mapping.color_base import ColorBase, ColorBaseConfig
from h3edge.mapping.voxels import pack


def _read(base: ColorBase, views: list, tsdf_renders: list, shift: float) -> tuple[float, float]:
    """Mean PSNR, SSIM of the base's colour at the TSDF's depth (the TSDF's colour where the base has none)."""
    p, s = [], []
    for (ct, zt), f in zip(tsdf_renders, views):
        o, d = pixel_rays_world(f.intrinsics, np.asarray(f.pose, np.float64))
        pts = o[None] + d.reshape(-1, 3) * zt.reshape(-1, 1) + shift
        rgb, known = base.sample(torch.from_numpy(pts))
        img = (np.clip(rgb.numpy(), 0, 1) * 255 + 0.5).astype(np.uint8).reshape(f.color.shape)
        ok = ((zt.reshape(-1) > 0) & known.numpy()).reshape(f.color.shape[:2])
        img = np.where(ok[..., None], img, ct)
        p.append(psnr(img, f.color))
        s.append(ssim(img, f.color))
    return float(np.mean(p)), float(np.mean(s))


def _tsdf_voxels(tsdf: TsdfFusion) -> ColorBase:
    """The TSDF's voxel colours in a base (its voxel i centred at i * voxel: read half a voxel up)."""
    vbg = tsdf._vbg
    coords, idx = vbg.voxel_coordinates_and_flattened_indices()
    idx = idx.numpy()
    weight = vbg.attribute("weight").reshape((-1,)).numpy()[idx]
    keep = weight > 0
    ijk = np.round(coords.numpy()[keep] / tsdf.voxel).astype(np.int64)
    base = ColorBase(ColorBaseConfig(cell=tsdf.voxel, max_cells=len(ijk) + 1))
    base.load_state_dict({"keys": pack(ijk),
                          "rgb": (vbg.attribute("color").reshape((-1, 3)).numpy()[idx][keep] / 255).astype(np.float32),
                          "weight": weight[keep].astype(np.float32),
                          "distance": vbg.attribute("tsdf").reshape((-1,)).numpy()[idx][keep].astype(np.float32)})
    return base


def reference(name: str, cache: Path) -> tuple[list, list, list, list, TsdfFusion]:
    """A dataset's frames, 8 held-out views, the frames' cleaned depths, the TSDF mesh's renders of
    the views (colour, depth) and the TSDF itself (1 cm, every frame fused)."""
    seq = open_dataset({"sim": "default"}.get(name, name), cache)
    frames = [seq[i] for i in range(len(seq))]
    held = getattr(seq, "heldout", None)
    held = [held[i] for i in range(len(held))] if held is not None and len(held) else frames[::10]
    views = anytime.pick_views(held, 8)
    depths = [np.where((f.depth > 0.05) & (f.depth < 10), f.depth, 0).astype(np.float32) for f in frames]
    tsdf = TsdfFusion(frames[0].intrinsics, block_count=20_000)
    for f, d in zip(frames, depths):
        tsdf.integrate(f.color, d, f.pose)
    mesh = MeshRenderer(tsdf.mesh())
    return frames, views, depths, [mesh.render(f.intrinsics, f.pose) for f in views], tsdf


def run(name: str, cache: Path) -> list[dict]:
    frames, views, depths, renders, tsdf = reference(name, cache)
    rows = [{"dataset": name, "colours": "TSDF mesh", "shift_cell": 0.0,
             "psnr_db": float(np.mean([psnr(c, f.color) for (c, _), f in zip(renders, views)])),
             "ssim": float(np.mean([ssim(c, f.color) for (c, _), f in zip(renders, views)]))}]
    p, s = _read(_tsdf_voxels(tsdf), views, renders, tsdf.voxel / 2)
    rows.append({"dataset": name, "colours": "TSDF voxels, base reader", "shift_cell": 0.0, "psnr_db": p, "ssim": s})
    cfg = load_profile("x86-cpu").map_settings().color_base
    for normal_px in (0, 2, 4):
        for shift in (0.0, 0.25, 0.5):
            base = ColorBase(dataclasses.replace(cfg, normal_px=normal_px))
            times = []
            for f, d in zip(frames, depths):
                pose = np.array(f.pose, np.float64)
                pose[:3, 3] += shift * cfg.cell
                t0 = time.perf_counter()
                base.fuse(f.color, d, f.intrinsics, pose)
                times.append(time.perf_counter() - t0)
            p, s = _read(base, views, renders, shift * cfg.cell)
            rows.append({"dataset": name, "colours": f"base, normal_px {normal_px}", "shift_cell": shift,
                         "psnr_db": p, "ssim": s, "fuse_ms_median": 1e3 * float(np.median(times[1:]))})
            print(rows[-1], flush=True)
    return rows


def write_record(lines: list[str], rows: list[dict], out: Path) -> None:
    """Print the table ``lines`` and write it to OUT.md, the ``rows`` to OUT.json."""
    table = "\n".join(lines)
    print(table)
    out.with_suffix(".md").write_text(table + "\n")
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", nargs="+", default=["loft", "real"])
    ap.add_argument("--cache", type=Path, default=Path("out/bench_mapping"))
    ap.add_argument("--out", type=Path, default=Path("research/base_foot_point"))
    args = ap.parse_args()
    rows = [r for name in args.datasets for r in run(name, args.cache)]
    lines = ["| dataset | colours | world shift [cells] | PSNR [dB] | SSIM | fuse median [ms] |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        ms = f"{r['fuse_ms_median']:.1f}" if "fuse_ms_median" in r else "—"
        lines.append(f"| {r['dataset']} | {r['colours']} | {r['shift_cell']:g} | {r['psnr_db']:.2f} | "
                     f"{r['ssim']:.4f} | {ms} |")
    write_record(lines, rows, args.out)


if __name__ == "__main__":
    main()
