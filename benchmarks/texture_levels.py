"""Diagnosis: which texture feature block and level the colour field actually uses.

    python -m benchmarks.texture_levels [--sequence studio|default|real|PATH] [--profile x86-cpu]
        [--set SECTION.KEY=VALUE ...] [--views 20] [--out research/texture_levels]

Maps the sequence (or reuses ``--work``'s checkpoint of the same settings), then for every feature
block of the texture encoder (identity, scaling-warped, affine-warped m = 0, 1; the uniform grid
has one block) and every level of it:
- ``col_norm``: the mean L2 norm of the colour MLP's first-layer weight columns that read it;
- ``feature``: the mean |feature| at points of the map's surface (marching-cubes vertices);
- ``d_colour``: the mean |colour change| x 255 at those points when that level's features are
  read as zero (everything else as trained): what the level contributes to the colours;
- ``psnr_drop``: with ``--views`` > 0, the held-out PSNR of the map minus that with the level
  zeroed, over evenly spread held-out views (positive: the level helps).
A level whose zeroing changes nothing was trained but is not used. Writes OUT.md and OUT.json.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
import torch

from benchmarks.mapping import open_dataset
from benchmarks.silhouettes import mapped
from benchmarks.tables import write_table
from h3edge.config import apply_overrides, load_profile
from h3edge.eval.metrics import psnr
from h3edge.mapping.raymarch import PriorLookup

log = logging.getLogger("benchmarks.texture_levels")
BLOCKS = ("identity", "scaling warp", "affine warp m=0", "affine warp m=1")


class LevelMask:
    """Context manager: the texture encoder ``texture`` reads the feature columns ``cols`` as zero."""

    def __init__(self, texture: torch.nn.Module, cols: list[int]):
        self.texture, self.cols = texture, cols

    def __enter__(self):
        inner = self.texture.forward

        def forward(points, voxel_index):
            out = inner(points, voxel_index)
            if self.cols:
                out = out.clone()
                out[:, self.cols] = 0
            return out

        self.texture.forward = forward
        return self

    def __exit__(self, *exc):
        del self.texture.forward  # back to the class's method
        return False


def level_columns(block: int, level: int, levels: int, features: int) -> list[int]:
    """Columns of ``level`` of feature block ``block`` in the encoder's output (block-major,
    level-major within a block, ``features`` per level)."""
    start = block * levels * features + level * features
    return list(range(start, start + features))


def heldout_psnr(m, frames) -> float:
    view = m.view()
    return float(np.mean([psnr(view.render(f.intrinsics, f.pose)[0], f.color) for f in frames]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="studio", help="studio | default | real | a sequence directory")
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--views", type=int, default=20, help="held-out views for the PSNR column (0: none)")
    ap.add_argument("--work", default="out/bench_mapping", help="datasets and map checkpoints")
    ap.add_argument("--out", default="research/texture_levels")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    settings = apply_overrides(load_profile(args.profile).map_settings(), args.set)
    work = Path(args.work)
    seq = open_dataset(args.sequence, work)
    m = mapped(seq, settings, len(seq), work / "texture_levels_maps")
    texture = m.field.texture
    spec = texture.grid.spec
    n_blocks = texture.out_dim // (spec.levels * spec.features)
    verts = np.asarray(m.mesh(resolution=5, color=False).vertices, np.float32)
    pts = torch.from_numpy(verts).to(m.field.color_mlp[0][0].weight.device)
    vox = torch.from_numpy(PriorLookup(m.voxels)(verts)[1]).to(pts.device)
    weight = m.field.color_mlp[0][0].weight.detach().cpu().numpy()
    held = seq.heldout if getattr(seq, "heldout", None) is not None and len(seq.heldout) else seq
    frames = [held[int(i)] for i in np.linspace(0, len(held) - 1, min(args.views, len(held))).round()]
    base = heldout_psnr(m, frames) if frames else None
    rows = []
    with torch.no_grad():
        feats = texture(pts, vox).cpu().numpy()
        colour = m.field.color(pts, vox)
        for b in range(n_blocks):
            for level in range(spec.levels):
                cols = level_columns(b, level, spec.levels, spec.features)
                with LevelMask(texture, cols):
                    d = float(255 * (m.field.color(pts, vox) - colour).abs().mean())
                    drop = base - heldout_psnr(m, frames) if frames else None
                rows.append({"block": BLOCKS[b] if n_blocks > 1 else "uniform", "level": level,
                             "col_norm": float(np.linalg.norm(weight[:, cols], axis=0).mean()),
                             "feature": float(np.abs(feats[:, cols]).mean()), "d_colour": d, "psnr_drop": drop})
                log.info("%s level %d: |d colour| %.2f, PSNR drop %s", rows[-1]["block"], level, d, drop)
    overrides = ", " + "; ".join(args.set) if args.set else ""
    title = (f"texture feature levels, {args.sequence} ({args.profile}{overrides}): {len(verts)} surface points, "
             f"held-out PSNR {base if base is None else round(base, 2)} dB over {len(frames)} views")
    columns = [("block", lambda r: r["block"], None), ("level", lambda r: r["level"], None),
               ("first-layer column norm", lambda r: r["col_norm"], 2), ("mean |feature|", lambda r: r["feature"], 3),
               ("mean |colour change| x255 when zeroed", lambda r: r["d_colour"], 2),
               ("held-out PSNR drop when zeroed [dB]", lambda r: r["psnr_drop"], 2)]
    write_table(Path(args.out), title, columns, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
