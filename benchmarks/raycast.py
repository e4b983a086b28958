"""Ray-caster benchmark: h3edge's Open3D ``MeshRaycaster`` against the embreex binding it replaced.

    python -m benchmarks.raycast [--views 20] [--width 640 --height 480] [--out research/bench_raycast]

Same process, same mesh (the simulated room at the default seed), same camera poses along its
trajectory: median milliseconds per full frame (rays through pixel centres, z-depth, triangle ids,
barycentrics) for each caster, and their agreement (depth |difference| and triangle ids). embreex
has no linux-aarch64 wheel, so it is only measured where it imports (``pip install embreex``);
the row is left out otherwise. Prints a markdown table and writes it with the JSON beside it.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from benchmarks.tables import markdown_table
from h3edge.geometry.camera import Intrinsics
from h3edge.geometry.raycast import MeshRaycaster

log = logging.getLogger(__name__)


class _EmbreexCaster(MeshRaycaster):
    """The previous caster: embreex's scene, rays split over a thread pool (embreex releases the GIL)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, threads: int):
        import os
        from concurrent.futures import ThreadPoolExecutor

        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh

        super().__init__(vertices, faces)
        self._escene = rtcs.EmbreeScene()
        self._emesh = TriangleMesh(self._escene, self.vertices, self.faces)
        self._nthreads = max(1, threads or os.cpu_count() or 1)
        self._pool = ThreadPoolExecutor(self._nthreads)

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> dict:
        o = np.ascontiguousarray(np.broadcast_to(origins, directions.shape), dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        b = np.linspace(0, len(d), self._nthreads + 1).astype(int)
        parts = list(self._pool.map(lambda ab: self._escene.run(o[ab[0]:ab[1]], d[ab[0]:ab[1]], output=1),
                                    zip(b[:-1], b[1:])))
        return {k: np.concatenate([p[k] for p in parts]) for k in ("tfar", "primID", "u", "v")}


def run(views: int, width: int, height: int) -> dict:
    from h3edge.sim.make import PRESETS
    from h3edge.sim.scene import build_room
    from h3edge.sim.trajectory import camera_path

    spec = PRESETS["default"]
    room = build_room(spec.seed)
    f = 0.5 * width / np.tan(np.radians(spec.hfov_deg) / 2)
    intr = Intrinsics(width, height, f, f, width / 2, height / 2)
    poses = camera_path(spec.frames)[:: max(1, spec.frames // views)][:views]
    meshes = {"render mesh": (room.vertices, room.faces),
              "GT mesh (5 cm)": (room.gt_mesh.vertices, room.gt_mesh.faces)}
    rows: list[dict] = []
    result = {"width": width, "height": height, "views": len(poses), "rows": rows, "meshes": {}}
    for mesh_name, (v, fc) in meshes.items():
        result["meshes"][mesh_name] = _compare(mesh_name, v, fc, intr, poses, rows)
    return result


def _compare(mesh_name: str, v: np.ndarray, fc: np.ndarray, intr: Intrinsics, poses: np.ndarray,
             rows: list[dict]) -> dict:
    casters = {"open3d": MeshRaycaster(v, fc)}
    try:
        casters["embreex"] = _EmbreexCaster(v, fc, threads=0)
    except ImportError:
        log.warning("embreex not importable: only Open3D is measured")
    hits, mine = {}, []
    for name, c in casters.items():
        c.hits(intr, poses[0])  # warm-up: BVH build, ray table
        ts, out = [], []
        for T in poses:
            t0 = time.perf_counter()
            out.append(c.hits(intr, T))
            ts.append(time.perf_counter() - t0)
        hits[name] = out
        mine.append({"mesh": mesh_name, "faces": int(len(fc)), "caster": name, "ms": 1e3 * float(np.median(ts)),
                     "p95": 1e3 * float(np.percentile(ts, 95))})
    rows += mine
    result: dict = {"faces": int(len(fc))}
    if "embreex" in hits:
        dd, same = [], []
        for a, b in zip(hits["open3d"], hits["embreex"]):
            both = a.valid & b.valid
            dd.append(np.abs(a.depth[both] - b.depth[both]))
            same.append((a.prim == b.prim).mean())
        result["depth_abs_diff_max_m"] = float(np.concatenate(dd).max())
        result["same_triangle_share"] = float(np.mean(same))
        ref = next(r["ms"] for r in mine if r["caster"] == "embreex")
        for r in mine:
            r["vs_embreex"] = ref / r["ms"]
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=20)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--out", default="research/bench_raycast", help="writes OUT.md and OUT.json")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    res = run(args.views, args.width, args.height)
    cols = [("mesh", lambda r: r["mesh"], None), ("faces", lambda r: r["faces"], None),
            ("caster", lambda r: r["caster"], None), ("median ms / frame", lambda r: r["ms"], 1),
            ("p95 ms", lambda r: r["p95"], 1), ("speed vs embreex", lambda r: r.get("vs_embreex"), 2)]
    table = markdown_table(f"Ray casting, {res['width']}x{res['height']}, {res['views']} views of the simulated room",
                           cols, res["rows"])
    for name, m in res["meshes"].items():
        if "same_triangle_share" in m:
            table += (f"\n\n{name}: same triangle on {100 * m['same_triangle_share']:.3f} % of pixels, "
                      f"depth |difference| at most {1e3 * m['depth_abs_diff_max_m']:.4f} mm where both hit.")
    print(table)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(table + "\n")
    out.with_suffix(".json").write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
