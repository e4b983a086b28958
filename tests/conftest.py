"""Shared fixtures: a tiny simulated scene made once per session, and the optional real data.

``H3EDGE_TEST_DEVICE=cuda`` runs every mapper the tests build on that device whatever their
settings say (``deploy/check-cuda.sh`` uses it on a GPU machine; CPU-only backends stay on CPU).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import pytest

from h3edge.sim.make import PRESETS, make_scene

SHARED = Path(__file__).resolve().parents[2] / "shared"
REPLICA = SHARED / "data" / "replica_office0"


@pytest.fixture(scope="session")
def tiny_spec():
    return PRESETS["tiny"]


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory, tiny_spec) -> Path:
    out = tmp_path_factory.mktemp("tiny") / "scene"
    make_scene(out, tiny_spec)
    return out


@pytest.fixture(scope="session")
def tiny_noisy_spec(tiny_spec):
    return dataclasses.replace(tiny_spec, frames=6, depth_noise=True, missing_depth=True)


requires_replica = pytest.mark.skipif(not REPLICA.is_dir(), reason="../shared/data/replica_office0 not present")


@pytest.fixture(autouse=True)
def _forced_device(monkeypatch):
    """Map on ``H3EDGE_TEST_DEVICE`` when set: resolve every mapper device to it, torch hash grids."""
    forced = os.environ.get("H3EDGE_TEST_DEVICE")
    if not forced:
        yield
        return
    import torch

    from h3edge.mapping import engine as mapper_mod
    from h3edge.mapping import field as field_mod

    real_resolve = mapper_mod.resolve_device
    monkeypatch.setattr(mapper_mod, "resolve_device", lambda name: real_resolve(forced))
    real_init = field_mod.Field.__init__

    def init(self, cfg, *a, **kw):
        dev = kw.get("device", a[2] if len(a) > 2 else None)
        if dev is not None and torch.device(dev).type != "cpu" and cfg.backend == "numba":
            cfg = dataclasses.replace(cfg, backend="torch")
        real_init(self, cfg, *a, **kw)

    monkeypatch.setattr(field_mod.Field, "__init__", init)
    yield
