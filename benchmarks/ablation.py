"""Benchmark: H3-Mapping's ablations on a scene (the paper's Tables II, III, Fig. 1).

Scenes (``--scene``): ``default`` (the bundled simulated room), ``studio`` (the second simulated
scene: other textures, layout and trajectory; 300 frames, 30 held out) and ``real`` (the 7-Scenes
dev set under ``../shared/data``, when present).

Every variant maps the same frames with the same seeds and budget (the profile's rays and
iterations) and is evaluated on the same held-out and training views:
- Table II, quasi-heterogeneous grids: (w.R, w.W) in {no, yes}^2, where (no, no) is H2-Mapping's
  uniform texture grid;
- Table III, the rest of the method: the full method without the gradient-aided keyframe score
  (H2's voxel-count coverage), without adaptive pruning (same insertion interval), without the
  surface-aware SDF loss;
- Fig. 1: held-out PSNR against iterations per frame, uniform vs quasi-heterogeneous (PNG);
- a picture of the texture classes over the scene (the full method's mesh coloured by its voxels'
  class, beside the real view), to look at what the classifier decided;
- held-out PSNR per texture class, to see where a variant gains or loses: on the simulated
  scenes by the class each surface was designed as (weak / stripes / rich, from ray casting the
  scene), on every scene by the class the mapper decided for the voxel the sensor's surface point
  lies in (weak / directional / unstructured).

``--variant 'LABEL:section.key=value;...'`` adds a Table II row with those settings changed.

Runs are cached per variant under ``--work`` (a run is reused when its settings and frame count
match), so an interrupted benchmark resumes. Output: OUT.md, OUT.json, OUT_curve.png,
OUT_classes.png.

    python -m benchmarks.ablation [--scene default|studio|real] [--frames N] [--iterations 1 2 4] \
        [--out research/ablation]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from pathlib import Path

import cv2
import numpy as np

from benchmarks.tables import markdown_table
from h3edge.apps.offline import run_offline
from h3edge.config import Profile, load_profile, parse_variant
from h3edge.eval.metrics import psnr
from h3edge.io.sequence import write_color
from h3edge.mapping.engine import MapSettings
from h3edge.mapping.texture_patterns import PLAIN, RICH, WEAK

log = logging.getLogger("benchmarks.ablation")
CLASS_BGR = {RICH: (40, 40, 230), WEAK: (230, 140, 40), PLAIN: (170, 170, 170)}


def _with(s: MapSettings, section: str, **kw) -> MapSettings:
    return dataclasses.replace(s, **{section: dataclasses.replace(getattr(s, section), **kw)})


def variants(base: MapSettings, iterations: list[int]) -> dict[str, tuple[str, MapSettings]]:
    """name -> (table, settings)."""
    uni = _with(base, "texture", quasi_heterogeneous=False)
    out = {
        "uniform": ("II", uni),
        "w.R": ("II", _with(base, "texture", warp_weak=False)),
        "w.W": ("II", _with(base, "texture", warp_rich=False)),
        "w.R + w.W (full)": ("II", base),
        "full w/o gradient-aided selection": ("III", _with(base, "keyframes", gradient_aided=False)),
        "full w/o adaptive pruning": ("III", _with(base, "keyframes", adaptive_pruning=False)),
        "full w/o surface-aware loss": ("III", _with(base, "train", surface_aware=False)),
    }
    it0 = base.mapper.iterations
    for it in iterations:
        if it != it0:
            out[f"uniform, {it} it/frame"] = ("curve", _with(uni, "mapper", iterations=it))
            out[f"quasi-heterogeneous, {it} it/frame"] = ("curve", _with(base, "mapper", iterations=it))
    return out


def _cached(run_dir: Path, settings: MapSettings, frames: int | None) -> dict | None:
    try:
        run = json.loads((run_dir / "run.json").read_text())
        timings = json.loads((run_dir / "timings.json").read_text())
    except (OSError, ValueError):
        return None
    if run.get("settings") != json.loads(json.dumps(dataclasses.asdict(settings))) or run.get("frames_req") != frames:
        return None
    if "metrics" not in run or "class_psnr" not in run:
        return None
    return {"metrics": run["metrics"], "stats": run["stats"], "components": timings["components"],
            "class_psnr": run["class_psnr"]}


def run_variant(seq, profile: Profile, settings: MapSettings, run_dir: Path, frames: int | None,
                kinds_of=None) -> dict:
    hit = _cached(run_dir, settings, frames)
    if hit is not None:
        log.info("%s: cached", run_dir.name)
        return hit
    run = run_offline(seq, profile, run_dir, frames=frames, settings=settings)
    per_class = class_psnr(run["mapper"], seq, kinds_of=kinds_of)
    # record the request so that the cache can be checked next time
    meta = json.loads((run_dir / "run.json").read_text())
    meta["frames_req"] = frames
    meta["class_psnr"] = per_class
    (run_dir / "run.json").write_text(json.dumps(meta, indent=1, default=str) + "\n")
    return {"metrics": run["metrics"], "stats": run["stats"], "components": run["mapper"].timings.summary(),
            "mapper": run["mapper"], "class_psnr": per_class}


def designed_kinds(seq):
    """Per held-out view, a function giving the designed texture kind of each pixel's surface
    (weak / stripes / rich) of a simulated scene; None for other data."""
    from h3edge.sim.make import scene_spec
    from h3edge.sim.scene import build_room
    from h3edge.sim.sensor import RoomRenderer

    spec = scene_spec(seq.root)
    if spec is None:
        return None
    room = build_room(spec.seed, layout=spec.layout)
    caster, kinds = RoomRenderer(room).raycaster, np.array(room.surface_kinds)

    def of(frame) -> np.ndarray:
        hits = caster.hits(frame.intrinsics, frame.pose)
        k = kinds[room.face_surface[np.maximum(hits.prim, 0)]].reshape(frame.depth.shape)
        return np.where(hits.valid.reshape(frame.depth.shape), k, "")
    return of


def class_psnr(mapper, seq, views: int = 10, kinds_of=None) -> dict:
    """Held-out PSNR over the pixels of each texture class (module doc), on ``views`` views."""
    from h3edge.geometry.camera import backproject
    from h3edge.mapping.texture_patterns import CLASS_NAMES

    held = getattr(seq, "heldout", None)
    src = held if held is not None and len(held) else seq
    decided = mapper.patterns.classes(len(mapper.voxels))
    preds, gts, masks = [], [], {}
    for i in np.linspace(0, len(src) - 1, min(views, len(src))).round().astype(int):
        f = src[int(i)]
        rgb, _ = mapper.render(f.intrinsics, f.pose)
        preds.append(rgb)
        gts.append(f.color)
        valid = f.depth.reshape(-1) > 0
        vox = np.full(valid.shape, -1, np.int64)
        vox[valid], _ = mapper.voxels.locate(backproject(f.depth, f.intrinsics, f.pose).reshape(-1, 3)[valid])
        cls = np.where(vox >= 0, decided[np.maximum(vox, 0)], -1).reshape(f.depth.shape)
        for c, name in CLASS_NAMES.items():
            masks.setdefault(f"decided: {name}", []).append(cls == c)
        if kinds_of is not None:
            k = kinds_of(f)
            for name in ("weak", "stripes", "rich"):
                masks.setdefault(f"designed: {name}", []).append(k == name)
    pred, gt = np.stack(preds), np.stack(gts)
    return {name: {"psnr_db": psnr(pred, gt, np.stack(m)) if np.stack(m).any() else None,
                   "pixel_share": float(np.stack(m).mean())} for name, m in masks.items()}


def row(name: str, table: str, settings: MapSettings, res: dict) -> dict:
    m = res["metrics"]
    g, h = m.get("geometry", {}), m.get("heldout_views", {})
    comp = res["components"]
    return {"variant": name, "table": table, "iterations": settings.mapper.iterations,
            "quasi_heterogeneous": settings.texture.quasi_heterogeneous,
            "psnr_heldout_db": h.get("psnr_db"), "ssim_heldout": h.get("ssim"),
            "depth_l1_heldout_cm": h.get("depth_l1_cm"), "psnr_train_db": m.get("train_views", {}).get("psnr_db"),
            "accuracy_cm": g.get("accuracy_cm"), "completion_cm": g.get("completion_cm"),
            "frame_ms_median": comp["frame"]["median_ms"],
            "texture_ms_per_frame": (1000 * comp["texture"]["total_s"] / comp["frame"]["count"]
                                     if "texture" in comp else 0.0),
            "keyframes": res["stats"].get("keyframes"), "texture_classes": res["stats"].get("texture_classes"),
            "class_psnr": res.get("class_psnr", {})}


COLUMNS = [
    ("variant", lambda r: r["variant"], None),
    ("PSNR held-out [dB]", lambda r: r["psnr_heldout_db"], 2),
    ("SSIM", lambda r: r["ssim_heldout"], 3),
    ("Depth L1 [cm]", lambda r: r["depth_l1_heldout_cm"], 3),
    ("Acc [cm]", lambda r: r["accuracy_cm"], 3),
    ("Comp [cm]", lambda r: r["completion_cm"], 3),
    ("frame [ms]", lambda r: r["frame_ms_median"], 0),
    ("texture [ms/frame]", lambda r: r["texture_ms_per_frame"], 1),
    ("keyframes", lambda r: r["keyframes"], None),
]


def format_table(title: str, rows: list[dict]) -> str:
    return markdown_table(title, COLUMNS, rows)


def format_class_table(title: str, rows: list[dict]) -> str:
    """Held-out PSNR per texture class, one column per class (share of pixels in the header)."""
    names = [n for n in (rows[0].get("class_psnr") or {})] if rows else []
    cols = [("variant", lambda r: r["variant"], None)]
    for n in names:
        share = rows[0]["class_psnr"][n]["pixel_share"]
        cols.append(
            (f"{n} ({100 * share:.0f} % px)", lambda r, n=n: (r.get("class_psnr") or {}).get(n, {}).get("psnr_db"), 2)
        )
    return markdown_table(title, cols, rows)


def plot_curve(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=120)
    for quasi, label, style in ((False, "uniform grid (H2)", "o--"), (True, "quasi-heterogeneous (H3)", "s-")):
        pts = sorted((r["iterations"], r["psnr_heldout_db"]) for r in rows if r["quasi_heterogeneous"] == quasi)
        if pts:
            ax.plot(*zip(*pts), style, label=label)
    ax.set_xlabel("iterations per frame")
    ax.set_ylabel("held-out PSNR [dB]")
    ax.set_title("texture fidelity vs training iterations")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def class_picture(mapper, seq, path: Path, views: int = 3) -> dict:
    """The map's mesh coloured by texture class beside the real view, for a few views."""
    from h3edge.geometry.raycast import MeshRaycaster

    mesh = mapper.mesh(color=False)
    vox, _ = mapper.voxels.locate(np.asarray(mesh.vertices))
    cls = mapper.patterns.classes(len(mapper.voxels))
    vcls = np.where(vox >= 0, cls[np.maximum(vox, 0)], PLAIN)
    colors = np.array([CLASS_BGR[int(c)][::-1] for c in vcls], np.uint8)
    caster = MeshRaycaster(mesh.vertices, mesh.faces)
    strips = []
    for i in np.linspace(0, len(seq) - 1, views).round().astype(int):
        f = seq[int(i)]
        rgb, depth = caster.render_vertex_colors(f.intrinsics, f.pose, colors)
        rgb[depth <= 0] = 0
        blend = (0.55 * rgb + 0.45 * f.color).astype(np.uint8)
        strips.append(np.concatenate([f.color, blend], 1))
    img = np.concatenate(strips, 0)[..., ::-1]
    img = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)  # docs-sized
    for k, (c, name) in enumerate(((RICH, "rich + low-freq. directions (affine warps)"), (WEAK, "weak (scaling warp)"),
                                  (PLAIN, "unstructured rich (identity)"))):
        cv2.rectangle(img, (6, 6 + 16 * k), (18, 18 + 16 * k), CLASS_BGR[c], -1)
        cv2.putText(img, name, (24, 17 + 16 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    write_color(Path(path), img[..., ::-1])
    return {k: int((vcls == c).sum()) for k, c in (("rich", RICH), ("weak", WEAK), ("plain", PLAIN))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--frames", type=int, help="map only the first N frames (smoke runs)")
    ap.add_argument("--iterations", type=int, nargs="+", default=[1, 2, 4], help="Fig. 1 curve points")
    ap.add_argument("--max-views", type=int, default=20, help="evaluation views per split")
    ap.add_argument("--only", nargs="+", help="run only these variants (names as printed)")
    ap.add_argument("--scene", choices=["default", "studio", "real"], default="default")
    ap.add_argument("--variant", action="append", default=[], metavar="LABEL:SECTION.KEY=VALUE[;...]",
                    help="one more Table II row with these settings changed")
    ap.add_argument("--work", default="out/bench_ablation")
    ap.add_argument("--out", default="research/ablation",
                    help="writes OUT.md, OUT.json, OUT_curve.png, OUT_classes.png")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    profile = load_profile(args.profile)
    profile = dataclasses.replace(profile, eval=dataclasses.replace(profile.eval, max_views=args.max_views))
    from benchmarks.mapping import REAL, open_dataset

    if args.scene == "real" and not REAL.is_dir():
        log.error("%s not present", REAL)
        return 2
    seq = open_dataset(args.scene, Path("out/bench_mapping"))
    kinds_of = designed_kinds(seq)
    work, out = Path(args.work) / args.scene, Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows, classes = [], None
    todo = variants(profile.map_settings(), args.iterations)
    for v in args.variant:
        label, settings = parse_variant(v, profile.map_settings())
        todo[label] = ("II", settings)
    for name, (table, settings) in todo.items():
        if args.only and name not in args.only:
            continue
        log.info("variant %r", name)
        slug = "".join(c if c.isalnum() else "_" for c in name).strip("_")
        res = run_variant(seq, profile, settings, work / slug, args.frames, kinds_of)
        rows.append(row(name, table, settings, res))
        if name == "w.R + w.W (full)" and "mapper" in res:
            classes = class_picture(res["mapper"], seq, out.with_name(out.name + "_classes.png"))
        res.pop("mapper", None)
    t2 = [r for r in rows if r["table"] == "II"]
    t3 = [r for r in rows if r["variant"] == "w.R + w.W (full)"] + [r for r in rows if r["table"] == "III"]
    curve = [r for r in rows if r["table"] == "curve" or r["variant"] in ("uniform", "w.R + w.W (full)")]
    frames = args.frames or len(seq)
    tables = [format_table(f"Table II: quasi-heterogeneous feature grids ({args.scene} scene, {profile.name}, "
                           f"{frames} frames)", t2),
              format_class_table("Table II per texture class: held-out PSNR [dB]", t2),
              format_table("Table III: keyframe policy and surface-aware loss", t3),
              format_table("Fig. 1: held-out PSNR vs iterations per frame", sorted(
                  curve, key=lambda r: (r["quasi_heterogeneous"], r["iterations"])))]
    for t in tables:
        print(t + "\n", flush=True)
    if curve:
        plot_curve(curve, out.with_name(out.name + "_curve.png"))
    out.with_suffix(".json").write_text(json.dumps({"profile": profile.name, "frames": frames, "rows": rows,
                                                    "class_picture_vertices": classes}, indent=1) + "\n")
    out.with_suffix(".md").write_text("\n\n".join(tables) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
