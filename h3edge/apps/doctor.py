"""``h3edge doctor``: is this machine ready to run a profile? One line per check, ok / warn / FAIL.

Checks, in order: the Python and the platform; torch and the mapping device the profile asks for
(``auto``, ``cpu``, ``cuda``); numba and a thread-safe threading layer (training on its own thread
needs one); onnxruntime and the profile's query-decoder providers (a missing one is a warning:
queries fall back); zenoh; Open3D (only the ``eval`` extra needs it); the profile's memory plan
against its budget; a map of a few synthetic frames on the profile's device (integrate, train,
render: the whole path in seconds); and, where CUDA is present, the hash encodings on CPU and CUDA
against each other (forward values, gradients, one sparse Adam step). Exit status 1 when a check
fails; 2, with one line, when the profile maps on CUDA and the machine has none.
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import json
import platform
import sys
import time
from dataclasses import dataclass

import numpy as np

OK, WARN, FAIL = "ok", "warn", "FAIL"


@dataclass
class Check:
    name: str
    status: str  # OK, WARN or FAIL
    detail: str


def _version(*distributions: str) -> str | None:
    """The installed version of the first of ``distributions`` present (package metadata; nothing imported)."""
    for name in distributions:
        try:
            return importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
    return None


def encoding_parity(n: int = 200_000, seed: int = 0, devices: tuple[str, str] = ("cpu", "cuda")) -> dict:
    """Max |difference| of a hash grid's forward values, gradients (and whether the same rows were
    touched) and one sparse Adam step between two devices, from the same table and points; ``ok``
    within float32 rounding of the two backends."""
    import torch

    from h3edge.mapping.hashgrid import HashGrid, HashGridSpec

    bound = np.array([[-1.0, -1.0, -1.0], [3.0, 3.0, 3.0]])
    spec = HashGridSpec(levels=4, features=2, log2_table=16, base_resolution=16, per_level_scale=2.0)
    x = torch.rand(n, 3, generator=torch.Generator().manual_seed(seed)) * 4 - 1
    res: dict = {}
    for key, dev in zip(("ref", "other"), devices):
        g = HashGrid(spec, bound, backend="torch", seed=seed, device=torch.device(dev))
        if key == "other":
            g.table.data.copy_(res["ref"]["table0"].to(dev))
        y = g(x.to(dev))
        (y * torch.arange(y.shape[1], dtype=torch.float32, device=dev)).sum().backward()
        rows, grads = g.take_sparse_grad()
        order = torch.argsort(rows)
        res[key] = {"table0": g.table.detach().clone().cpu(), "y": y.detach().cpu(), "rows": rows[order].cpu(),
                    "grads": grads[order].cpu()}
        g._accumulate(rows, grads)
        g.sparse_adam_step(1e-2)
        res[key]["table1"] = g.table.detach().cpu()
    ref, other = res["ref"], res["other"]
    out = {"forward_max_abs": float((ref["y"] - other["y"]).abs().max()),
           "same_rows": bool(torch.equal(ref["rows"], other["rows"]))}
    out["grad_max_abs"] = float((ref["grads"] - other["grads"]).abs().max()) if out["same_rows"] else None
    out["adam_max_abs"] = float((ref["table1"] - other["table1"]).abs().max())
    out["ok"] = bool(out["forward_max_abs"] < 1e-5 and out["same_rows"] and out["grad_max_abs"] is not None
                     and out["grad_max_abs"] < 1e-3 and out["adam_max_abs"] < 1e-4)
    return out


def _smoke_map(settings) -> str:
    """Map a few synthetic frames on the settings' device and render them; a one-line summary."""
    from h3edge.mapping.engine import synthetic_map

    t0 = time.perf_counter()
    mapper, intr = synthetic_map(settings, frames=3)
    _, d = mapper.render(intr, np.eye(4))
    if not (d > 0).mean() > 0.5:
        raise RuntimeError(f"the render of the synthetic wall covers {100 * (d > 0).mean():.0f} % of the view")
    steps = sum(mapper.iterations.values())
    return f"{mapper.device}: 3 frames, {steps} steps, a render in {time.perf_counter() - t0:.1f} s"


def _open3d_check() -> Check:
    """Open3D (the ``eval`` extra: sim, eval, demo, benchmarks; the service does not need it), imported
    as the simulator imports it."""
    from h3edge.geometry.raycast import import_open3d

    try:
        return Check("open3d", OK, import_open3d().__version__)
    except ImportError as e:
        return Check("open3d", WARN, f"{e} (only sim, eval, demo and the benchmarks need it)")


