"""``h3edge`` command line: one entry point, one sub-command per job.

    h3edge sim make OUT [--seed S --frames N --width W --height H --preset default|studio|loft|tiny]
    h3edge sim sheet SEQUENCE OUT.png [--frames N]
    h3edge eval SEQUENCE [--mesh MESH.ply] [--reference tsdf|MESH.ply|none] [--json OUT.json]
    h3edge map SEQUENCE --out DIR [--profile P --frames N --stride S --device D --no-eval]
        (SEQUENCE: Replica / own, TUM, ScanNet export, or a rosbag2 folder / .mcap / .db3 with the ROS flags)
    h3edge demo [--out DIR] [--preset default|tiny]   # the README's main job: the whole system on loopback
    h3edge serve --profile P [--zenoh-config F] [--map-id ID] [--state-dir DIR] [--resume]
                 [--ros --base-to-camera "x y z qx qy qz qw" --ros-keys bridge|rmw_zenoh --color-topic T ...]
    h3edge sim publish SEQUENCE --rate HZ [--pose-rate HZ --jitter MS --frames N --embed-pose]
    h3edge sim bag SEQUENCE OUT [--storage mcap|sqlite3|ros1 --base-to-camera ...]
    h3edge view --save FILE.rrd | --spawn | --rerun-url URL [--duration S --render-every S]
    h3edge query status|profile|mesh|render|sdf|slice|save|load|export [--out FILE] [...]
    h3edge profile report RUN_DIR|zenoh:[MAP-ID] [--vs OTHER] [--format table|markdown|json]
    h3edge deploy plan [--profile P]   # install-time: profile for this Jetson, unit memory limits
    h3edge doctor [--profile P] [--json F]   # is this machine ready for the profile
Every zenoh-speaking command takes --zenoh-config FILE, --map-id ID and the endpoint overrides
--mode, --connect EP, --listen EP, --no-multicast.
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
    if not mesh_path.is_file():
        raise SystemExit(f"error: --mesh {mesh_path}: no such mesh file")
    mesh = trimesh.load(mesh_path, process=False)
    cfg = load_profile(args.profile).eval
    if args.points:
        cfg = dataclasses.replace(cfg, n_points=args.points)
    reference = None
    if args.reference == "tsdf" or (args.reference is None and seq.gt_mesh_path is None):
        from h3edge.eval.tsdf import fuse_tsdf

        log.info("fusing a %.0f mm TSDF of the same frames as the reference mesh", 1000 * args.tsdf_voxel)
        reference, _ = fuse_tsdf(seq, args.tsdf_voxel)
    elif args.reference and args.reference != "none":
        if not Path(args.reference).is_file():
            raise SystemExit(f"error: --reference {args.reference}: no such mesh file (or use 'tsdf' / 'none')")
        reference = trimesh.load(args.reference, process=False)
    res = evaluate(seq, mesh=mesh, cfg=cfg, reference=reference)
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
    from h3edge.apps.offline import run_offline
    from h3edge.config import apply_overrides, load_profile
    from h3edge.io import open_sequence

    profile = load_profile(args.profile)
    if args.device:
        profile = profile.with_device(args.device)
    if args.threads:
        threads = apply_overrides(profile.mapping, [f"mapper.threads={args.threads}"])
        profile = dataclasses.replace(profile, mapping=threads)
    seq = open_sequence(args.sequence, _ros_config(args, profile.ros))
    run = run_offline(seq, profile, Path(args.out), frames=args.frames, stride=args.stride,
                      evaluate_map=not args.no_eval, camera_hz=args.camera_hz, settle_s=args.settle_s)
    _print_run(run, Path(args.out))
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    """Make (or reuse) the bundled simulated scene; serve, stream, query, evaluate, print, stop."""
    from h3edge.config import load_profile
    from h3edge.io.replica import ReplicaSequence
    from h3edge.sim.make import PRESETS, ensure_scene

    out = Path(args.out)
    scene = ensure_scene(out / f"scene_{args.preset}", PRESETS[args.preset])
    if args.offline:
        from h3edge.apps.offline import run_offline

        run = run_offline(ReplicaSequence(scene), load_profile(args.profile), out / "map")
        _print_run(run, out / "map")
        return 0
    from h3edge.apps.demo import run_demo

    return run_demo(ReplicaSequence(scene), args.profile, out / "live", rate=args.rate)


def _zenoh_conf(args: argparse.Namespace):
    from h3edge.io.zenoh_session import zenoh_config

    return zenoh_config(args.zenoh_config, args.mode, args.connect, args.listen,
                        False if args.no_multicast else None)


def _profile_with_overrides(args: argparse.Namespace):
    from h3edge.config import load_profile

    profile = load_profile(args.profile)
    svc = {k: v for k, v in (("map_id", args.map_id), ("state_dir", args.state_dir),
                             ("site_from_world", getattr(args, "site_from_world", None))) if v}
    if svc:
        profile = dataclasses.replace(profile, service=dataclasses.replace(profile.service, **svc))
    if getattr(args, "device", None):
        profile = profile.with_device(args.device)
    return dataclasses.replace(profile, ros=_ros_config(args, profile.ros))


_ROS_FLAGS = {"base_to_camera": "base_to_camera", "ros_keys": "key_style", "color_topic": "color_topic",
              "depth_topic": "depth_topic", "camera_info_topic": "camera_info_topic", "pose_topic": "pose_topic",
              "pose_type": "pose_type", "base_frame": "base_frame", "world_frame": "world_frame",
              "depth_camera_info_topic": "depth_camera_info_topic", "depth_to_color": "depth_to_color"}


def _ros_config(args: argparse.Namespace, base=None):
    """The profile's ``[ros]`` table (or the defaults) with the ROS command-line flags applied."""
    from h3edge.errors import InputError
    from h3edge.io.ros import RosConfig

    over = {field: getattr(args, flag) for flag, field in _ROS_FLAGS.items() if getattr(args, flag, None)}
    try:
        return dataclasses.replace(base or RosConfig(), **over)
    except ValueError as e:
        raise InputError(f"ROS options: {e}") from None


