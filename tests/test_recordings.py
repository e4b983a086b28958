"""Recordings users have: rosbag2 (MCAP and sqlite3, written with rosbags) and ScanNet exports, read
back through the readers and mapped with ``h3edge map``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from h3edge.io import open_sequence
from h3edge.io.replica import ReplicaSequence
from h3edge.io.ros import RosConfig
from h3edge.io.rosbag import RosbagSequence, write_rosbag
from h3edge.io.scannet import ScanNetSequence, write_scannet
from h3edge.io.sequence import DatasetError

EXTRINSIC = "0.1 0.0 0.2 -0.5 0.5 -0.5 0.5"


@pytest.mark.parametrize("storage", ["mcap", "sqlite3", "ros1"])
def test_a_rosbag_reads_back_as_the_sequence_it_recorded(tiny_scene, tmp_path, storage):
    """ROS 2 bags and ROS 1 ``.bag`` files (issue [4/5] 13: read directly, ROS 1 field names)."""
    seq = ReplicaSequence(tiny_scene)
    cfg = RosConfig(base_to_camera=EXTRINSIC, world_frame="odom")
    bag = write_rosbag(seq, tmp_path / f"bag_{storage}{'.bag' if storage == 'ros1' else ''}", cfg, storage, rate=15.0)
    back = open_sequence(bag, cfg)
    assert isinstance(back, RosbagSequence) and len(back) == len(seq) and not back.skipped
    for i in (0, len(seq) - 1):
        a, b = seq[i], back[i]
        assert np.array_equal(a.color, b.color) and np.abs(a.depth - b.depth).max() < 6e-4
        assert np.allclose(a.pose, b.pose, atol=1e-6) and a.intrinsics == b.intrinsics
    assert np.isclose(back[1].timestamp - back[0].timestamp, 1 / 15.0)
    # the same bag with the wrong extrinsic gives other camera poses; without one it is refused
    other = open_sequence(bag, RosConfig(base_to_camera="identity"))
    assert not np.allclose(other.poses, back.poses, atol=1e-3)
    with pytest.raises(DatasetError, match="extrinsic"):
        open_sequence(bag, RosConfig())
    with pytest.raises(DatasetError, match="not in the bag"):
        open_sequence(bag, RosConfig(base_to_camera="identity", pose_topic="/tf"))


def test_a_bag_of_depth_not_registered_to_colour_is_refused(tiny_scene, tmp_path):
    """Issue [4/5] 14: a recording whose depth camera info differs from the colour camera's is refused
    with the reason, never mapped misaligned; the same depth camera info as colour's reads."""
    from h3edge.geometry.camera import Intrinsics

    seq = ReplicaSequence(tiny_scene)
    cfg = RosConfig(base_to_camera=EXTRINSIC)
    i = seq[0].intrinsics
    wide = Intrinsics(i.width, i.height, i.fx * 0.64, i.fy * 0.64, i.cx, i.cy)
    bag = write_rosbag(seq, tmp_path / "unregistered.bag", cfg, "ros1", frames=3, depth_intrinsics=wide)
    with pytest.raises(DatasetError, match="not registered to colour"):
        open_sequence(bag, cfg)
    ok = write_rosbag(seq, tmp_path / "registered.mcap", cfg, "mcap", frames=3, depth_intrinsics=i)
    assert len(open_sequence(ok, cfg)) == 3


def test_h3edge_map_maps_a_recorded_bag(tiny_scene, tmp_path):
    from h3edge.cli import main

    seq = ReplicaSequence(tiny_scene)
    bag = write_rosbag(seq, tmp_path / "bag", RosConfig(base_to_camera=EXTRINSIC), "mcap")
    out = tmp_path / "run"
    profile = Path(__file__).parent / "data" / "service-test.toml"
    rc = main(["map", str(bag), "--out", str(out), "--profile", str(profile), "--frames", "4", "--no-eval",
               "--base-to-camera", EXTRINSIC])
    assert rc == 0
    run = json.loads((out / "run.json").read_text())
    assert run["stats"]["frames_mapped"] == 4 and run["mesh_vertices"] > 0


def test_scannet_exports_resize_colour_and_skip_lost_poses(tiny_scene, tmp_path):
    seq = ReplicaSequence(tiny_scene)
    root = write_scannet(seq, tmp_path / "scene0000_00")
    (root / "pose" / "2.txt").write_text("-inf -inf -inf -inf\n" * 4)  # ScanNet's lost tracking
    sc = open_sequence(root)
    assert isinstance(sc, ScanNetSequence) and len(sc) == len(seq) - 1 and sc.skipped == {"invalid_pose": 1}
    f = sc[0]
    assert f.color.shape == (seq.intrinsics.height, seq.intrinsics.width, 3) and f.intrinsics == seq.intrinsics
    assert np.abs(f.color.astype(int) - seq[0].color.astype(int)).mean() < 6  # JPEG + resize round trip
    assert np.allclose(sc[2].pose, seq[3].pose)  # frame 2 left out
    from h3edge.mapping.engine import MapEngine, MapperConfig, MapSettings

    m = MapEngine(MapSettings(mapper=MapperConfig(device="cpu", rays_per_iteration=256)))
    assert all(m.process(sc[i]).mapped for i in range(2))
