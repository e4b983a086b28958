"""Benchmark: the H3 mapper vs a TSDF-fusion peer on the same frames, side by side.

Datasets:
- ``sim``: the default simulated scene (400 frames 640x480, held-out views between them);
- ``loft``: the photographic simulated scene (scikit-image photographs and textures, 450 frames at
  a hand-held pace, 45 held out);
- ``studio``: the second simulated scene (other textures, layout and trajectory; 300 frames, 30
  held out);
- ``real``: the real Kinect v1 sequence ``../shared/data/7scenes_redkitchen_dev`` (7-Scenes
  redkitchen, 270 frames mapped, 30 held out; no GT mesh: both meshes are compared with the TSDF
  mesh instead, both directions);
- ``replica``: real Replica office0 geometry (``../shared/data/replica_office0``, research-only
  terms: read in place, never copied into the repository): its GT mesh ray-cast with vertex colours
  along every ``--replica-stride``-th of the 2000 real poses, held-out views at the poses half-way
  between two used ones. The rendered sequence is cached under ``--work``.

Peer: Open3D's ``VoxelBlockGrid`` TSDF fusion (CPU) when ``open3d`` imports, at ``--tsdf-voxel``
(1 cm) with a 4-voxel truncation; its mesh is rendered with vertex colours for PSNR / SSIM / Depth L1.
Both run in this process on the same frames; per-frame time is the median of the per-frame
integration time (TSDF) or whole-frame time including reading and decoding (h3edge). Beside Depth L1:
the share of valid pixels rendered "off", > 5 cm (Replica: 10 cm) in front of / behind the sensor
depth, and the median error. Output: a markdown table and JSON, and one picture per dataset (OUT_<dataset>.png; rows are
held-out views; columns: sensor colour | h3edge | TSDF | h3edge depth error (then each variant's) | TSDF depth error,
red = > 5 cm in front of the sensor depth, blue = > 5 cm behind, grey = within, white = not
rendered, black = no sensor depth).

More h3edge rows in the same run: ``--variant 'LABEL:section.key=value;section.key=value'`` maps
the same frames with those settings changed; ``--live-hz F [--settle-s S]`` adds a live replay
(frames arriving at F Hz and integrated as they come, what integration cannot keep up with
skipped, training on its own thread, then S s more; the service's path, research/decisions.md
D53-1), to compare at equal wall time; ``bench/anytime`` scores such replays against time. ``wall [s]`` is each
method's mapping time: the sum of TSDF integrations, h3edge's whole run.

    python -m benchmarks.mapping [--datasets sim replica real] [--profile x86-cpu] [--out research/bench_mapping]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from pathlib import Path

import cv2
import numpy as np
import trimesh

from benchmarks.tables import cell, markdown_table
from h3edge.apps.offline import run_offline
from h3edge.config import apply_overrides, load_profile, parse_variant
from h3edge.eval.evaluate import MeshRenderer, evaluate
from h3edge.eval.metrics import depth_error_map
from h3edge.eval.tsdf import TIMED_BLOCKS, fuse_tsdf
from h3edge.geometry.raycast import MeshRaycaster
from h3edge.io.replica import ReplicaSequence
from h3edge.io.sequence import read_pose_rows, write_color, write_depth, write_pose_rows

log = logging.getLogger("benchmarks.mapping")
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
REPLICA = SHARED / "replica_office0"
REAL = SHARED / "7scenes_redkitchen_dev"


def open_dataset(name: str, work: Path) -> ReplicaSequence:
    """A benchmark dataset by name: ``real`` (the 7-Scenes dev set), a simulated preset (``default``,
    ``studio``, ``tiny``: made once under ``work/scene_<name>``) or a sequence directory."""
    from h3edge.sim.make import PRESETS, ensure_scene

    if name == "real":
        return ReplicaSequence(REAL)
    if name in PRESETS:
        return ReplicaSequence(ensure_scene(Path(work) / f"scene_{name}", PRESETS[name]))
    return ReplicaSequence(Path(name))


def render_replica(root: Path, out: Path, stride: int) -> Path:
    """Ray-cast Replica office0's GT mesh along every ``stride``-th real pose (cached)."""
    from h3edge.io.replica import _intrinsics_from_file, find_intrinsics

    done = out / "meta.json"
    if done.is_file() and json.loads(done.read_text()).get("stride") == stride:
        return out
    intr, scale = _intrinsics_from_file(find_intrinsics(root / "office0"))
    poses = read_pose_rows(root / "office0" / "traj.txt")
    mesh = trimesh.load(root / "office0_mesh.ply", process=False)
    caster = MeshRaycaster(mesh.vertices, mesh.faces)
    colors = np.asarray(mesh.visual.vertex_colors)[:, :3]
    train = np.arange(0, len(poses), stride)
    held = train[::2][:-1] + stride // 2
    for sub, idx in (("", train), ("heldout", held)):
        d = out / sub if sub else out
        (d / "results").mkdir(parents=True, exist_ok=True)
        for k, i in enumerate(idx):
            rgb, depth = caster.render_vertex_colors(intr, poses[i], colors)
            write_color(d / "results" / f"frame{k:06d}.jpg", rgb)
            write_depth(d / "results" / f"depth{k:06d}.png", depth, scale)
        write_pose_rows(d / "traj.txt", poses[idx])
        (d / "timestamps.txt").write_text("".join(f"{i / 30:.6f}\n" for i in idx))
        (d / "intrinsics.json").write_text(json.dumps({**intr.to_dict(), "depth_scale": scale}) + "\n")
    mesh.export(out / "gt_mesh.ply")
    done.write_text(json.dumps({"source": str(root), "stride": stride, "frames": len(train)}) + "\n")
    return out