def _add_ros_args(p: argparse.ArgumentParser, keys: bool = False) -> None:
    g = p.add_argument_group("ROS 2 topics (live input, rosbag2 recordings; defaults: the profile's [ros])")
    g.add_argument("--base-to-camera", help="the camera optical frame in the robot's base frame, "
                   "'x y z qx qy qz qw', or 'identity' when the poses already are the camera's")
    if keys:
        g.add_argument("--ros-keys", choices=["bridge", "rmw_zenoh"],
                       help="how the topics appear on zenoh: zenoh-bridge-ros2dds (ns/topic) or rmw_zenoh")
    g.add_argument("--color-topic")
    g.add_argument("--depth-topic", help="depth registered to the colour camera (16UC1 mm or 32FC1 m)")
    g.add_argument("--camera-info-topic")
    g.add_argument("--depth-camera-info-topic", help="the depth camera's own camera info: where it differs from the "
                   "colour camera's, depth is registered with --depth-to-color or refused")
    g.add_argument("--depth-to-color", help="the depth camera's optical frame in the colour camera's optical frame, "
                   "'x y z qx qy qz qw' (the driver's depth -> colour extrinsics) or 'identity': depth from its own "
                   "camera is registered into the colour camera")
    g.add_argument("--pose-topic")
    g.add_argument("--pose-type", choices=["odometry", "pose", "tf"])
    g.add_argument("--base-frame", help="the frame the poses place (Odometry child frame, TF child)")
    g.add_argument("--world-frame", help="the frame the poses are in ('' = any)")


def _cmd_serve(args: argparse.Namespace) -> int:
    from h3edge.apps.daemon import serve

    profile = _profile_with_overrides(args)
    if args.fleet_checkpoints:
        profile = dataclasses.replace(profile, service=dataclasses.replace(profile.service, fleet_checkpoints=True))
    return serve(profile, _zenoh_conf(args), resume=args.resume, ros=args.ros,
                 resume_from_fleet=args.fleet_timeout if args.resume_from_fleet else None)


def _cmd_router(args: argparse.Namespace) -> int:
    from h3edge.apps.router import run_router
    from h3edge.io.zenoh_session import zenoh_config

    listen = args.listen or (None if args.zenoh_config else ["tcp/[::]:7447"])  # the config's own wins
    return run_router(zenoh_config(args.zenoh_config, None, args.connect, listen, False if args.no_multicast else None))


def _cmd_view(args: argparse.Namespace) -> int:
    from h3edge.apps.viewer import run_viewer
    from h3edge.io.zenoh_session import open_session

    try:
        import rerun  # noqa: F401
    except ImportError:
        raise ImportError("h3edge view needs rerun-sdk: pip install 'h3edge[view]'") from None
    if not (args.save or args.rerun_url or args.spawn):
        raise SystemExit("error: view needs --save FILE.rrd, --rerun-url URL or --spawn")
    with open_session(_zenoh_conf(args)) as session:
        if args.fleet:
            from h3edge.apps.viewer import run_fleet_viewer

            counts = run_fleet_viewer(session, args.save, args.spawn, args.rerun_url, args.duration, args.render_every)
        else:
            counts = run_viewer(session, args.map_id or "default", args.save, args.spawn, args.rerun_url,
                                args.duration, args.render_every)
    print(json.dumps(counts))
    return 0


def _cmd_sim_bag(args: argparse.Namespace) -> int:
    from h3edge.io import open_sequence
    from h3edge.io.rosbag import write_rosbag

    cfg = _ros_config(args)
    if not cfg.base_to_camera:
        cfg = dataclasses.replace(cfg, base_to_camera="identity")
    out = write_rosbag(open_sequence(args.sequence), args.out, cfg, args.storage, args.rate, frames=args.frames)
    print(f"wrote {out} ({args.storage}; topics {cfg.color_topic}, {cfg.depth_topic}, {cfg.camera_info_topic}, "
          f"{cfg.pose_topic}; base_to_camera {cfg.base_to_camera})")
    return 0


