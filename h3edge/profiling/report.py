"""Timing profiles: the document a run or a live service gives, and ``h3edge profile report``.

A profile document is JSON: ``{"profile", "device", "host", "power_mode", "frames", "components":
{name: {median_ms, p95_ms, mean_ms, total_s, count}}, "memory_bytes", "dropped"}``. Offline runs
write it as ``DIR/profile.json`` (and every frame's component times as ``DIR/timings.jsonl``); the
service answers it on ``h3edge/<map-id>/profile``. The report shows the paper's Table I
components first (ms per frame: median, p95, count), then ingest / association / queue wait /
frame age / mesh / render / checkpoint, memory and drops; with ``--vs`` two documents side by
side with the ratio other / this.
"""

from __future__ import annotations

import json
import platform
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path

from h3edge.profiling.timing import LABELS, PAPER_COMPONENTS

ORDER = PAPER_COMPONENTS + ("idle_training", "integration", "integration_wait", "frame", "ingest", "queue_wait",
                            "association", "frame_delay", "mesh", "render", "checkpoint")


def power_mode() -> str:
    """The Jetson power mode (``nvpmodel -q``, read-only), or 'n/a' off a Jetson."""
    exe = shutil.which("nvpmodel")
    if not exe:
        return "n/a"
    try:
        out = subprocess.run([exe, "-q"], capture_output=True, text=True, timeout=5).stdout
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    lines = [ln.strip() for ln in out.splitlines() if ln.strip()]
    return "; ".join(lines[:2]) or "unknown"


def device_info(device: str) -> dict:
    name = platform.processor() or platform.machine()
    try:
        import torch

        if device.startswith("cuda") and torch.cuda.is_available():
            name = torch.cuda.get_device_name(0)
    except Exception:  # noqa: BLE001 - informational only
        pass
    return {"device": f"{device} ({name})", "host": platform.node(), "power_mode": power_mode()}


def profile_document(profile_name: str, device: str, frames: int, components: dict, memory: dict | None = None,
                     dropped: dict | None = None, inference: dict | None = None) -> dict:
    """The profile document: host and mapping device, timings per component, memory, drops, and
    what the query decoders run on (``inference``: requested / active onnxruntime providers)."""
    return {"profile": profile_name, **device_info(device), "frames": frames, "components": components,
            "memory_bytes": memory or {}, "dropped": dropped or {}, "inference": inference or {}}


def load_document(source: str, live: Callable[[str], dict] | None = None, map_id: str = "default") -> dict:
    """A profile document from a run directory, a JSON file, or a live service (``zenoh:`` or
    ``zenoh:<map-id>``: ``live(map_id)`` fetches it, e.g. :func:`h3edge.serving.client.Client.profile`)."""
    if source.startswith("zenoh:"):
        if live is None:
            raise ValueError(f"{source}: a live profile needs a service connection")
        return live(source[len("zenoh:"):] or map_id)
    p = Path(source)
    if p.is_dir():
        if (p / "profile.json").exists():
            p = p / "profile.json"
        elif (p / "timings.json").exists():  # a run directory from before profile.json
            t = json.loads((p / "timings.json").read_text())
            run = json.loads((p / "run.json").read_text()) if (p / "run.json").exists() else {}
            stats = run.get("stats", {})
            return {"profile": run.get("profile", "?"), "device": stats.get("device", "?"), "host": "?",
                    "power_mode": "?", "frames": t.get("frames", 0), "components": t["components"],
                    "memory_bytes": stats.get("memory_bytes", {}), "dropped": stats.get("dropped", {})}
        else:
            raise FileNotFoundError(f"{p}: no profile.json or timings.json (not a run directory)")
    return json.loads(p.read_text())


def _rows(doc: dict) -> list[tuple[str, dict]]:
    comps = doc.get("components", {})
    names = [c for c in ORDER if c in comps] + sorted(set(comps) - set(ORDER))
    return [(c, comps[c]) for c in names]


def _decoders(doc: dict) -> str:
    """", query decoders on <providers>" from a document's ``inference`` part (older documents: "")."""
    inf = doc.get("inference") or {}
    if not inf:
        return ""
    if inf.get("decoders") != "onnx":
        return f", query decoders in {inf.get('decoders', '?')}"
    missing = f" (requested but missing: {', '.join(inf['missing'])})" if inf.get("missing") else ""
    return f", query decoders on {', '.join(inf.get('active') or ['?'])} ({inf.get('onnxruntime', '?')}){missing}"


def report(doc: dict, other: dict | None = None, fmt: str = "table") -> str:
    if fmt == "json":
        return json.dumps({"this": doc, "other": other} if other else doc, indent=1)
    head = [f"profile {doc.get('profile')} on {doc.get('device')} (host {doc.get('host')}, power mode "
            f"{doc.get('power_mode')}), {doc.get('frames')} frames{_decoders(doc)}"]
    if other:
        head.append(f"vs profile {other.get('profile')} on {other.get('device')} (host {other.get('host')}, power "
                    f"mode {other.get('power_mode')}), {other.get('frames')} frames{_decoders(other)}")
    cols = ["component", "median ms", "p95 ms", "count"]
    if other:
        cols += ["other median ms", "other p95 ms", "other / this"]
    rows = []
    oc = (other or {}).get("components", {})
    for name, s in _rows(doc):
        r = [LABELS.get(name, name), f"{s['median_ms']:.1f}", f"{s['p95_ms']:.1f}", str(s["count"])]
        if other:
            o = oc.get(name)
            r += [f"{o['median_ms']:.1f}", f"{o['p95_ms']:.1f}", f"{o['median_ms'] / s['median_ms']:.2f}x"
                  if o and s["median_ms"] > 0 else "-"] if o else ["-", "-", "-"]
        rows.append(r)
    extra = []
    for title, key in (("memory", "memory_bytes"), ("dropped", "dropped")):
        a = doc.get(key) or {}
        b = (other or {}).get(key) or {}
        if a or b:
            fmt_v = (lambda v: f"{v / 1e6:.1f} MB") if key == "memory_bytes" else str
            extra.append(f"{title}: " + ", ".join(f"{k} {fmt_v(v)}" for k, v in a.items())
                         + (" | other: " + ", ".join(f"{k} {fmt_v(v)}" for k, v in b.items()) if other else ""))
    if fmt == "markdown":
        lines = [f"**{h}**" for h in head] + ["", "| " + " | ".join(cols) + " |", "|---" * len(cols) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines + [""] + [f"- {e}" for e in extra])
    widths = [max(len(c), *(len(r[i]) for r in rows)) if rows else len(c) for i, c in enumerate(cols)]
    line = lambda vals: "  ".join(v.ljust(w) if i == 0 else v.rjust(w) for i, (v, w) in enumerate(zip(vals, widths)))  # noqa: E731
    return "\n".join(head + ["", line(cols), line(["-" * w for w in widths])] + [line(r) for r in rows] + [""] + extra)
