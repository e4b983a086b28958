"""Benchmark: a real ``h3edge serve``'s peak RSS for hostile and large frames against its budget.

Each case gets a fresh service process (peak RSS only ever grows): three small frames of the tiny
scene warm it up, then the case's one message arrives, then a good frame. The table reports the
message's size, what the service did with it (mapped, or the drop reason), whether the good frame
after it mapped, and the service's peak RSS before and after the message, against the profile's
memory budget plus the runtime's fixed cost (RSS at start-up). Cases:

- image bombs: small PNG / JPEG / 16-bit PNG images that decode to 32767x32767 (colour) or
  20000x20000 pixels, sent (a) in a frame whose header declares 640x480 and (b) in one whose
  header declares their true size;
- legal frames: 640x480, the profile's ``max_frame_pixels`` (1920x1080 in x86-cpu) and 4096x3072
  (over that cap: refused; and mapped by a copy of the profile whose cap admits it).

Usage: ``python -m benchmarks.frame_memory [--profile x86-cpu] [--out research/bench_frame_memory]``.
"""

from __future__ import annotations

import argparse
import json
import logging
import struct
import time
import zlib
from pathlib import Path

import cv2
import numpy as np

from benchmarks.service import _rss_mb
from benchmarks.tables import write_table
from h3edge.apps.demo import ServiceProcess, wait_drained
from h3edge.config import load_profile
from h3edge.geometry.camera import Intrinsics
from h3edge.io.protocol import FrameMessage, Keys, encode_frame
from h3edge.io.replica import ReplicaSequence
from h3edge.io.zenoh_session import open_session
from h3edge.mapping.settings_file import PROFILES_DIR
from h3edge.serving.client import query, wait_for_service
from h3edge.sim.make import PRESETS, ensure_scene

log = logging.getLogger(__name__)