def _cmd_sim_publish(args: argparse.Namespace) -> int:
    from h3edge.io import open_sequence
    from h3edge.io.protocol import Keys
    from h3edge.io.zenoh_session import open_session
    from h3edge.sim.publish import publish_sequence

    seq = open_sequence(args.sequence, _ros_config(args))
    if args.as_ros:
        from h3edge.sim.publish import publish_ros_sequence

        cfg = _ros_config(args)
        with open_session(_zenoh_conf(args)) as session:
            sent = publish_ros_sequence(session, seq, cfg, args.rate, args.pose_rate or 60.0, args.frames,
                                        args.stride)
        print(f"published {sent['frames']} frames and {sent['poses']} odometry messages as ROS 2 topics on "
              f"{', '.join(cfg.keys().values())}")
        return 0
    with open_session(_zenoh_conf(args)) as session:
        sent = publish_sequence(session, seq, Keys.for_map(args.map_id or "default"), args.rate, args.pose_rate,
                                args.jitter, args.frames, args.stride, args.embed_pose)
    print(f"published {sent['frames']} frames and {sent['poses']} poses")
    return 0


def _cmd_camera_oak(args: argparse.Namespace) -> int:
    """Check depthai and the device first (a one-line error, no traceback), then stream."""
    import signal
    import threading

    from h3edge.io import oak
    from h3edge.io.protocol import Keys
    from h3edge.io.zenoh_session import open_session

    try:
        cfg = oak.OakConfig(args.width, args.height, args.fps, args.pose_source, args.pose_wait,
                            stereo_preset=args.preset)
        dai = oak.require_depthai()
        device = oak.open_device(dai)
        stop = threading.Event()
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
        with device, open_session(_zenoh_conf(args)) as session:
            counts = oak.run_oak(cfg, session, Keys.for_map(args.map_id or "default"), device, dai, stop, args.frames)
    except (ValueError, oak.OakUnavailable) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0
    print(f"published {counts['frames']} frames and {counts['poses']} poses ({counts['dropped']} dropped)")
    return 0


def _parse_floats(text: str, n: int, what: str) -> list[float]:
    try:
        v = [float(x) for x in text.replace(",", " ").split()]
    except ValueError:
        raise SystemExit(f"error: {what} must be {n} numbers") from None
    if len(v) != n:
        raise SystemExit(f"error: {what} must be {n} numbers, got {len(v)}")
    return v


def _cmd_query(args: argparse.Namespace) -> int:
    import io

    import numpy as np

    from h3edge.serving.client import Client, RemoteError

    what = args.what
    if what == "render":
        if not args.out:
            raise SystemExit("error: render needs --out PREFIX")
        c2w = _camera_pose(args)
    elif what == "sdf" and not args.points:
        raise SystemExit("error: sdf needs --points FILE (.npy (N, 3) or text x y z per line)")
    elif what == "slice" and (args.z is None or not args.aabb):
        raise SystemExit("error: slice needs --z and --aabb x0,y0,x1,y1")
    with Client(args.map_id or "default", _zenoh_conf(args), timeout=args.timeout) as client:
        try:
            if what in ("status", "profile", "save", "load", "export"):
                reply = (client.status() if what == "status" else client.profile() if what == "profile"
                         else client.export(args.name, args.format) if what == "export"
                         else getattr(client, what)(args.name))
                if what == "profile" and not args.out:
                    print(reply["table"])
                    return 0
                _write_or_print(args.out, json.dumps(reply).encode())
            elif what == "mesh":
                aabb = _parse_floats(args.aabb, 6, "--aabb") if args.aabb else None
                _write_or_print(args.out, client.mesh(args.format, args.resolution, aabb))
            elif what == "render":
                from h3edge.io.sequence import write_color, write_depth

                color, depth = client.render(c2w, args.width, args.height, fov_deg=args.fov)
                stem = Path(args.out).with_suffix("") if Path(args.out).suffix else Path(args.out)
                cpath, dpath = Path(f"{stem}_color.png"), Path(f"{stem}_depth.png")
                cpath.parent.mkdir(parents=True, exist_ok=True)
                write_color(cpath, color)
                write_depth(dpath, depth, 1000.0)
                print(f"wrote {cpath} and {dpath}")
            else:
                if what == "sdf":
                    pts = np.load(args.points) if args.points.endswith(".npy") else np.loadtxt(args.points, ndmin=2)
                    d = client.signed_distance(pts, args.gradient)
                    arrays = {"sdf": d.sdf, "state": d.state}
                    if d.gradient is not None:
                        arrays["gradient"] = d.gradient
                    meta = None
                else:
                    box = _parse_floats(args.aabb, 4, "--aabb (x0,y0,x1,y1)")
                    sl = client.slice(args.z, box[:2], box[2:], args.cell)
                    arrays = {"occupancy": sl.occupancy, "distance": sl.distance}
                    meta = {"resolution": sl.resolution, "origin": list(sl.origin), "frame": "world",
                            "rows": "y up from origin"}
                if args.out:
                    if meta:
                        arrays_out = dict(arrays, meta=np.frombuffer(json.dumps(meta).encode(), np.uint8))
                    else:
                        arrays_out = arrays
                    buf = io.BytesIO()
                    np.savez(buf, **arrays_out)
                    Path(args.out).write_bytes(buf.getvalue())
                    print(f"wrote {args.out} (.npz: {', '.join(f'{k} {v.shape}' for k, v in arrays.items())})")
                else:
                    print(json.dumps({k: v.tolist() if v.size <= 64 else f"{v.dtype} {v.shape}"
                                      for k, v in arrays.items()}))
                    if meta:
                        print(json.dumps(meta))
        except RemoteError as e:
            print(f"error from the service: {e}", file=sys.stderr)
            return 1
        except TimeoutError as e:
            print(f"error: {e}", file=sys.stderr)
            return 1
    return 0


