"""Benchmark: hash encoding forward + backward at the paper's configuration, three variants.

Points are samples along real camera rays of the simulated room (a truncation band of +-5 cm
around the measured depth, as training samples them). Variants, measured side by side in one
process on the same points, median of ``--repeats``:
- ``plain``: PyTorch autograd on a gather from an nn.Parameter table (dense gradient);
- ``torch``: h3edge's PyTorch path (gather forward, row-sparse backward via unique);
- ``numba``: h3edge's fused CPU kernels (row-sparse backward).
Each timed step is forward + backward + collecting the gradient rows.

    python -m benchmarks.hashgrid [--points 200000] [--repeats 7] [--json out.json]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from benchmarks.tables import median_time
from h3edge.geometry.camera import backproject
from h3edge.mapping.hashgrid import HashGrid, HashGridSpec, corner_indices_torch
from h3edge.sim.make import SimSpec
from h3edge.sim.scene import ROOM_SIZE, build_room
from h3edge.sim.sensor import RoomRenderer
from h3edge.sim.trajectory import camera_path

VOXEL = 0.1


def ray_points(n: int, seed: int = 0) -> np.ndarray:
    """``n`` points in +-5 cm bands around the depth along pixel rays of a few frames."""
    room = build_room(0)
    r = RoomRenderer(room)
    intr = SimSpec().intrinsics
    rng = np.random.default_rng(seed)
    pts = []
    per_frame = n // 4
    for T in camera_path(40)[::10]:
        _, depth, _ = r.render(intr, T)
        rays = backproject(np.ones_like(depth), intr, None).reshape(-1, 3)  # z = 1 directions
        d = depth.reshape(-1)
        pix = rng.choice(np.flatnonzero(d > 0), per_frame // 16)
        t = d[pix, None] + np.linspace(-0.05, 0.05, 16)[None, :]
        p_cam = rays[pix, None, :] * t[..., None]
        pts.append((p_cam.reshape(-1, 3) @ T[:3, :3].T) + T[:3, 3])
    return np.concatenate(pts).astype(np.float32)


def paper_specs(bound: np.ndarray) -> dict[str, HashGridSpec]:
    base = int(np.ceil((bound[1] - bound[0]).max() / VOXEL))
    return {"geometry": HashGridSpec(4, 2, 19, base, 2.0), "texture": HashGridSpec(4, 2, 19, base, 3.0)}


def run(n_points: int, repeats: int) -> dict:
    bound = np.stack([np.zeros(3) - 0.2, ROOM_SIZE + 0.2])
    x = torch.from_numpy(ray_points(n_points))
    head = torch.randn(8)
    results = {"points": len(x), "threads": torch.get_num_threads(), "rows": []}
    for name, spec in paper_specs(bound).items():
        grids = {b: HashGrid(spec, bound, backend=b, seed=0) for b in ("torch", "numba")}
        plain_table = torch.nn.Parameter(grids["torch"].table.detach().clone())
        xn = grids["torch"].normalise(x)

        def plain():
            plain_table.grad = None
            idx, w = corner_indices_torch(xn, spec)
            y = (plain_table[idx] * w[..., None]).sum(2).reshape(len(xn), -1)
            (y @ head).sum().backward()

        def ours(grid):
            def step():
                (grid(x) @ head).sum().backward()
                grid.take_sparse_grad()
            return step

        t = {"plain": median_time(plain, repeats), "torch": median_time(ours(grids["torch"]), repeats),
             "numba": median_time(ours(grids["numba"]), repeats)}
        for variant, sec in t.items():
            results["rows"].append({"encoding": name, "variant": variant, "ms": 1000 * sec,
                                    "mpts_per_s": len(x) / sec / 1e6, "speedup_vs_plain": t["plain"] / sec})
    return results


def format_table(res: dict) -> str:
    lines = [f"hash encoding fwd+bwd, {res['points']:,} points along real rays, {res['threads']} threads",
             "", "| encoding | variant | ms | Mpts/s | x plain |", "|---|---|---|---|---|"]
    for r in res["rows"]:
        lines.append(f"| {r['encoding']} | {r['variant']} | {r['ms']:.1f} | {r['mpts_per_s']:.2f} | "
                     f"{r['speedup_vs_plain']:.1f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--json")
    a = ap.parse_args()
    res = run(a.points, a.repeats)
    print(format_table(res))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