def _row(name: str, per_frame: list[float], res: dict, wall_s: float | None = None) -> dict:
    g, h, t = res.get("geometry", {}), res.get("heldout_views", {}), res.get("train_views", {})
    ref = res.get("vs_reference", {})
    pct = lambda v: None if v is None else 100 * v  # noqa: E731
    return {"method": name, "frame_ms_median": 1000 * float(np.median(per_frame)) if per_frame else None,
            "wall_s": float(sum(per_frame)) if wall_s is None else wall_s,
            "front_pct_heldout": pct(h.get("front_share")), "behind_pct_heldout": pct(h.get("behind_share")),
            "depth_median_heldout_cm": h.get("depth_median_cm"),
            "to_tsdf_cm": ref.get("to_reference_cm"), "far_from_tsdf_pct": pct(ref.get("far_from_reference_share")),
            "tsdf_not_covered_pct": pct(ref.get("reference_not_covered_share")),
            "accuracy_cm": g.get("accuracy_cm"), "completion_cm": g.get("completion_cm"),
            "completion_ratio": g.get("completion_ratio"),
            "psnr_train_db": t.get("psnr_db"), "psnr_heldout_db": h.get("psnr_db"), "ssim_heldout": h.get("ssim"),
            "depth_l1_train_cm": t.get("depth_l1_cm"), "depth_l1_heldout_cm": h.get("depth_l1_cm")}


def _ratio(r: dict) -> str:
    v = r["completion_ratio"]
    return cell(None if v is None else 100 * v, 1) + " %"


COLUMNS = [("method", lambda r: r["method"], None), ("frame [ms] median", lambda r: r["frame_ms_median"], 0),
           ("wall [s]", lambda r: r.get("wall_s"), 1),
           ("Acc [cm]", lambda r: r["accuracy_cm"], 2), ("Comp [cm]", lambda r: r["completion_cm"], 2),
           ("Comp ratio", _ratio, None), ("PSNR train", lambda r: r["psnr_train_db"], 2),
           ("PSNR held-out", lambda r: r["psnr_heldout_db"], 2), ("SSIM held-out", lambda r: r["ssim_heldout"], 3),
           ("Depth L1 train [cm]", lambda r: r["depth_l1_train_cm"], 3),
           ("Depth L1 held-out [cm]", lambda r: r["depth_l1_heldout_cm"], 3),
           ("median err held-out [cm]", lambda r: r.get("depth_median_heldout_cm"), 2),
           ("off in front [%]", lambda r: r.get("front_pct_heldout"), 2),
           ("off behind [%]", lambda r: r.get("behind_pct_heldout"), 2),
           ("mesh -> TSDF [cm]", lambda r: r.get("to_tsdf_cm"), 2),
           ("mesh > 5 cm from TSDF [%]", lambda r: r.get("far_from_tsdf_pct"), 1),
           ("TSDF > 5 cm from mesh [%]", lambda r: r.get("tsdf_not_covered_pct"), 1)]