def _write_or_print(out: str | None, data: bytes) -> None:
    if out:
        Path(out).write_bytes(data)
        print(f"wrote {out} ({len(data)} bytes)")
    else:
        print(data.decode(errors="replace"))


def _cmd_doctor(args: argparse.Namespace) -> int:
    from h3edge.apps.doctor import doctor

    return doctor(args.profile, args.json)


def _cmd_profile_report(args: argparse.Namespace) -> int:
    from h3edge.profiling.report import load_document, report

    conf = _zenoh_conf(args) if args.source.startswith("zenoh:") or (args.vs or "").startswith("zenoh:") else None
    mid = args.map_id or "default"

    def live(map_id: str) -> dict:
        from h3edge.serving.client import Client

        with Client(map_id, conf, timeout=10.0) as client:
            return client.profile()

    try:
        doc = load_document(args.source, live, mid)
        other = load_document(args.vs, live, mid) if args.vs else None
    except (OSError, ValueError, TimeoutError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(report(doc, other, args.format))
    return 0


def _cmd_fleet(args: argparse.Namespace) -> int:
    import time

    import numpy as np

    from h3edge.io.zenoh_session import open_session
    from h3edge.serving import fleet as fl

    needs = {"sdf": (args.points, "--points FILE (.npy (N, 3) float, or text x y z per line; site frame)"),
             "slice": (args.z is not None and args.aabb, "--z and --aabb x0,y0,x1,y1 (site frame)"),
             "render": (args.out and (args.pose or args.look_at), "--out PREFIX and --pose or --look-at"),
             "mesh": (args.out, "--out FILE (.ply, .obj or .glb: one node per map)"),
             "keep": (args.dir, "--dir DIRECTORY")}
    if args.what in needs and not needs[args.what][0]:
        raise SystemExit(f"error: fleet {args.what} needs {needs[args.what][1]}")
    with open_session(_zenoh_conf(args)) as session:
        if args.what == "keep":
            return _fleet_keep(session, args)
        t0 = time.perf_counter()
        if args.what == "status":
            entries = fl.fleet_status(session, args.timeout)
            while args.wait and sum("status" in e for e in entries) < args.wait:
                if time.perf_counter() - t0 > args.wait_timeout:
                    print(f"error: {sum('status' in e for e in entries)} of {args.wait} maps answered within "
                          f"{args.wait_timeout:.0f} s", file=sys.stderr)
                    return 1
                time.sleep(0.5)
                entries = fl.fleet_status(session, args.timeout)
            seconds = time.perf_counter() - t0
            print(json.dumps(entries, indent=1) if args.json else fl.format_fleet(entries, seconds))
            return 0 if entries else 1
        if args.what == "sdf":
            pts = np.load(args.points) if args.points.endswith(".npy") else np.loadtxt(args.points, ndmin=2)
            d = fl.fleet_sdf(session, pts, args.timeout, args.gradient)
            arrays = {"sdf": d.sdf, "state": d.state, "source": d.source}
            if d.gradient is not None:
                arrays["gradient"] = d.gradient
            what = f"{len(d.sdf)} points, {int((d.source >= 0).sum())} known"
        elif args.what == "slice":
            box = _parse_floats(args.aabb, 4, "--aabb (x0,y0,x1,y1)")
            d = fl.fleet_slice(session, args.z, box[:2], box[2:], args.cell, args.timeout)
            meta = {"resolution": d.slice.resolution, "origin": list(d.slice.origin), "frame": "site",
                    "rows": "y up from origin"}
            arrays = {"occupancy": d.slice.occupancy, "distance": d.slice.distance, "source": d.source,
                      "meta": np.frombuffer(json.dumps(meta).encode(), np.uint8)}
            what = f"slice {d.source.shape[1]}x{d.source.shape[0]} cells, {int((d.source >= 0).sum())} known"
        elif args.what == "render":
            c2w = _camera_pose(args)
            d = fl.fleet_render(session, c2w, args.width, args.height, fov_deg=args.fov, timeout=args.timeout)
            from h3edge.io.sequence import write_color, write_depth

            stem = Path(args.out).with_suffix("") if Path(args.out).suffix else Path(args.out)
            Path(stem).parent.mkdir(parents=True, exist_ok=True)
            write_color(Path(f"{stem}_color.png"), d.color)
            write_depth(Path(f"{stem}_depth.png"), d.depth, 1000.0)
            arrays, what = None, f"render {args.width}x{args.height}, {int((d.source >= 0).sum())} pixels seen"
        else:
            aabb = _parse_floats(args.aabb, 6, "--aabb (site x0,y0,z0,x1,y1,z1)") if args.aabb else None
            d = fl.fleet_mesh(session, args.resolution, aabb, max(args.timeout, 30.0))
            fmt = Path(args.out).suffix.lstrip(".") or "ply"
            if fmt not in ("ply", "obj", "glb"):
                raise SystemExit("error: fleet mesh --out must end in .ply, .obj or .glb")
            Path(args.out).write_bytes(d.export(fmt))
            arrays = None
            what = "mesh " + ", ".join(f"{m}: {len(mesh.faces)} faces" for m, mesh in d.meshes.items())
        seconds = time.perf_counter() - t0
    if arrays is not None and args.out:
        import io

        buf = io.BytesIO()
        np.savez(buf, **arrays, maps=np.array(d.maps, dtype=str))
        Path(args.out).write_bytes(buf.getvalue())
    print(f"{what} from {d.maps} in {seconds * 1000:.0f} ms"
          + (f"; no answer: {d.missing}" if d.missing else "") + (f"; not near: {d.skipped}" if d.skipped else "")
          + (f"; wrote {args.out}" if args.out else ""))
    return 0 if d.maps or not d.missing else 1


def _fleet_keep(session, args: argparse.Namespace) -> int:
    import signal
    import threading

    from h3edge.serving.keeping import CheckpointKeeper

    keeper = CheckpointKeeper(session, Path(args.dir), int(args.max_mb * 2**20))
    keeper.start()
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, _frame: stop.set())
    logging.getLogger("h3edge.fleet").info("keeping the fleet's checkpoints in %s (%d kept)", args.dir,
                                            len(keeper.kept))
    stop.wait()
    keeper.close()
    return 0


