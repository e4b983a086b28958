"""Experiment (D53-8): one live map, its colour composed three ways, held-out views scored.

Replays a dataset at 30 Hz through the anytime benchmark's live path up to the last frame (and
``--still`` seconds of standing still), then scores the same map with the colour MLP composed with
the base as before D53-8 ("uncentred"), relative to the MLP's colour at zero texture features
("centred", shipped), and with the base alone wherever it knows a colour ("base only"). The composition is swapped on
``Field.color`` for the scoring only.

    python research/scripts/colour_composition.py --dataset real [--still 30]
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import torch

from benchmarks import anytime
from benchmarks.mapping import open_dataset
from h3edge.config import load_profile
from h3edge.mapping import field as field_module
from h3edge.mapping.color_base import compose


def _colour(mode: str):
    def color(self, points, voxel_index=None):
        if voxel_index is None:
            voxel_index = torch.full((len(points),), -1, dtype=torch.long, device=points.device)
        features = self.texture(points, voxel_index)
        rgb = self.color_mlp(features)
        base, known = self.color_base.sample(points)
        if mode == "base only":
            return torch.where(known[:, None], base, rgb)
        neutral = self.color_mlp(features.new_zeros((1, features.shape[1]))) if mode == "centred" else None
        return compose(rgb, base, known, neutral)
    return color


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default="real")
    ap.add_argument("--still", type=float, default=0.0)
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO)
    profile = load_profile("x86-cpu")
    settings = profile.map_settings()
    seq = open_dataset({"sim": "default"}.get(args.dataset, args.dataset), Path("out/bench_mapping"))
    frames = [seq[i] for i in range(len(seq))]
    held = getattr(seq, "heldout", None)
    held = [held[i] for i in range(len(held))] if held is not None and len(held) else frames[::10]
    views = anytime.pick_views(held, 8)
    marks = anytime.checkpoints(len(frames), 30.0, 1e9, [args.still] if args.still else [])
    thr = profile.eval.depth_error_threshold
    _, tsdf = anytime.replay_tsdf(frames, 30.0, 2, marks, views, thr, 0.01)
    _, _, mapper = anytime.replay_h3edge(frames, settings, 30.0, 2, marks, views, thr, tsdf["meshes"], "live")
    view = mapper.view()
    shipped = field_module.Field.color
    try:
        for mode in ("uncentred", "centred", "base only"):
            field_module.Field.color = _colour(mode)
            s = anytime.score(view, views, thr)
            print(f"{args.dataset} {'still ' + str(args.still) + ' s' if args.still else 'last frame'} {mode}: "
                  f"PSNR {s['psnr_db']:.2f} dB, SSIM {s['ssim']:.4f}", flush=True)
    finally:
        field_module.Field.color = shipped


if __name__ == "__main__":
    main()
