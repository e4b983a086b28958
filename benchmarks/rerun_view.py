"""The live view end to end, as a picture: a real ``h3edge serve --ros`` fed a sequence as ROS 2
topics (CDR on loopback zenoh), ``h3edge view`` recording it to an ``.rrd`` file, and that
recording read back and drawn to a PNG (what the Rerun viewer shows: the block meshes, the camera
path, the latest frame, a render from the latest pose, the status and timing plots).

Usage: ``python -m benchmarks.rerun_view [--dataset real] [--frames 60]``; writes
``research/rerun_view.png`` and the recording under ``--work``.
"""

from __future__ import annotations

import argparse
import collections
import json
import logging
import threading
import time
from pathlib import Path

import numpy as np

from benchmarks.mapping import REAL, open_dataset

log = logging.getLogger("benchmarks.rerun_view")


def record(seq, frames: int, rate: float, profile: str, work: Path) -> Path:
    from h3edge.apps.demo import ServiceProcess, wait_drained
    from h3edge.apps.viewer import run_viewer
    from h3edge.io.protocol import Keys
    from h3edge.io.ros import RosConfig
    from h3edge.io.zenoh_session import open_session
    from h3edge.serving.client import wait_for_service
    from h3edge.sim.publish import publish_ros_sequence

    rrd = work / "view.rrd"
    rrd.unlink(missing_ok=True)
    state = work / "state"
    svc = ServiceProcess(profile, state, "view", work / "service.log", extra=["--ros", "--base-to-camera", "identity"])
    try:
        svc.wait_listening()
        keys = Keys.for_map("view")
        with open_session(svc.client_config()) as session:
            wait_for_service(session, keys, timeout=120)
            stop = threading.Event()
            counts: dict = {}
            viewer = threading.Thread(target=lambda: counts.update(run_viewer(session, "view", save=str(rrd), stop=stop,
                                                                             render_every_s=5.0)))
            viewer.start()
            stride = max(1, len(seq) // frames)
            publish_ros_sequence(session, seq, RosConfig(base_to_camera="identity"), rate=rate, frames=frames,
                                 stride=stride)
            wait_drained(session, keys, timeout=1800)
            time.sleep(4.0)  # the last live updates
            stop.set()
            viewer.join(120)
            log.info("viewer logged %s", counts)
    finally:
        svc.stop()
    return rrd


def read_recording(rrd: Path) -> dict:
    """The latest value of each entity of interest, and the scalar series."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    latest: dict[str, dict] = {}
    series: dict[str, list[tuple[float, float]]] = collections.defaultdict(list)
    for ch in RrdReader(str(rrd)).store().stream():
        path = str(ch.entity_path)
        rb = ch.to_record_batch()
        cols = {n.split(":")[-1]: rb.column(n) for n in rb.schema.names}
        t = cols.get("time")
        times = [v * 1e-9 for v in t.cast(pa.int64()).to_pylist()] if t is not None else [0.0] * rb.num_rows
        if "scalars" in cols:
            for tt, v in zip(times, cols["scalars"].to_pylist()):
                if v:
                    series[path].append((tt, float(v[0])))
            continue
        for r in range(rb.num_rows):
            row = {k: c[r].as_py() for k, c in cols.items() if k not in ("RowId", "log_time", "time")}
            row = {k: v for k, v in row.items() if v is not None}
            if row and (path not in latest or times[r] >= latest[path]["_t"]):
                latest[path] = {**latest.get(path, {}), **row, "_t": times[r]}
    return {"latest": latest, "series": dict(series)}


def _image(entry: dict) -> np.ndarray | None:
    if "buffer" not in entry or "format" not in entry:
        return None
    fmt = entry["format"][0]  # component batches of one
    w, h = fmt["width"], fmt["height"]
    buf = np.frombuffer(bytes(entry["buffer"][0]), np.uint8)
    return buf.reshape(h, w, -1)[..., :3] if buf.size >= w * h * 3 else None


def draw(data: dict, out: Path) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    latest, series = data["latest"], data["series"]
    verts, faces, cols = [], [], []
    n = 0
    for path, e in latest.items():
        if path.startswith("/world/mesh/") and "vertex_positions" in e and "triangle_indices" in e:
            v = np.asarray(e["vertex_positions"], np.float32)
            f = np.asarray(e["triangle_indices"], np.int64)
            c = np.asarray(e.get("vertex_colors", [[200, 200, 200, 255]] * len(v)))
            c = np.stack([(c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255], -1) if c.ndim == 1 else c[:, :3]
            verts.append(v)
            faces.append(f + n)
            cols.append(c)
            n += len(v)
    V, F, C = np.concatenate(verts), np.concatenate(faces), np.concatenate(cols).astype(np.float64) / 255
    fig = plt.figure(figsize=(16, 9))
    ax = fig.add_subplot(1, 2, 1)
    # the scene as the viewer's 3D view shows it: from behind and above the latest camera
    cam = latest.get("/world/camera", {})
    R = np.asarray(cam.get("mat3x3", [np.eye(3).reshape(-1).tolist()])[0], np.float64).reshape(3, 3, order="F")
    t = np.asarray(cam.get("translation", [[0.0, 0.0, 0.0]])[0], np.float64)
    eye = t - 1.5 * R[:, 2] - 0.8 * R[:, 1]  # back along the view axis, up (camera y points down)
    fwd = np.median(V, 0) - eye  # looking at the middle of the map
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, -R[:, 1])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    W2C = np.stack([right, down, fwd])
    f_px, w_px, h_px = 700.0, 960, 720

    def project(p):
        q = (np.asarray(p) - eye) @ W2C.T
        u = f_px * q[..., 0] / q[..., 2] + w_px / 2
        return np.stack([u, f_px * q[..., 1] / q[..., 2] + h_px / 2], -1), q[..., 2]

    uv, z = project(V)
    tri_z = z[F].mean(1)
    ok = (z[F] > 0.1).all(1)
    order = np.argsort(-tri_z[ok])
    from matplotlib.collections import PolyCollection

    ax.add_collection(PolyCollection(uv[F[ok]][order], facecolors=C[F[ok]].mean(1)[order], edgecolors="none"))
    traj = latest.get("/world/trajectory", {}).get("strips")
    if traj:
        tp, tz = project(np.asarray(traj[0]))
        ax.plot(tp[tz > 0.1, 0], tp[tz > 0.1, 1], color="orange", lw=2)
    ax.set_xlim(0, w_px)
    ax.set_ylim(h_px, 0)
    ax.set_aspect("equal")
    ax.axis("off")
    blocks = sum(1 for p in latest if p.startswith("/world/mesh/"))
    ax.set_title(f"world/mesh ({blocks} block meshes, {len(F)} faces) and world/trajectory, from behind the camera")
    for k, (path, title) in enumerate((("/world/camera/image", "world/camera/image (latest frame)"),
                                       ("/world/render/color", "world/render/color (map rendered at that pose)"))):
        img = _image(latest.get(path, {}))
        a = fig.add_subplot(3, 4, 3 + k)
        if img is not None:
            a.imshow(img)
        a.set_title(title, fontsize=9)
        a.axis("off")
    for k, (path, label) in enumerate((("/status/frames_mapped", "status/frames_mapped"),
                                       ("/status/voxels", "status/voxels"),
                                       ("/timings/frame", "timings/frame (median ms)"),
                                       ("/timings/training", "timings/training (median ms)"))):
        a = fig.add_subplot(3, 4, 7 + k + (2 if k >= 2 else 0))
        s = np.array(series.get(path, []))
        if len(s):
            a.plot(s[:, 0] - s[0, 0], s[:, 1])
        a.set_title(label, fontsize=9)
        a.set_xlabel("s", fontsize=8)
    fig.suptitle("h3edge view: the Rerun recording of a live ROS 2 mapping run, read back from the .rrd")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    return {"blocks": blocks, "faces": int(len(F)), "trajectory_points": len(traj[0]) if traj else 0,
            "entities": sorted(latest) + sorted(series)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", default="real" if REAL.is_dir() else "default")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--rate", type=float, default=1.0, help="frames per second published")
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--work", type=Path, default=Path("runs/rerun_view"))
    ap.add_argument("--out", type=Path, default=Path("research/rerun_view.png"))
    ap.add_argument("--rrd", type=Path, help="draw this recording instead of making one")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    rrd = args.rrd or record(open_dataset(args.dataset, Path("runs/bench_mapping")), args.frames, args.rate,
                             args.profile, args.work)
    info = draw(read_recording(rrd), args.out)
    print(json.dumps({"rrd": str(rrd), "png": str(args.out), **info}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
