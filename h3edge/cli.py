"""``h3edge`` command line: one entry point, one sub-command per job.

    h3edge sim make OUT [--seed S --frames N --width W --height H --preset default|tiny]
    h3edge sim sheet SEQUENCE OUT.png [--frames N]
    h3edge eval SEQUENCE [--mesh MESH.ply] [--json OUT.json]
    h3edge map SEQUENCE --out DIR [--profile P --frames N --stride S --device D --no-eval]
    h3edge demo [--out DIR] [--preset default|tiny]   # the README's main job: make, map, evaluate
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from pathlib import Path

log = logging.getLogger("h3edge")


def _cmd_sim_make(args: argparse.Namespace) -> int:
    from h3edge.sim.make import PRESETS, make_scene

    spec = PRESETS[args.preset]
    overrides = {k: getattr(args, k) for k in ("seed", "frames", "width", "height") if getattr(args, k) is not None}
    overrides.update({k: True for k in ("depth_noise", "missing_depth") if getattr(args, k)})
    spec = dataclasses.replace(spec, **overrides)
    summary = make_scene(args.out, spec)
    print(f"wrote {args.out}: {summary['frames']} frames + {summary['heldout_frames']} held-out at "
          f"{spec.width}x{spec.height}; render {summary['render_ms_median']:.1f} ms/frame median "
          f"({summary['render_fps']:.1f} frames/s)")
    return 0


def _cmd_sim_sheet(args: argparse.Namespace) -> int:
    from h3edge.io import open_sequence
    from h3edge.sim.contact_sheet import write_contact_sheet

    write_contact_sheet(open_sequence(args.sequence), args.out, args.frames)
    print(f"wrote {args.out}")
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    import trimesh

    from h3edge.config import load_profile
    from h3edge.eval.evaluate import evaluate, format_table
    from h3edge.io import open_sequence

    seq = open_sequence(args.sequence)
    mesh_path = Path(args.mesh) if args.mesh else seq.gt_mesh_path
    if mesh_path is None:
        raise SystemExit(f"error: {args.sequence} has no gt_mesh.ply; pass --mesh")
    mesh = trimesh.load(mesh_path, process=False)
    cfg = load_profile(args.profile).eval
    if args.points:
        cfg = dataclasses.replace(cfg, n_points=args.points)
    res = evaluate(seq, mesh=mesh, cfg=cfg)
    print(format_table(res, f"{mesh_path} vs {args.sequence}"))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1) + "\n")
    return 0


def _print_run(run: dict, out: Path) -> None:
    stats = run["stats"]
    print(run["tables"])
    print(f"\n{stats['frames_mapped']} frames mapped ({sum(stats['dropped'].values())} dropped) in "
          f"{run['mapping_wall_s']:.1f} s, {stats['voxels']} voxels, {stats['keyframes']} keyframes; "
          f"mesh {run['mesh_vertices']} vertices; outputs in {out}/")


def _cmd_map(args: argparse.Namespace) -> int:
    import torch

    from h3edge.config import load_profile
    from h3edge.io import open_sequence
    from h3edge.mapping.offline import run_offline

    profile = load_profile(args.profile)
    if args.device:
        profile = dataclasses.replace(profile, mapper=dataclasses.replace(profile.mapper, device=args.device))
    if args.threads:
        torch.set_num_threads(args.threads)
    seq = open_sequence(args.sequence)
    run = run_offline(seq, profile, Path(args.out), frames=args.frames, stride=args.stride,
                      evaluate_map=not args.no_eval)
    _print_run(run, Path(args.out))
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    """Make (or reuse) the bundled simulated scene, map it, evaluate, print metrics and timings."""
    from h3edge.config import load_profile
    from h3edge.io.replica import ReplicaSequence
    from h3edge.mapping.offline import run_offline
    from h3edge.sim.make import PRESETS, ensure_scene

    out = Path(args.out)
    scene = ensure_scene(out / f"scene_{args.preset}", PRESETS[args.preset])
    run = run_offline(ReplicaSequence(scene), load_profile(args.profile), out / "map")
    _print_run(run, out / "map")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="h3edge", description=__doc__.splitlines()[0])
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("sim", help="simulated scene").add_subparsers(dest="sim_command", required=True)
    mk = sim.add_parser("make", help="render the procedural room into h3edge's dataset format")
    mk.add_argument("out")
    mk.add_argument("--preset", choices=["default", "tiny"], default="default")
    mk.add_argument("--seed", type=int)
    mk.add_argument("--frames", type=int)
    mk.add_argument("--width", type=int)
    mk.add_argument("--height", type=int)
    mk.add_argument("--depth-noise", action="store_true", help="axial depth noise (Kinect model)")
    mk.add_argument("--missing-depth", action="store_true", help="holes at edges, grazing angles, blobs")
    mk.set_defaults(func=_cmd_sim_make)
    sh = sim.add_parser("sheet", help="contact sheet PNG (colour over depth) of a sequence")
    sh.add_argument("sequence")
    sh.add_argument("out")
    sh.add_argument("--frames", type=int, default=12)
    sh.set_defaults(func=_cmd_sim_sheet)

    ev = sub.add_parser("eval", help="evaluate a mesh against a sequence (Acc/Comp, Depth L1, PSNR, SSIM)")
    ev.add_argument("sequence")
    ev.add_argument("--mesh", help="mesh to evaluate (default: the sequence's GT mesh)")
    ev.add_argument("--profile", default="x86-cpu", help="profile name or TOML path")
    ev.add_argument("--points", type=int, help="surface samples per mesh (default: the profile's)")
    ev.add_argument("--json", help="write the metrics here")
    ev.set_defaults(func=_cmd_eval)

    mp = sub.add_parser("map", help="map a sequence offline: mesh, renders, metrics, timings")
    mp.add_argument("sequence")
    mp.add_argument("--profile", default="x86-cpu", help="profile name or TOML path")
    mp.add_argument("--out", required=True, help="run directory to write")
    mp.add_argument("--frames", type=int, help="map only the first N (strided) frames")
    mp.add_argument("--stride", type=int, default=1, help="use every n-th frame")
    mp.add_argument("--device", help="override the profile's device (cpu, cuda, auto)")
    mp.add_argument("--threads", type=int, help="torch CPU threads")
    mp.add_argument("--no-eval", action="store_true", help="skip evaluation")
    mp.set_defaults(func=_cmd_map)

    demo = sub.add_parser("demo", help="make the bundled simulated scene, map it, evaluate (README's main job)")
    demo.add_argument("--out", default="out/demo")
    demo.add_argument("--preset", choices=["default", "tiny"], default="default")
    demo.add_argument("--profile", default="x86-cpu", help="profile name or TOML path")
    demo.set_defaults(func=_cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from h3edge.config import ProfileError
    from h3edge.io.sequence import DatasetError

    try:
        return args.func(args)
    except (DatasetError, ProfileError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