def format_rows(title: str, rows: list[dict]) -> str:
    return markdown_table(title, COLUMNS, rows)


def bench_dataset(name: str, seq, profile, work: Path, frames: int | None, tsdf_voxel: float,
                  picture: Path | None = None, settings=None, variants: dict | None = None,
                  live_hz: float | None = None, settle_s: float = 0.0) -> dict:
    """TSDF and h3edge on ``seq``; ``variants`` {label: MapSettings} and a live replay as extra rows."""
    log.info("%s: TSDF peer (Open3D VoxelBlockGrid, %.0f mm voxels)", name, 1000 * tsdf_voxel)
    tsdf, tsdf_times = fuse_tsdf(seq, tsdf_voxel, frames, block_count=TIMED_BLOCKS)
    work.mkdir(parents=True, exist_ok=True)
    tsdf.export(work / f"{name}_tsdf_mesh.ply")
    reference = tsdf if seq.gt_mesh_path is None else None  # no GT mesh: compare with the TSDF mesh
    settings = settings or profile.map_settings()
    runs = {f"h3edge ({profile.name})": dict(settings=settings)}
    for label, st in (variants or {}).items():
        runs[f"h3edge {label}"] = dict(settings=st)
    if live_hz:
        runs[f"h3edge live @ {live_hz:g} Hz" + (f" + {settle_s:g} s" if settle_s else "")] = dict(
            settings=settings, camera_hz=live_hz, settle_s=settle_s)
    rows, first, stats, mappers = [], None, {}, {}
    for k, (label, kw) in enumerate(runs.items()):
        log.info("%s: %s, %d frames", name, label, len(seq) if frames is None else frames)
        run = run_offline(seq, profile, work / f"{name}_h3edge{'' if k == 0 else f'_{k}'}", frames=frames,
                          reference=reference, **kw)
        mapped = run["mapper"].timings.samples.get("frame", [])
        row = _row(label, mapped, run["metrics"], wall_s=run["mapping_wall_s"])
        row.update(frames_mapped=run["stats"]["frames_mapped"], iterations=run["replay"]["iterations"])
        rows.append(row)
        stats[label] = run["stats"]
        mappers[label] = run["mapper"]
        first = first or run
    rows.append(_row(f"TSDF fusion (Open3D, {1000 * tsdf_voxel:.0f} mm)", tsdf_times,
                     evaluate(seq, mesh=tsdf, cfg=profile.eval)))
    if picture is not None:
        write_comparison(seq, list(mappers.values()), MeshRenderer(tsdf), picture, profile.eval.depth_error_threshold)
    return {"dataset": name, "frames": len(first["mapper"].timings.samples["frame"]), "rows": rows,
            "h3edge_components": first["mapper"].timings.summary(), "h3edge_stats": stats}


