"""Benchmark: how much mapped surface the hash tables hold before their levels fill up.

Maps a dataset with a profile, samples points on the map's surface (its mesh, ``--samples`` per
run), and counts per hash-grid level the distinct grid vertices those points' cells touch,
before hashing. Vertices per square metre of surface, divided into the table's rows per level
(T), give the surface area at which a level is fully subscribed (load 1: from there on every row
is shared by more than one vertex on average, and collisions grow linearly with area). Reported
for the geometry and texture grids; the mapping benchmark's ``--variant`` rows with smaller
tables (``field.geo_log2_table`` / ``tex_log2_table``) show what a given load costs in quality
(docs/map_extent.md).

Usage: ``python -m benchmarks.hash_load [--dataset real] [--profile x86-cpu]``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
import torch
import trimesh

from benchmarks.mapping import open_dataset
from benchmarks.tables import write_table
from h3edge.apps.offline import map_sequence
from h3edge.config import load_profile
from h3edge.mapping.engine import MapEngine
from h3edge.mapping.trilinear import CORNERS

log = logging.getLogger(__name__)


def vertices_per_m2(grid, mesh, level: int, samples: int, rng: np.random.Generator) -> tuple[float, float]:
    """(distinct grid vertices per m² of surface at ``level``, the area measured on): cells are
    counted on a patch of the mesh (the faces nearest a random face, in the max norm) small enough
    that ``samples`` points put ~8 in every cell of the level: a surface touches vertices in
    proportion to its area, and a compact patch keeps the count's border effect at ~1 %."""
    scale = float(grid.spec.level_scales()[level])
    cell = float(grid.bound_size.max()) / scale
    want = min(float(mesh.area), samples * cell ** 2 / 8)
    centres = mesh.triangles_center
    seed = centres[rng.integers(len(centres))]
    order = np.argsort(np.abs(centres - seed).max(1), kind="stable")
    k = int(np.searchsorted(np.cumsum(mesh.area_faces[order]), want)) + 1
    sub = mesh.submesh([order[:k]], append=True)
    pts, _ = trimesh.sample.sample_surface(sub, samples, seed=int(rng.integers(1 << 31)))
    xn = grid.normalise(torch.from_numpy(np.asarray(pts, np.float32))).double()
    g = torch.floor(xn * scale + 0.5).long()
    offs = torch.from_numpy(CORNERS)
    corners = (g[:, None, :] + offs[None]).reshape(-1, 3)
    return len(torch.unique(corners, dim=0)) / float(sub.area), float(sub.area)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", default="real")
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--samples", type=int, default=2_000_000, help="surface samples per level")
    ap.add_argument("--work", type=Path, default=Path("runs/bench_mapping"))
    ap.add_argument("--out", type=Path, default=Path("research/bench_hash_load"))
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    prof = load_profile(args.profile)
    seq = open_dataset(args.dataset, args.work)
    m = MapEngine(prof.map_settings())
    map_sequence(seq, m)
    mesh = m.mesh(color=False)
    area = float(mesh.area)
    rng = np.random.default_rng(0)
    rows = []
    for name, grid in (("geometry", m.field.geo_grid), ("texture", m.field.texture.grid)):
        T = grid.spec.table_size
        for level, s in enumerate(grid.spec.level_scales()):
            per_m2, measured = vertices_per_m2(grid, mesh, level, args.samples, rng)
            n = per_m2 * area
            rows.append({"grid": name, "level": level, "cell_mm": 1000 * float(grid.bound_size.max()) / float(s),
                         "vertices": int(n), "measured_on_m2": measured, "table_rows": T, "load": n / T,
                         "vertices_per_m2": per_m2, "area_at_load_1_m2": T / per_m2})
    columns = [("grid", lambda r: r["grid"], None), ("level", lambda r: r["level"], None),
               ("cell mm", lambda r: r["cell_mm"], 1), ("vertices on the map's surface", lambda r: r["vertices"], None),
               ("rows T", lambda r: r["table_rows"], None), ("load", lambda r: r["load"], 2),
               ("vertices / m² of surface", lambda r: r["vertices_per_m2"], 0),
               ("surface m² at load 1", lambda r: r["area_at_load_1_m2"], 1)]
    write_table(args.out, f"Hash-table load, {args.dataset} ({len(seq)} frames, {area:.1f} m² of mesh surface), "
                          f"profile {args.profile}", columns, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
