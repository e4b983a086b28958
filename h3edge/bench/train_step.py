"""Benchmark: the training step at equal rays, colour at every band sample vs only where it weighs.

Maps the first ``--frames`` frames of a sequence (the real dev set by default), draws ``--batches``
ray batches from the selected keyframes, then times ``train_step`` on the same batches for each
``train.color_weight_floor`` in ``--floors``, the settings alternated for ``--rounds`` rounds
(medians; the first round is warm-up). Also reports the share of in-voxel band samples above
each floor, and the median time of a mapped frame (frames 10 on, while mapping, with the profile's
floor). Output: a markdown table and JSON.

    python -m h3edge.bench.train_step [--sequence real|default|studio|PATH] [--floors 0 0.001 0.01]

To compare two versions of the code at equal rays, run it with one floor in both checkouts,
alternated (``PYTHONPATH=CHECKOUT python -m h3edge.bench.train_step --floors 0.001``).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from pathlib import Path

import numpy as np
import torch

from h3edge.bench.mapping import open_dataset
from h3edge.bench.tables import write_table
from h3edge.config import load_profile
from h3edge.mapping.mapper import Mapper
from h3edge.mapping.trainer import sample_depths, train_step
from h3edge.mapping.volume_rendering import color_samples

log = logging.getLogger("h3edge.bench.train_step")


def band_share(m: Mapper, rays, floor: float) -> float:
    """Share of the in-voxel band samples of ``rays`` whose colour a floor of ``floor`` evaluates."""
    cfg = m.train_cfg
    t, b0 = sample_depths(rays.depth, cfg, m.voxels.cfg.truncation, m.settings.render.near, m.generator)
    pts = (rays.origins[:, None] + rays.dirs[:, None] * t[..., None])[:, b0:].reshape(-1, 3)
    with torch.no_grad():
        sdf, inside = m.field.sdf(pts, m.voxels, m.voxels.locate(pts.cpu().numpy()))
    sdf, inside = sdf.reshape(len(t), -1), inside.reshape(len(t), -1)
    return float(color_samples(sdf, m.field.cfg.beta, inside, floor).sum() / max(int(inside.sum()), 1))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="real")
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--floors", type=float, nargs="+", default=[0.0, 1e-3, 1e-2])
    ap.add_argument("--batches", type=int, default=6)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--work", default="out/bench_mapping")
    ap.add_argument("--out", default="docs/bench_train_step")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    seq = open_dataset(args.sequence, Path(args.work))
    m = Mapper(load_profile(args.profile).map_settings())
    frame_s = []
    for i in range(min(args.frames, len(seq))):
        t0 = time.perf_counter()
        m.process(seq[i])
        frame_s.append(time.perf_counter() - t0)
    frame_ms = 1000 * float(np.median(frame_s[10:] or frame_s))
    batches = [m._sample_rays([k.payload for k in m.keyframes.select()]) for _ in range(args.batches)]
    times: dict[float, list[float]] = {f: [] for f in args.floors}
    for rnd in range(args.rounds):
        for floor in args.floors:
            cfg = dataclasses.replace(m.train_cfg, color_weight_floor=floor)
            for b in batches:
                t0 = time.perf_counter()
                train_step(m.field, m.voxels, b, m.optimizer, cfg, m.settings.render.near, m.generator, m.prior_opt)
                if rnd:
                    times[floor].append(time.perf_counter() - t0)
    base = float(np.median(times[args.floors[0]]))
    rows = [{"floor": f, "band_share": band_share(m, batches[0], f), "step_ms": 1000 * float(np.median(v)),
             "speedup": base / float(np.median(v)), "frame_ms": frame_ms} for f, v in times.items()]
    title = (f"training step, {len(batches[0].depth)} rays, {args.sequence} after {args.frames} frames "
             f"({args.profile}, medians of {args.rounds - 1} rounds x {args.batches} batches)")
    write_table(args.out, title, [("colour weight floor", lambda r: r["floor"], None),
                                  ("band samples coloured", lambda r: f"{100 * r['band_share']:.0f} %", None),
                                  ("step [ms]", lambda r: r["step_ms"], 1),
                                  (f"speed-up vs floor {args.floors[0]:g}", lambda r: r["speedup"], 2),
                                  ("frame [ms] (mapping)", lambda r: r["frame_ms"], 0)], rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