def write_comparison(seq, h3: list, tsdf, path: Path, threshold: float = 0.05, views: int = 4, tile: int = 256) -> None:
    """One row per held-out view (training views when there are none): sensor colour | the first
    h3edge map | TSDF | each h3edge map's depth error (the first, then every variant's, in order) |
    TSDF depth error (:func:`~h3edge.eval.metrics.depth_error_map`)."""
    held = getattr(seq, "heldout", None)
    src = held if held is not None and len(held) else seq
    rows = []
    for i in np.linspace(0, len(src) - 1, min(views, len(src))).round().astype(int):
        f = src[int(i)]
        renders = [m.render(f.intrinsics, f.pose) for m in h3]
        c2, d2 = tsdf.render(f.intrinsics, f.pose)
        tiles = [f.color, renders[0][0], c2, *(depth_error_map(d, f.depth, threshold) for _, d in renders),
                 depth_error_map(d2, f.depth, threshold)]
        h = int(round(tile * f.color.shape[0] / f.color.shape[1]))
        rows.append(np.concatenate([cv2.resize(t, (tile, h), interpolation=cv2.INTER_AREA) for t in tiles], 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_color(path, np.concatenate(rows, 0))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", nargs="+", default=["sim", "studio", "replica", "real"],
                    choices=["sim", "studio", "loft", "replica", "real"])
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--frames", type=int, help="limit frames per dataset (smoke runs)")
    ap.add_argument("--replica-stride", type=int, default=5)
    ap.add_argument("--tsdf-voxel", type=float, default=0.01)
    ap.add_argument("--work", default="out/bench_mapping", help="cache and run directories")
    ap.add_argument("--out", default="research/bench_mapping", help="writes OUT.md and OUT.json")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="change the profile's setting for every h3edge row")
    ap.add_argument("--variant", action="append", default=[], metavar="LABEL:SECTION.KEY=VALUE[;...]",
                    help="one more h3edge row with these settings changed")
    ap.add_argument("--live-hz", type=float, help="one more h3edge row: a live replay at this camera rate")
    ap.add_argument("--settle-s", type=float, default=0.0, help="the live replay's training after the last frame")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    profile = load_profile(args.profile)
    settings = apply_overrides(profile.map_settings(), args.set)
    variants = dict(parse_variant(v, settings) for v in args.variant)
    work = Path(args.work)
    tables = []
    for ds in args.datasets:
        if ds == "sim":
            seq = open_dataset("default", work)
            title = "default simulated scene (640x480)"
        elif ds == "studio":
            seq = open_dataset("studio", work)
            title = "second simulated scene, studio (640x480, 300 frames, 30 held out)"
        elif ds == "loft":
            seq = open_dataset("loft", work)
            title = "photographic simulated scene, loft (640x480, 450 frames at a hand-held pace, 45 held out)"
        elif ds == "real":
            if not REAL.is_dir():
                log.warning("real skipped: %s not present", REAL)
                continue
            seq = open_dataset("real", work)
            title = "real Kinect v1: 7-Scenes redkitchen dev (270 frames, 30 held out, 640x480; no GT mesh)"
        else:
            if not REPLICA.is_dir():
                log.warning("replica skipped: %s not present", REPLICA)
                continue
            seq = ReplicaSequence(render_replica(REPLICA, work / "replica_office0", args.replica_stride))
            title = f"Replica office0 GT mesh along every {args.replica_stride}th real pose (1200x680)"
        # pixels "off": farther than this from the sensor depth (Replica's target is stated at 10 cm)
        threshold = 0.10 if ds == "replica" else profile.eval.depth_error_threshold
        prof = dataclasses.replace(profile, eval=dataclasses.replace(profile.eval, depth_error_threshold=threshold))
        title += f"; off = > {100 * threshold:.0f} cm from the sensor depth"
        out = Path(args.out)
        r = bench_dataset(ds, seq, prof, work, args.frames, args.tsdf_voxel,
                          picture=out.parent / f"{out.name}_{ds}.png", settings=settings, variants=variants,
                          live_hz=args.live_hz, settle_s=args.settle_s)
        r["title"] = title
        tables.append(format_rows(title, r["rows"]))
        print(tables[-1], flush=True)
        # written after each dataset: a long run stopped midway keeps what it measured
        out.parent.mkdir(parents=True, exist_ok=True)
        merged = _merge(out.with_suffix(".json"), [r])
        out.with_suffix(".json").write_text(json.dumps(merged, indent=1, default=str) + "\n")
        out.with_suffix(".md").write_text("\n\n".join(format_rows(m["title"], m["rows"]) for m in merged) + "\n")
    return 0


def _merge(path: Path, results: list[dict]) -> list[dict]:
    """Results of this run replace same-dataset entries of an earlier run; other datasets are kept."""
    try:
        old = json.loads(path.read_text()) if path.is_file() else []
    except ValueError:
        old = []
    fresh = {r["dataset"] for r in results}
    return [r for r in old if r.get("dataset") not in fresh] + results


if __name__ == "__main__":
    raise SystemExit(main())
