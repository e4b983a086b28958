"""Shared fixtures: a tiny simulated scene made once per session, and the optional real data."""

from __future__ import annotations

import dataclasses
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
