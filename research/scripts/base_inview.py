"""Experiment (D53-13): which cells a frame fuses its colour into, scored on the colour alone.

Fuses every frame of a dataset into the colour base (the x86-cpu settings) and into an Open3D TSDF
(1 cm, every frame) offline, then renders the held-out views with the base's colour read at the
TSDF mesh's depth (both have the same geometry; only the colours differ), against the TSDF's own
render, as ``research/scripts/base_foot_point.py`` does. Since D53-13 every cell of the blocks a
frame's pixels reach whose centre lies within ``color_base.trunc`` of its pixel's depth fuses that
frame once (as TSDF fusion updates every voxel within its truncation); ``trunc`` 0.015 m is about
the band the pixels' own samples reach (band 1: 1.5 cells), what a cell saw before D53-13. Before
D53-13 (the base's pass over the cells the pixels reached, at 045a4e0) the same script's reading
scored real 0.5784 and loft 0.8920 SSIM (``research/base_foot_point.md``, normal_px 4, shift 0).

    PYTHONPATH=. python research/scripts/base_inview.py --datasets loft real --out research/base_inview
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
from base_foot_point import _read, reference, write_record

from h3edge.config import load_profile
from h3edge.eval.metrics import psnr, ssim
from h3edge.mapping.color_base import ColorBase


def run(name: str, cache: Path, truncs: list[float]) -> list[dict]:
    frames, views, depths, renders, _ = reference(name, cache)
    rows = [{"dataset": name, "colours": "TSDF mesh",
             "psnr_db": float(np.mean([psnr(c, f.color) for (c, _), f in zip(renders, views)])),
             "ssim": float(np.mean([ssim(c, f.color) for (c, _), f in zip(renders, views)]))}]
    cfg = load_profile("x86-cpu").map_settings().color_base
    for trunc in truncs:
        base = ColorBase(dataclasses.replace(cfg, trunc=trunc))
        times = []
        for f, d in zip(frames, depths):
            t0 = time.perf_counter()
            base.fuse(f.color, d, f.intrinsics, f.pose)
            times.append(time.perf_counter() - t0)
        p, s = _read(base, views, renders, 0.0)
        rows.append({"dataset": name, "colours": f"base, trunc {trunc:g} m", "psnr_db": p, "ssim": s,
                     "fuse_ms_median": 1e3 * float(np.median(times[1:])), "cells": len(base),
                     "blocks": base.nblocks, "mb": base.nbytes / 2**20})
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", nargs="+", default=["loft", "real"])
    ap.add_argument("--trunc", type=float, nargs="+", default=[0.015, 0.04])
    ap.add_argument("--cache", type=Path, default=Path("out/bench_mapping"))
    ap.add_argument("--out", type=Path, default=Path("research/base_inview"))
    args = ap.parse_args()
    rows = [r for name in args.datasets for r in run(name, args.cache, args.trunc)]
    lines = ["| dataset | colours | PSNR [dB] | SSIM | fuse median [ms] | cells | blocks | MB |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        extra = (f"{r['fuse_ms_median']:.1f} | {r['cells']:,} | {r['blocks']:,} | {r['mb']:.0f}" if "cells" in r
                 else "— | — | — | —")
        lines.append(f"| {r['dataset']} | {r['colours']} | {r['psnr_db']:.2f} | {r['ssim']:.4f} | {extra} |")
    write_record(lines, rows, args.out)


if __name__ == "__main__":
    main()