def _camera_pose(args: argparse.Namespace):
    """The camera-to-world pose of ``--pose`` (tx ty tz qx qy qz qw) or ``--look-at`` (eye, target)."""
    import numpy as np

    from h3edge.geometry.camera import look_at
    from h3edge.io.protocol import pose_from_json

    if args.pose:
        v = _parse_floats(args.pose, 7, "--pose (tx ty tz qx qy qz qw)")
        return pose_from_json({"t": v[:3], "q": v[3:]}, "--pose")
    if args.look_at:
        v = _parse_floats(args.look_at, 6, "--look-at (eye xyz, target xyz)")
        return look_at(np.array(v[:3]), np.array(v[3:]))
    raise SystemExit("error: render needs --pose or --look-at")

def _cmd_deploy_site(args: argparse.Namespace) -> int:
    from h3edge.apps.site import Site, write_site

    def names(text: str) -> list[str]:
        return [n.strip() for n in text.split(",") if n.strip()]

    try:
        site = Site(names(args.robots), names(args.clients), names(args.operators), names(args.keepers), args.certs,
                    args.router, args.listen)
        written = write_site(site, Path(args.out))
    except ValueError as e:
        raise SystemExit(f"error: {e}") from None
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


def _cmd_deploy_plan(args: argparse.Namespace) -> int:
    from h3edge.deploy import format_plan, plan

    print(format_plan(plan(args.profile, args.model_file, args.meminfo, args.runtime_mb)))
    return 0


def _add_zenoh_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("zenoh")
    g.add_argument("--zenoh-config", help="zenoh JSON5 config file (default: zenoh's defaults, peer mode)")
    g.add_argument("--map-id", help="map id: keys live under h3edge/<map-id>/ (default: the profile's)")
    g.add_argument("--mode", choices=["peer", "client"], help="override the config's mode")
    g.add_argument("--connect", action="append", help="endpoint to connect to, e.g. tcp/192.168.1.10:7447")
    g.add_argument("--listen", action="append", help="endpoint to listen on, e.g. tcp/0.0.0.0:7447")
    g.add_argument("--no-multicast", action="store_true", help="disable multicast scouting")


