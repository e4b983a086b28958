"""The mapper's complete state as plain data (a JSON-able ``meta`` dict + named numpy arrays), and
back: what a checkpoint holds, so a restored mapper goes on mapping exactly where it stopped.

Hash tables are stored sparsely: only rows the optimiser ever touched (non-zero Adam second
moment) are written with their Adam state; the others still hold the table's seeded
initialisation, which the restoring :class:`Field` recreates. Keyframes keep their stored pixel
subsets; the texture encoder's per-voxel warps are restored as they were (not recomputed).
"""

from __future__ import annotations

import numpy as np
import torch

from h3edge.mapping.mapper import Mapper, MapSettings

STATE_VERSION = 1


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy().copy()


def _prefixed(prefix: str, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {f"{prefix}/{k}": v for k, v in arrays.items()}


def _unprefixed(prefix: str, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    n = len(prefix) + 1
    return {k[n:]: v for k, v in arrays.items() if k.startswith(prefix + "/")}


def mapper_state(m: Mapper) -> tuple[dict, dict[str, np.ndarray]]:
    """Copy everything the mapper needs to resume (call between frames, on the mapper's thread)."""
    if m.field is None:
        raise RuntimeError("nothing mapped yet")
    arrays: dict[str, np.ndarray] = {}
    meta: dict = {"state_version": STATE_VERSION, "frames_mapped": m.frames_mapped, "dropped": dict(m.dropped),
                  "last_timestamp": m.last_timestamp,
                  "iterations": dict(m.iterations),
                  "bound": m.bound.tolist(), "rng": m.rng.bit_generator.state, "grid_steps": {}}
    # field: hash grids sparsely, everything else whole
    grids = {"geo": m.field.geo_grid, "tex": m.field.texture.grid}
    for name, g in grids.items():
        rows = torch.nonzero(((g.adam_v != 0) | (g.adam_m != 0)).any(1)).squeeze(1)  # every row Adam moved
        arrays[f"grid/{name}/rows"] = _np(rows)
        for part in ("table", "adam_m", "adam_v"):
            arrays[f"grid/{name}/{part}"] = _np(getattr(g, part)[rows])
        meta["grid_steps"][name] = g.adam_steps
    for k, v in m.field.state_dict().items():
        if k.endswith(("table", "adam_m", "adam_v")):
            continue
        arrays[f"field/{k}"] = _np(v)
    opt = m.optimizer.state_dict()
    meta["optimizer_groups"] = opt["param_groups"]
    for i, st in opt["state"].items():
        for k, v in st.items():
            arrays[f"opt/{i}/{k}"] = _np(v) if torch.is_tensor(v) else np.asarray(v)
    arrays["torch_generator"] = _np(m.generator.get_state())
    # voxels and priors, their optimiser
    vmeta, varrays = m.voxels.state_dict()
    meta.update(vmeta)
    arrays.update(_prefixed("voxels", varrays))
    ometa, oarrays = m.prior_opt.state_dict()
    meta["prior_steps"] = ometa["steps"]
    arrays.update(_prefixed("prior_opt", oarrays))
    # keyframes
    kmeta, karrays = m.keyframes.state_dict()
    meta.update(kmeta)
    arrays.update(_prefixed("kf", karrays))
    # texture patterns
    pmeta, parrays = m.patterns.state_dict()
    meta["texture_updates"] = pmeta["updates"]
    arrays.update(_prefixed("patterns", parrays))
    return meta, arrays


def restore_mapper(settings: MapSettings, meta: dict, arrays: dict[str, np.ndarray]) -> Mapper:
    """A mapper in the state :func:`mapper_state` captured (settings must be the ones it ran with)."""
    if meta.get("state_version") != STATE_VERSION:
        raise ValueError(f"map state version {meta.get('state_version')} is not {STATE_VERSION}")
    m = Mapper(settings, bound=np.asarray(meta["bound"], np.float64))
    dev = m.device
    t = lambda a: torch.from_numpy(np.asarray(a)).to(dev)  # noqa: E731
    with torch.no_grad():
        for name, g in {"geo": m.field.geo_grid, "tex": m.field.texture.grid}.items():
            rows = t(arrays[f"grid/{name}/rows"]).long()
            for part in ("table", "adam_m", "adam_v"):
                getattr(g, part)[rows] = t(arrays[f"grid/{name}/{part}"])
            g.adam_steps = int(meta["grid_steps"][name])
        sd = {k[len("field/"):]: torch.from_numpy(v) for k, v in arrays.items() if k.startswith("field/")}
        current = m.field.state_dict()
        for k, v in sd.items():
            if k not in current:
                raise ValueError(f"checkpoint field entry {k!r} does not exist in this configuration")
            if k.startswith("texture.") and k.split(".")[1] in ("centres", "weak", "n_dirs", "affine"):
                setattr(m.field.texture, k.split(".")[1], v.to(dev))  # per-voxel warps: sized by the map
                continue
            if current[k].shape != v.shape:
                raise ValueError(f"checkpoint field entry {k!r} has shape {tuple(v.shape)}, "
                                 f"this configuration {tuple(current[k].shape)}")
            current[k].copy_(v.to(dev))
    state: dict = {}
    for k, v in arrays.items():
        if k.startswith("opt/"):
            _, i, name = k.split("/")
            vt = torch.from_numpy(np.array(v))
            state.setdefault(int(i), {})[name] = vt if name != "step" else vt.to(torch.float32)
    m.optimizer.load_state_dict({"state": state, "param_groups": meta["optimizer_groups"]})
    m.generator.set_state(torch.from_numpy(arrays["torch_generator"]))
    m.voxels.load_state_dict(meta, _unprefixed("voxels", arrays))
    m.prior_opt.load_state_dict({"steps": meta["prior_steps"]}, _unprefixed("prior_opt", arrays), dev)
    m.keyframes.load_state_dict(meta, _unprefixed("kf", arrays))
    m.patterns.load_state_dict({"updates": meta["texture_updates"]}, _unprefixed("patterns", arrays))
    m.frames_mapped = int(meta["frames_mapped"])
    m.dropped = dict(meta["dropped"])
    m.last_timestamp = meta["last_timestamp"]
    m.iterations.update({k: int(v) for k, v in meta.get("iterations", {}).items() if k in m.iterations})
    m.rng.bit_generator.state = meta["rng"]
    return m
