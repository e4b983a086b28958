"""Observed free space and the planner outputs: free only where depth rays passed, unknown
elsewhere; signed distance near surfaces; the free-space record survives a checkpoint."""

from __future__ import annotations

import numpy as np

from h3edge.geometry.camera import Intrinsics
from h3edge.io.replica import ReplicaSequence
from h3edge.mapping.distance import FREE, INSIDE, NEAR, UNKNOWN, distance_slice, signed_distance
from h3edge.mapping.engine import MapEngine, MapperConfig, MapSettings
from h3edge.mapping.free_space import FreeSpace, FreeSpaceConfig


def test_free_space_is_only_where_rays_passed():
    intr = Intrinsics(320, 240, 300.0, 300.0, 160.0, 120.0)  # rays 8 px apart: 5 cm apart at 1.9 m
    depth = np.full((240, 320), 2.0, np.float32)
    depth[:, :40] = 0.0  # no return on the left edge: not evidence of anything
    fs = FreeSpace(FreeSpaceConfig(stride=8), voxel_size=0.1, truncation=0.05)
    assert fs.mark(depth, intr, np.eye(4)) > 0
    in_front = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.85]])
    behind_or_outside = np.array([[0.0, 0.0, 2.5], [0.0, 0.0, -1.0], [5.0, 0.0, 1.0], [-0.85, 0.0, 1.7]])
    assert fs.contains(in_front).all() and not fs.contains(behind_or_outside).any()
    meta, arrays = fs.state_dict()
    again = FreeSpace(FreeSpaceConfig(), 0.1, 0.05)
    again.load_state_dict(meta, arrays)
    assert np.array_equal(again.contains(in_front), fs.contains(in_front)) and len(again) == len(fs)
    capped = FreeSpace(FreeSpaceConfig(stride=8, max_cells=10), 0.1, 0.05)
    capped.mark(depth, intr, np.eye(4))
    assert len(capped) == 10 and capped.refused > 0
    endless = depth.copy()
    endless[4::16] = np.inf  # every other sampled row: raw depth with no bound (callers pass cleaned
    # depth): those rays mark nothing
    inf_marked = FreeSpace(FreeSpaceConfig(stride=8), 0.1, 0.05)
    inf_marked.mark(endless, intr, np.eye(4))
    assert 0 < len(inf_marked) <= len(fs) and not inf_marked.contains(behind_or_outside).any()


def test_signed_distance_and_slice_on_a_mapped_scene(tiny_scene):
    seq = ReplicaSequence(tiny_scene)
    m = MapEngine(MapSettings(mapper=MapperConfig(device="cpu", rays_per_iteration=512)))
    for i in range(0, len(seq), 4):
        m.process(seq[i])
    view = m.view().frozen()
    f = seq[len(seq) // 2]  # seen by the frames around it (the first frame's edges are seen once)
    from h3edge.geometry.camera import backproject

    surface = backproject(f.depth, f.intrinsics, f.pose).reshape(-1, 3)[f.depth.reshape(-1) > 0][::11]
    ray = f.pose[:3, 2]
    s = signed_distance(view, np.concatenate([surface, surface - 0.03 * ray, surface + 0.5 * ray]), gradient=True)
    n = len(surface)
    on, front = s.state[:n], s.state[n:2 * n]
    assert (on == NEAR).mean() > 0.9 and np.nanmedian(np.abs(s.sdf[:n][on == NEAR])) < 0.015
    # 3 cm in front along the camera axis: positive; 50 cm behind the surface: never free
    assert np.nanmedian(s.sdf[n:2 * n][front == NEAR]) > 0.005
    assert not (s.state[2 * n:] == FREE).any()
    assert set(np.unique(s.state[2 * n:])) <= {UNKNOWN, INSIDE, NEAR}
    sl = distance_slice(view, float(f.pose[2, 3]), (-4.0, -4.0), (4.0, 4.0), 0.1)
    occ, dist = sl.occupancy, sl.distance
    assert occ.shape == (80, 80) and {-1, 0} <= set(np.unique(occ)) <= {-1, 0, 100}
    assert np.isnan(dist[occ == -1]).all() and (dist[occ == 100] == 0).all()
    meta, arrays = m.state_dict()
    r = MapEngine.from_state_dict(m.settings, meta, arrays)
    assert len(r.free_space) == len(m.free_space) > 0
    # the live view's block meshes tile the whole mesh
    from h3edge.mapping.voxels import unpack

    blocks = np.unique(np.floor_divide(unpack(view.voxels.voxel_keys), 4), axis=0)
    parts = view.block_meshes(blocks, 4, resolution=2)
    whole = view.mesh(2)
    assert len(blocks) > 4 and sum(len(p.faces) for p in parts) == len(whole.faces)