def build_parser() -> argparse.ArgumentParser:
    from h3edge import __version__

    p = argparse.ArgumentParser(prog="h3edge", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"h3edge {__version__}")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("sim", help="simulated scene").add_subparsers(dest="sim_command", required=True)
    mk = sim.add_parser("make", help="render the procedural room into h3edge's dataset format")
    mk.add_argument("out")
    mk.add_argument("--preset", choices=["default", "studio", "loft", "tiny"], default="default",
                    help="studio: the second scene (other textures, layout and trajectory); loft: the photographic one")
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
    pb = sim.add_parser("publish", help="stream a sequence over zenoh as a robot would (frames + poses)")
    pb.add_argument("sequence")
    pb.add_argument("--rate", type=float, default=30.0, help="frames per second")
    pb.add_argument("--pose-rate", type=float, help="poses per second on the pose key (default: 30)")
    pb.add_argument("--jitter", type=float, default=0.0, help="send each message up to this many ms late")
    pb.add_argument("--frames", type=int, help="publish only the first N (strided) frames")
    pb.add_argument("--stride", type=int, default=1)
    pb.add_argument("--embed-pose", action="store_true", help="put the pose inside each frame message instead")
    pb.add_argument("--as-ros", action="store_true", help="publish as ROS 2 topics (CDR: colour, depth, camera "
                    "info, odometry), as zenoh-bridge-ros2dds or rmw_zenoh would carry them")
    _add_ros_args(pb, keys=True)
    _add_zenoh_args(pb)
    bg = sim.add_parser("bag", help="record a sequence as a rosbag2 (colour, depth, camera info, odometry)")
    bg.add_argument("sequence")
    bg.add_argument("out")
    bg.add_argument("--storage", choices=["mcap", "sqlite3", "ros1"], default="mcap",
                    help="ROS 2 bag storage, or ros1: a ROS 1 .bag")
    bg.add_argument("--rate", type=float, default=30.0, help="frames per second of the recording")
    bg.add_argument("--frames", type=int, help="only the first N frames")
    _add_ros_args(bg)
    bg.set_defaults(func=_cmd_sim_bag)
    pb.set_defaults(func=_cmd_sim_publish)

    cam = sub.add_parser("camera", help="live camera sources").add_subparsers(dest="camera_command", required=True)
    oak_p = cam.add_parser("oak", help="stream a Luxonis OAK (depthai v3): colour + depth aligned to colour "
                                       "(needs the 'oak' extra)")
    oak_p.add_argument("--width", type=int, default=640, help="colour and depth width (multiple of 16)")
    oak_p.add_argument("--height", type=int, default=480)
    oak_p.add_argument("--fps", type=float, default=15.0)
    oak_p.add_argument("--pose-source", choices=["external", "vio"], default="external",
                       help="external: the robot's odometry on h3edge/<id>/pose; vio: depthai's BasaltVIO")
    oak_p.add_argument("--pose-wait", type=float, default=10.0,
                       help="external: seconds to wait for a first pose before giving up (0: don't check)")
    oak_p.add_argument("--preset", default="DEFAULT", help="StereoDepth preset (DEFAULT, ROBOTICS, ...)")
    oak_p.add_argument("--frames", type=int, help="stop after N frames")
    _add_zenoh_args(oak_p)
    oak_p.set_defaults(func=_cmd_camera_oak)

    ev = sub.add_parser("eval", help="evaluate a mesh against a sequence (Acc/Comp, Depth L1, PSNR, SSIM)")
    ev.add_argument("sequence")
    ev.add_argument("--mesh", help="mesh to evaluate (default: the sequence's GT mesh)")
    ev.add_argument("--profile", default="x86-cpu", help="profile name or TOML path")
    ev.add_argument("--points", type=int, help="surface samples per mesh (default: the profile's)")
    ev.add_argument("--json", help="write the metrics here")
    ev.add_argument("--reference", help="reference mesh to compare with: a PLY path, 'tsdf' (fuse one from the "
                                        "sequence) or 'none'; default: 'tsdf' when the sequence has no GT mesh")
    ev.add_argument("--tsdf-voxel", type=float, default=0.01, help="voxel of the reference TSDF [m]")
    ev.set_defaults(func=_cmd_eval)

    mp = sub.add_parser("map", help="map a sequence offline: mesh, renders, metrics, timings")
    mp.add_argument("sequence")
    mp.add_argument("--profile", default="x86-cpu", help="profile name or TOML path")
    mp.add_argument("--out", required=True, help="run directory to write")
    mp.add_argument("--frames", type=int, help="map only the first N (strided) frames")
    mp.add_argument("--stride", type=int, default=1, help="use every n-th frame")
    mp.add_argument("--device", help="override the profile's device (cpu, cuda, auto)")
    mp.add_argument("--threads", type=int, help="the mapper's CPU threads (the profile's [mapper] threads)")
    mp.add_argument("--no-eval", action="store_true", help="skip evaluation")
    mp.add_argument("--camera-hz", type=float, help="live replay, as the service maps: frames arrive at this "
                                                    "rate and are integrated as they come (what integration cannot "
                                                    "keep up with is skipped) while training runs on its own thread "
                                                    "(default: every frame, fixed iterations)")
    mp.add_argument("--settle-s", type=float, default=0.0,
                    help="after the last frame, keep training on keyframes this many seconds")
    _add_ros_args(mp)
    mp.set_defaults(func=_cmd_map)

    demo = sub.add_parser("demo", help="the whole system on loopback: service, publisher, queries, metrics")
    demo.add_argument("--out", default="out/demo")
    demo.add_argument("--preset", choices=["default", "studio", "loft", "tiny"], default="default")
    demo.add_argument("--profile", default="x86-cpu", help="profile name or TOML path")
    demo.add_argument("--rate", type=float, default=2.0, help="frames per second the publisher streams")
    demo.add_argument("--offline", action="store_true", help="map in-process without zenoh (the old demo)")
    demo.set_defaults(func=_cmd_demo)

    vw = sub.add_parser("view", help="stream a running service's live map into Rerun (mesh, poses, frames, timings)")
    vw.add_argument("--fleet", action="store_true", help="every map on the network in one recording, each placed "
                    "in the site frame (entities site/<map-id>/...)")
    vw.add_argument("--save", help="write the recording to this .rrd file (headless)")
    vw.add_argument("--spawn", action="store_true", help="start a Rerun viewer on this machine")
    vw.add_argument("--rerun-url", dest="rerun_url", help="a Rerun server, e.g. rerun+http://127.0.0.1:9876/proxy")
    vw.add_argument("--duration", type=float, help="stop after this many seconds (default: until Ctrl-C)")
    vw.add_argument("--render-every", type=float, default=0.0,
                    help="seconds between renders of the map from the latest pose (0: none)")
    _add_zenoh_args(vw)
    vw.set_defaults(func=_cmd_view)

    sv = sub.add_parser("serve", help="run the mapping service (zenoh ingest, queries, checkpoints)")
    sv.add_argument("--profile", default="x86-cpu", help="profile name or TOML path")
    sv.add_argument("--state-dir", help="checkpoint directory (default: the profile's; StateDirectory under systemd)")
    sv.add_argument("--resume", action="store_true", help="restore the map from its checkpoint and go on")
    sv.add_argument("--device", help="override the profile's device (cpu, cuda, auto)")
    sv.add_argument("--site-from-world", help="this map's world frame in the site frame a fleet shares, "
                    "'x y z qx qy qz qw' ([service] site_from_world; default: the same frame)")
    sv.add_argument("--ros", action="store_true",
                    help="also take ROS 2 topics: colour, depth, camera info, odometry / pose / TF ([ros])")
    sv.add_argument("--fleet-checkpoints", action="store_true", help="publish every checkpoint for a fleet keeper "
                    "([service] fleet_checkpoints)")
    sv.add_argument("--resume-from-fleet", action="store_true", help="resume; first fetch the map from a fleet "
                    "keeper when its copy is newer than the local checkpoint (after a lost disk)")
    sv.add_argument("--fleet-timeout", type=float, default=30.0, help="seconds to wait for the keeper's answer")
    _add_ros_args(sv, keys=True)
    _add_zenoh_args(sv)
    sv.set_defaults(func=_cmd_serve)

    pr = sub.add_parser("profile", help="timing profiles").add_subparsers(dest="profile_command", required=True)
    rp = pr.add_parser("report", help="per-component timing table of a run or a live service, optionally vs another")
    rp.add_argument("source", help="run directory, profile.json, or zenoh:[MAP-ID] for a live service")
    rp.add_argument("--vs", help="a second run / service to compare with (ratios other / this)")
    rp.add_argument("--format", choices=["table", "markdown", "json"], default="table")
    _add_zenoh_args(rp)
    rp.set_defaults(func=_cmd_profile_report)

    dr = sub.add_parser("doctor", help="is this machine ready for a profile: torch and its device, numba, "
                                       "onnxruntime providers, zenoh, the memory plan, a small map, CUDA parity")
    dr.add_argument("--profile", default="x86-cpu", help="profile name or TOML path")
    dr.add_argument("--json", help="also write the checks here")
    dr.set_defaults(func=_cmd_doctor)

    dp = sub.add_parser("deploy", help="install-time helpers").add_subparsers(dest="deploy_command", required=True)
    pl = dp.add_parser("plan", help="profile for this Jetson and the unit's memory limits (KEY=value lines)")
    pl.add_argument("--profile", help="profile name or TOML path (default: from the device-tree model)")
    pl.add_argument("--model-file", default="/proc/device-tree/model")
    pl.add_argument("--meminfo", default="/proc/meminfo")
    pl.add_argument("--runtime-mb", type=float, help="the runtime's fixed cost (default: measured here)")
    pl.set_defaults(func=_cmd_deploy_plan)
    st = dp.add_parser("site", help="zenoh configs for a site: a router with TLS and per-robot access rules, and "
                       "one config per robot / client / operator / keeper (deploy/site/README.md)")
    st.add_argument("--robots", required=True, help="comma-separated map ids (each robot's certificate CN)")
    st.add_argument("--clients", default="", help="comma-separated certificate CNs that read every map")
    st.add_argument("--operators", default="", help="... that also save, load and export")
    st.add_argument("--keepers", default="", help="... that run h3edge fleet keep")
    st.add_argument("--certs", default="/etc/h3edge/tls", help="where each host keeps ca.pem, <cn>.pem, <cn>-key.pem")
    st.add_argument("--router", default="tls/site-router.local:7447", help="the router's endpoint for the others")
    st.add_argument("--listen", default="tls/0.0.0.0:7447", help="the router's listening endpoint")
    st.add_argument("--out", required=True, help="folder for router.json5 and <cn>.json5")
    st.set_defaults(func=_cmd_deploy_site)

    q = sub.add_parser("query", help="ask a running service for status, profile, mesh, render or a checkpoint")
    q.add_argument("what", choices=["status", "profile", "mesh", "render", "sdf", "slice", "save", "load", "export"])
    q.add_argument("--out", help="write the reply here (mesh file; render: PREFIX_color.png + PREFIX_depth.png)")
    q.add_argument("--format", default="ply", choices=["ply", "glb", "obj"], help="mesh format")
    q.add_argument("--resolution", type=int, help="mesh: marching-cubes cells per voxel edge")
    q.add_argument("--aabb", help="mesh: xmin,ymin,zmin,xmax,ymax,zmax; slice: x0,y0,x1,y1")
    q.add_argument("--pose", help="render: tx,ty,tz,qx,qy,qz,qw (camera-to-world, OpenCV axes)")
    q.add_argument("--look-at", help="render: ex,ey,ez,tx,ty,tz (camera at e looking at t, z up)")
    q.add_argument("--width", type=int, default=320)
    q.add_argument("--height", type=int, default=240)
    q.add_argument("--fov", type=float, default=80.0, help="render: horizontal field of view [deg]")
    q.add_argument("--points", help="sdf: points file (.npy (N, 3) float, or text with x y z per line)")
    q.add_argument("--gradient", action="store_true", help="sdf: also the gradient")
    q.add_argument("--z", type=float, help="slice: height [m]")
    q.add_argument("--cell", type=float, default=0.05, help="slice: cell size [m]")
    q.add_argument("--name", help="save / load / export: file name under the service's state directory")
    q.add_argument("--timeout", type=float, default=60.0)
    _add_zenoh_args(q)
    q.set_defaults(func=_cmd_query)

    fl = sub.add_parser("fleet", help="every h3edge service on the zenoh network as one map in the site frame: "
                        "status, sdf, slice, render, mesh; keep: store their published checkpoints")
    fl.add_argument("what", choices=["status", "sdf", "slice", "render", "mesh", "keep"])
    fl.add_argument("--timeout", type=float, default=2.0, help="seconds a fan-out may take in all (mesh: at least "
                    "30); a map that has not answered by then is named, not waited for")
    fl.add_argument("--points", help="sdf: points in the site frame (.npy (N, 3) float, or text x y z per line)")
    fl.add_argument("--gradient", action="store_true", help="sdf: also the gradient (site frame)")
    fl.add_argument("--out", help="sdf / slice: .npz (source: the map index of each answer, maps: their ids); "
                    "render: PREFIX for _color.png and _depth.png; mesh: .ply, .obj or .glb")
    fl.add_argument("--z", type=float, help="slice: height (m, site frame)")
    fl.add_argument("--aabb", help="slice: x0,y0,x1,y1; mesh: x0,y0,z0,x1,y1,z1 (site metres)")
    fl.add_argument("--cell", type=float, default=0.05, help="slice: metres per cell")
    fl.add_argument("--pose", help="render: camera-to-site 'tx ty tz qx qy qz qw' (OpenCV optical axes)")
    fl.add_argument("--look-at", help="render: 'ex ey ez tx ty tz' (eye and target, site frame)")
    fl.add_argument("--width", type=int, default=640)
    fl.add_argument("--height", type=int, default=480)
    fl.add_argument("--fov", type=float, default=80.0, help="render: horizontal field of view (degrees)")
    fl.add_argument("--resolution", type=int, help="mesh: marching-cubes cells per voxel edge")
    fl.add_argument("--dir", help="keep: where the checkpoints are kept (<dir>/<map-id>/map.h3ckpt)")
    fl.add_argument("--max-mb", type=float, default=1024.0, help="keep: largest checkpoint kept (MB)")
    fl.add_argument("--json", action="store_true", help="status: print the status documents as JSON")
    fl.add_argument("--wait", type=int, default=0, help="status: until this many maps answer (services starting)")
    fl.add_argument("--wait-timeout", type=float, default=120.0, help="status --wait: give up after this many s")
    _add_zenoh_args(fl)
    fl.set_defaults(func=_cmd_fleet)

    rt = sub.add_parser("router", help="a zenoh router for a site's fleet (services and clients connect to it)")
    rt.add_argument("--zenoh-config", help="zenoh JSON5 config (deploy/site/router.json5: TLS and per-robot ACL)")
    rt.add_argument("--listen", action="append", help="endpoint to listen on (default tcp/[::]:7447)")
    rt.add_argument("--connect", action="append", help="another router to connect to")
    rt.add_argument("--no-multicast", action="store_true", help="disable multicast scouting")
    rt.set_defaults(func=_cmd_router)
    _show_defaults(p)
    return p


def _show_defaults(parser: argparse.ArgumentParser) -> None:
    """Every option of every command says its default in ``--help`` (those that have one)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _show_defaults(sub)
            continue
        if (action.default is None or action.default is False or action.default == argparse.SUPPRESS
                or not action.option_strings
                or "%(default)" in (action.help or "")):
            continue
        action.help = f"{action.help} (default: %(default)s)" if action.help else "default: %(default)s"


def main(argv: list[str] | None = None) -> int:
    from h3edge.mapping.threads import passive_environment

    passive_environment()  # before torch loads: idle OpenMP workers sleep instead of spinning
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from h3edge.errors import InputError

    # one line and an exit status, no traceback: bad input or an optional part not installed (the
    # eval extra, depthai) is 2 (a configuration error: systemd does not restart), no zenoh is 1
    try:
        return args.func(args)
    except (InputError, ConnectionError, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1 if isinstance(e, ConnectionError) else 2


if __name__ == "__main__":
    sys.exit(main())