def run_checks(profile_name: str) -> list[Check]:
    """Every check (module docstring) for the profile ``profile_name`` (a shipped name or a path)."""
    checks = [Check("python", OK if sys.version_info >= (3, 10) else FAIL,
                    f"{platform.python_version()} on {platform.machine()} ({platform.system()})")]
    from h3edge import __version__
    from h3edge.config import load_profile

    try:
        profile = load_profile(profile_name)
    except ValueError as e:
        return checks + [Check("profile", FAIL, str(e))]
    checks.append(Check("profile", OK, f"{profile.name} (h3edge {__version__})"))
    import torch

    from h3edge.mapping.engine import resolve_device

    want = profile.mapping.mapper.device
    cuda = torch.cuda.is_available()
    gpu = f", {torch.cuda.get_device_name(0)}" if cuda else ""
    try:
        dev = resolve_device(want)
        checks.append(Check("torch", OK, f"{torch.__version__}, CUDA {'yes' + gpu if cuda else 'no'}; mapping device "
                                         f"{dev} (profile: {want})"))
    except (RuntimeError, ValueError) as e:
        checks.append(Check("torch", FAIL, f"{torch.__version__}, CUDA {'yes' if cuda else 'no'}: profile device "
                                           f"{want!r}: {e}"))
    import numba

    from h3edge.mapping.background import _check_threading_layer

    try:
        _check_threading_layer()
        checks.append(Check("numba", OK, f"{numba.__version__}, threading layer {numba.threading_layer()}"))
    except RuntimeError as e:
        status = FAIL if profile.mapping.mapper.train_between_frames else WARN
        checks.append(Check("numba", status, f"{numba.__version__}: {e}"))
    ort = _version("onnxruntime", "onnxruntime-gpu")
    if ort is None:
        checks.append(Check("onnxruntime", FAIL, "not installed (the query decoders need it)"))
    else:
        from h3edge.mapping.onnx_decoders import resolve_providers

        names, missing = resolve_providers(profile.inference)
        checks.append(Check("onnxruntime", WARN if missing else OK,
                            f"{ort}; decoders on {', '.join(names)}"
                            + (f"; requested but missing: {', '.join(missing)}" if missing else "")))
    zen = _version("eclipse-zenoh")
    checks.append(Check("zenoh", OK if zen else FAIL, zen or "eclipse-zenoh is not installed (the service needs it)"))
    checks.append(_open3d_check())
    from h3edge.mapping.memory_plan import keyframe_bytes, memory_plan

    plan = memory_plan(profile.mapping, profile.service.memory_budget_mb, keyframe_bytes(profile.mapping),
                       profile.service.max_frame_pixels, profile.service.ingest_queue)
    checks.append(Check("memory plan", OK if plan["fits"] else FAIL,
                        f"budget {profile.service.memory_budget_mb} MB: keyframes at most {plan['max_keyframes']}"
                        + ("" if plan["fits"] else " (fewer than 8: raise memory_budget_mb)")))
    try:
        checks.append(Check("map", OK, _smoke_map(profile.mapping)))
    except Exception as e:  # noqa: BLE001 - reported, not raised: the other checks still print
        checks.append(Check("map", FAIL, f"{type(e).__name__}: {e}"))
    if cuda:
        p = encoding_parity()
        checks.append(Check("cuda parity", OK if p["ok"] else FAIL,
                            f"hash encodings CPU vs CUDA: forward {p['forward_max_abs']:.1e}, gradients "
                            f"{p['grad_max_abs']}, Adam {p['adam_max_abs']:.1e}"))
    return checks


NO_CUDA = 2  # exit status: the profile maps on CUDA and this machine has none


def doctor(profile_name: str, json_path: str | None = None) -> int:
    """Print the checks, one line each (and write them as JSON to ``json_path``); 1 when one failed;
    2 (:data:`NO_CUDA`, one line on standard error, nothing checked) when the profile maps on CUDA
    and this machine has no CUDA device (an Orin profile on a laptop: run it on the Orin)."""
    import torch

    from h3edge.config import load_profile

    try:
        wanted = load_profile(profile_name).mapping.mapper.device
    except ValueError:
        wanted = ""  # the profile check below names what is wrong
    if wanted.startswith("cuda") and not torch.cuda.is_available():
        print(f"h3edge doctor: profile {profile_name} maps on {wanted} and this machine has no CUDA device "
              f"(torch {torch.__version__}): run it on the device the profile is for", file=sys.stderr)
        return NO_CUDA
    checks = run_checks(profile_name)
    width = max(len(c.name) for c in checks)
    for c in checks:
        print(f"{c.status:>4}  {c.name:<{width}}  {c.detail}")
    if json_path:
        with open(json_path, "w") as f:
            json.dump([dataclasses.asdict(c) for c in checks], f, indent=1)
    return 1 if any(c.status == FAIL for c in checks) else 0
