"""Real Replica data (skipped where ../shared is absent): loader and the pixel convention."""

import dataclasses

import numpy as np
import pytest
import trimesh

from h3edge.geometry.raycast import MeshRaycaster
from h3edge.io import open_sequence
from tests.conftest import REPLICA, requires_replica

pytestmark = requires_replica


@pytest.fixture(scope="module")
def office0():
    return open_sequence(REPLICA / "office0")


@pytest.fixture(scope="module")
def raycaster():
    m = trimesh.load(REPLICA / "office0_mesh.ply", process=False)
    return MeshRaycaster(m.vertices, m.faces)


def test_reader_loads_real_frames(office0):
    assert len(office0) == 4
    assert len(office0.trajectory) == 2000
    f = office0[0]
    assert f.color.shape == (680, 1200, 3) and f.color.dtype == np.uint8
    assert f.depth.dtype == np.float32 and 0.1 < np.median(f.depth[f.depth > 0]) < 10
    assert office0.intrinsics.fx == 600.0 and office0.depth_scale == 6553.5


def test_gt_mesh_render_matches_real_depth(office0, raycaster):
    """Pixel-centre rays reproduce the real depth PNGs to < 0.05 cm median."""
    for f in office0:
        d = raycaster.render_depth(f.intrinsics, f.pose)
        ok = (f.depth > 0) & (d > 0)
        assert ok.mean() > 0.99
        assert np.median(np.abs(d - f.depth)[ok]) < 0.0005


def test_half_pixel_slip_is_detected(office0, raycaster):
    """The same check with rays through integer pixel corners fails the bound: the test has teeth."""
    f = office0[0]
    slipped = dataclasses.replace(f.intrinsics, cx=f.intrinsics.cx + 0.5, cy=f.intrinsics.cy + 0.5)
    d = raycaster.render_depth(slipped, f.pose)
    ok = (f.depth > 0) & (d > 0)
    assert np.median(np.abs(d - f.depth)[ok]) > 0.001
