"""Benchmark: does the map keep getting better while there is time? (training between frames)

Maps a sequence with the profile's fixed iterations per frame, then keeps training on the
keyframes alone (:meth:`~h3edge.mapping.engine.MapEngine.train_between_frames`, what the service
does whenever no frame waits and the robot stands still) and evaluates the held-out views after
each of ``--extra`` extra iterations (cumulative counts), beside a TSDF-fusion peer of the same
frames. Wall seconds of the extra training are measured; the iteration counts are what is
compared (this machine is shared). Output: a markdown table and JSON.

    python -m benchmarks.continuous [--sequence real|sim|PATH] [--extra 0 250 500 1000]
        [--out research/bench_continuous]
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from benchmarks.mapping import open_dataset
from benchmarks.tables import write_table
from h3edge.apps.offline import map_sequence
from h3edge.config import load_profile
from h3edge.eval.evaluate import MeshRenderer, evaluate_views
from h3edge.eval.tsdf import fuse_tsdf
from h3edge.mapping.engine import MapEngine

log = logging.getLogger("benchmarks.continuous")

COLUMNS = [("map", lambda r: r["map"], None), ("extra iterations", lambda r: r.get("extra_iterations"), None),
           ("extra training [s]", lambda r: r.get("extra_s"), 1),
           ("PSNR held-out [dB]", lambda r: r["psnr_db"], 2), ("SSIM", lambda r: r["ssim"], 3),
           ("Depth L1 [cm]", lambda r: r["depth_l1_cm"], 3),
           ("> 5 cm in front [%]", lambda r: 100 * r["front_share"], 2),
           ("> 5 cm behind [%]", lambda r: 100 * r["behind_share"], 2)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="real", help="real, a simulated preset (default, studio) or a path")
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--extra", type=int, nargs="+", default=[0, 250, 500, 1000],
                    help="evaluate after this many extra iterations in all (ascending)")
    ap.add_argument("--views", type=int, default=15, help="held-out views evaluated per point")
    ap.add_argument("--tsdf-voxel", type=float, default=0.01)
    ap.add_argument("--work", default="out/bench_mapping", help="where simulated scenes are cached")
    ap.add_argument("--out", default="research/bench_continuous", help="writes OUT.md and OUT.json")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    seq = open_dataset(args.sequence, Path(args.work))
    held = seq.heldout if seq.heldout is not None and len(seq.heldout) else seq
    profile = load_profile(args.profile)
    threshold = profile.eval.depth_error_threshold
    rows = []
    tsdf, _ = fuse_tsdf(seq, args.tsdf_voxel)
    rows.append({"map": f"TSDF fusion (Open3D, {1000 * args.tsdf_voxel:.0f} mm)",
                 **evaluate_views(MeshRenderer(tsdf), held, max_views=args.views, threshold=threshold)})
    mapper = MapEngine(profile.map_settings())
    t0 = time.perf_counter()
    map_sequence(seq, mapper)
    map_s = time.perf_counter() - t0
    done, spent = 0, 0.0
    for target in sorted(args.extra):
        t0 = time.perf_counter()
        while done < target and mapper.train_between_frames() is not None:
            done += 1
        spent += time.perf_counter() - t0
        res = evaluate_views(mapper.renderer(), held, max_views=args.views, threshold=threshold)
        rows.append({"map": f"h3edge ({profile.name})", "extra_iterations": done, "extra_s": spent, **res})
        log.info("%d extra iterations (%.1f s): PSNR %.2f dB, Depth L1 %.3f cm", done, spent, res["psnr_db"],
                 res["depth_l1_cm"])
    title = (f"{args.sequence}: {len(seq)} frames mapped in {map_s:.0f} s ({mapper.iterations['frame']} iterations), "
             f"then keyframe iterations only; {len(held)} held-out views, {args.views} evaluated")
    write_table(args.out, title, COLUMNS, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