def png_bomb(width: int, height: int, channels: int = 3, bits: int = 8) -> bytes:
    """A valid PNG of ``width`` x ``height`` zeros, compressed as a stream (never held decoded)."""
    color_type = {1: 0, 3: 2}[channels]
    row = b"\x00" + bytes(width * channels * bits // 8)
    z = zlib.compressobj(9)
    idat = b"".join(z.compress(row) for _ in range(height)) + z.flush()

    def chunk(tag: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + tag + body + struct.pack(">I", zlib.crc32(tag + body) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, bits, color_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def jpeg_bomb(side: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", np.zeros((side, side), np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 50])
    assert ok
    return buf.tobytes()


def splice(message: bytes, part: str, image: bytes, width: int | None = None, height: int | None = None) -> bytes:
    """``message`` with its colour or depth image replaced by ``image`` (and, when given, the
    header's width / height changed to match it)."""
    n = int.from_bytes(message[4:8], "little")
    header = json.loads(message[8:8 + n])
    body = message[8 + n:]
    cs, ds = header["color"]["size"], header["depth"]["size"]
    color, depth = body[:cs], body[cs:cs + ds]
    if part == "color":
        color = image
    else:
        depth = image
    header["color"]["size"], header["depth"]["size"] = len(color), len(depth)
    if width is not None:
        header["width"], header["height"] = width, height
    hb = json.dumps(header).encode()
    return message[:4] + len(hb).to_bytes(4, "little") + hb + color + depth


def frame_at(f, width: int, height: int, ts_ns: int, color_encoding: str = "jpeg") -> bytes:
    """Frame ``f`` resized to ``width`` x ``height`` (intrinsics scaled), pose embedded."""
    sx, sy = width / f.intrinsics.width, height / f.intrinsics.height
    intr = Intrinsics(width, height, f.intrinsics.fx * sx, f.intrinsics.fy * sy, f.intrinsics.cx * sx,
                      f.intrinsics.cy * sy)
    color = cv2.resize(f.color, (width, height), interpolation=cv2.INTER_LINEAR)
    depth = cv2.resize(f.depth, (width, height), interpolation=cv2.INTER_NEAREST)
    return encode_frame(FrameMessage(ts_ns, 0, color, depth, intr, f.pose), color_encoding, "png16")


def _settle(session, keys, received: int, timeout: float = 600.0) -> dict:
    """Status once ``received`` frames have arrived and each is mapped or dropped."""
    end = time.monotonic() + 60
    while json.loads(query(session, keys.status, timeout=10))["frames"]["received"] < received:
        if time.monotonic() > end:
            raise TimeoutError(f"{received} frames did not arrive")
        time.sleep(0.05)
    return wait_drained(session, keys, timeout=timeout)


def run_case(name: str, make_message, profile: Path, work: Path, seq) -> dict:
    keys = Keys.for_map("mem")
    svc = ServiceProcess(profile, work / f"state_{name}", "mem", work / f"service_{name}.log")
    try:
        svc.wait_listening()
        with open_session(svc.client_config()) as s:
            wait_for_service(s, keys, timeout=120)
            start_rss = _rss_mb(svc.proc.pid)[0]
            for i in range(3):
                s.put(keys.frame, frame_at(seq[i], seq[i].intrinsics.width, seq[i].intrinsics.height, time.time_ns()))
                time.sleep(0.3)
            before = _settle(s, keys, 3)
            peak_before = _rss_mb(svc.proc.pid)[1]
            msg = make_message(seq[3], time.time_ns())
            t0 = time.perf_counter()
            s.put(keys.frame, msg)
            mid = _settle(s, keys, 4)
            busy_s = time.perf_counter() - t0
            peak_after = _rss_mb(svc.proc.pid)[1]
            g = seq[4]
            s.put(keys.frame, frame_at(g, g.intrinsics.width, g.intrinsics.height, time.time_ns()))
            after = _settle(s, keys, 5)
        svc.stop()
    finally:
        if svc.proc.poll() is None:
            svc.kill()
    dropped = {k: v - before["dropped"].get(k, 0) for k, v in mid["dropped"].items() if v > before["dropped"].get(k, 0)}
    outcome = "mapped" if mid["frames"]["mapped"] > before["frames"]["mapped"] else ",".join(dropped) or "?"
    return {"case": name, "message_bytes": len(msg), "outcome": outcome, "busy_s": busy_s,
            "next_good_frame_mapped": after["frames"]["mapped"] > mid["frames"]["mapped"],
            "rss_start_mb": start_rss, "peak_before_mb": peak_before, "peak_after_mb": peak_after}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--profile", default="x86-cpu")
    ap.add_argument("--work", type=Path, default=Path("runs/bench_frame_memory"))
    ap.add_argument("--out", type=Path, default=Path("research/bench_frame_memory"))
    ap.add_argument("--cases", nargs="*", help="run only these cases")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    args.work.mkdir(parents=True, exist_ok=True)
    prof = load_profile(args.profile)
    cap = prof.service.max_frame_pixels
    budget = prof.service.memory_budget_mb
    src = Path(args.profile)
    base_text = (src if src.suffix else PROFILES_DIR / f"{args.profile}.toml").read_text()
    # the tiny scene is 160x120: 3 depth points make a voxel there (as the service benchmark's soak)
    drop = ("min_points", "max_frame_pixels")
    text = "\n".join(ln for ln in base_text.splitlines() if not ln.startswith(drop))
    text = text.replace("[voxels]", "[voxels]\nmin_points = 3", 1)
    if "[service]" not in text:
        text += "\n[service]\n"
    profile = args.work / "profile.toml"
    profile.write_text(text.replace("[service]", f"[service]\nmax_frame_pixels = {cap}", 1))
    big = args.work / "profile_4096x3072.toml"
    big.write_text(text.replace("[service]", f"[service]\nmax_frame_pixels = {4096 * 3072}", 1))
    seq = ReplicaSequence(ensure_scene(args.work / "scene_tiny", PRESETS["tiny"]))

    cache: dict[str, bytes] = {}

    def bomb(kind: str) -> bytes:
        if kind not in cache:
            cache[kind] = {"png": lambda: png_bomb(32767, 32767), "png16": lambda: png_bomb(20000, 20000, 1, 16),
                           "jpeg": lambda: jpeg_bomb(20000)}[kind]()
        return cache[kind]

    sides = {"png": 32767, "png16": 20000, "jpeg": 20000}
    cases = {}
    for kind in ("png", "jpeg", "png16"):
        part = "depth" if kind == "png16" else "color"
        enc = "png" if kind == "png" else "jpeg"
        cases[f"{kind} bomb, header 640x480"] = (
            lambda f, ts, k=kind, p=part, e=enc: splice(frame_at(f, 640, 480, ts, e), p, bomb(k)), profile)
        cases[f"{kind} bomb, header {sides[kind]}^2"] = (
            lambda f, ts, k=kind, p=part, e=enc: splice(frame_at(f, 640, 480, ts, e), p, bomb(k), sides[k], sides[k]),
            profile)
    cases["640x480"] = (lambda f, ts: frame_at(f, 640, 480, ts), profile)
    w, h = (1920, 1080) if cap == 1920 * 1080 else (int(np.sqrt(cap * 4 / 3)), int(np.sqrt(cap * 3 / 4)))
    cases[f"{w}x{h} (the profile's cap)"] = (lambda f, ts: frame_at(f, w, h, ts), profile)
    cases["4096x3072, over the cap"] = (lambda f, ts: frame_at(f, 4096, 3072, ts), profile)
    cases["4096x3072, cap raised to admit it"] = (lambda f, ts: frame_at(f, 4096, 3072, ts), big)
    rows = []
    for name, (make, prof_path) in cases.items():
        if args.cases and name not in args.cases:
            continue
        log.info("case %s", name)
        r = run_case(name.replace(" ", "_").replace(",", "").replace("^", "").replace("(", "").replace(")", ""),
                     make, prof_path, args.work, seq)
        r["case"] = name
        r["limit_mb"] = r["rss_start_mb"] + budget
        rows.append(r)
        log.info("%s", r)
    columns = [("case", lambda r: r["case"], None), ("MB sent", lambda r: r["message_bytes"] / 1e6, 2),
               ("outcome", lambda r: r["outcome"], None),
               ("next good frame mapped", lambda r: "yes" if r["next_good_frame_mapped"] else "NO", None),
               ("s until handled", lambda r: r["busy_s"], 2), ("peak before MB", lambda r: r["peak_before_mb"], 0),
               ("peak after MB", lambda r: r["peak_after_mb"], 0),
               ("added MB", lambda r: r["peak_after_mb"] - r["peak_before_mb"], 0),
               ("start RSS + budget MB", lambda r: r["limit_mb"], 0)]
    write_table(args.out, f"Peak RSS per message, profile {args.profile} (budget {budget} MB; frame cap {cap} px)",
                columns, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
