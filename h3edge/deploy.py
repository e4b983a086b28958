"""Install-time plan for a Jetson: which profile, and the systemd unit's memory limits.

``deploy/install-jetson.sh`` runs ``h3edge deploy plan`` on the device and evaluates its output
(``KEY=value`` lines, shell-quoted):

- the profile from the device-tree model (``/proc/device-tree/model``): AGX Orin -> ``orin-agx``,
  Orin NX -> ``orin-nx``, Orin Nano -> ``orin-nano``; anything else needs ``--profile``;
- the runtime's fixed cost, measured here: resident memory after loading what the service loads
  (torch, numba, onnxruntime, zenoh, OpenCV) and, for a CUDA profile, the CUDA context (the
  drop in the device's free memory when it is created: on a Jetson it comes out of the same RAM);
- ``MemoryHigh`` / ``MemoryMax`` = profile budget + runtime + headroom, refused (exit 2) when it
  does not fit the device's RAM less a reserve for the OS and the camera stack.
"""

from __future__ import annotations

import math
import shlex
from dataclasses import dataclass
from pathlib import Path

from h3edge.errors import InputError

# device-tree model substrings, most specific first
JETSON_PROFILES = (("AGX Orin", "orin-agx"), ("Orin NX", "orin-nx"), ("Orin Nano", "orin-nano"))
OS_RESERVE_MB = 1024  # the OS, the camera stack, sshd: never given to the service


def profile_for_model(model: str) -> str | None:
    """The shipped profile for a device-tree model string, or None when it is not a known Jetson."""
    text = model.replace("\x00", " ")
    for needle, name in JETSON_PROFILES:
        if needle.lower() in text.lower():
            return name
    return None


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise OSError("no VmRSS in /proc/self/status")


def total_memory_mb(meminfo: str | Path = "/proc/meminfo") -> float:
    for line in Path(meminfo).read_text().splitlines():
        if line.startswith("MemTotal:"):
            return int(line.split()[1]) / 1024
    raise InputError(f"{meminfo}: no MemTotal line")


def measure_runtime_mb(device: str) -> float:
    """Resident MB after importing the service's runtime, plus the CUDA context for ``cuda``."""
    import cv2  # noqa: F401
    import numba  # noqa: F401
    import onnxruntime  # noqa: F401
    import torch
    import zenoh  # noqa: F401

    import h3edge.mapping.engine  # noqa: F401  (the module-level numba kernels)

    rss = _rss_mb()
    if device in ("cuda", "auto") and torch.cuda.is_available():
        free0, _ = torch.cuda.mem_get_info()
        torch.zeros(1, device="cuda")
        torch.cuda.synchronize()
        free1, _ = torch.cuda.mem_get_info()
        rss = _rss_mb() + max(0.0, (free0 - free1) / 2**20)
    return rss


@dataclass(frozen=True)
class MemoryLimits:
    budget_mb: int
    runtime_mb: float
    headroom_mb: float
    high_mb: int  # MemoryHigh: the kernel reclaims above it
    max_mb: int  # MemoryMax: the OOM killer stops the service above it


def memory_limits(budget_mb: int, runtime_mb: float, total_mb: float | None = None) -> MemoryLimits:
    """Unit limits for a profile budget; InputError when they do not fit ``total_mb`` of RAM."""
    headroom = max(512.0, 0.15 * budget_mb)  # allocator slack, zenoh buffers, one query in flight
    step = 256
    high = int(math.ceil((budget_mb + runtime_mb + headroom / 2) / step) * step)
    mx = int(math.ceil((budget_mb + runtime_mb + headroom) / step) * step)
    if total_mb is not None and mx > total_mb - OS_RESERVE_MB:
        raise InputError(f"memory_budget_mb {budget_mb} + runtime {runtime_mb:.0f} MB + headroom {headroom:.0f} MB "
                         f"= {mx} MB does not fit this device ({total_mb:.0f} MB, {OS_RESERVE_MB} MB kept for the OS):"
                         " pick a smaller profile or lower [service] memory_budget_mb")
    return MemoryLimits(budget_mb, runtime_mb, headroom, high, mx)


def plan(profile: str | None, model_file: str | Path = "/proc/device-tree/model",
         meminfo: str | Path = "/proc/meminfo", runtime_mb: float | None = None) -> dict:
    """The install plan as a dict of shell variables (see the module docstring)."""
    from h3edge.config import load_profile
    from h3edge.mapping.settings_file import PROFILES_DIR

    model = Path(model_file).read_text(errors="replace").strip("\x00\n ") if Path(model_file).exists() else ""
    name = profile or profile_for_model(model)
    if name is None:
        raise InputError(f"device model {model or '(none: ' + str(model_file) + ' missing)'!r} is not a known "
                         f"Jetson ({', '.join(n for n, _ in JETSON_PROFILES)}): pass --profile")
    prof = load_profile(name)
    path = Path(name) if Path(name).suffix else PROFILES_DIR / f"{name}.toml"
    rt = measure_runtime_mb(prof.mapping.mapper.device) if runtime_mb is None else runtime_mb
    lim = memory_limits(prof.service.memory_budget_mb, rt, total_memory_mb(meminfo))
    return {"DEVICE_MODEL": model, "PROFILE": prof.name, "PROFILE_FILE": str(path.resolve()),
            "MAPPING_DEVICE": prof.mapping.mapper.device, "BUDGET_MB": lim.budget_mb,
            "RUNTIME_MB": round(lim.runtime_mb), "MEMORY_HIGH": f"{lim.high_mb}M", "MEMORY_MAX": f"{lim.max_mb}M"}


def format_plan(values: dict) -> str:
    return "\n".join(f"{k}={shlex.quote(str(v))}" for k, v in values.items())
