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
    with pytest.raises(DatasetError, match="not registered to colour.*depth_to_color.*no /tf_static chain"):
        open_sequence(bag, cfg)  # neither extrinsics nor a /tf_static: refused, the way out named
    ok = write_rosbag(seq, tmp_path / "registered.mcap", cfg, "mcap", frames=3, depth_intrinsics=i)
    assert len(open_sequence(ok, cfg)) == 3


def test_depth_from_its_own_camera_is_registered_into_the_colour_camera(tiny_scene, tmp_path):
    """Issue [4/5] 14 and deliver 4: a ROS 1 recording of depth as a depth camera beside the colour
    camera measured it (its own focal length and principal point, 2.5 cm to the side, turned 2
    degrees) maps aligned with the depth -> colour extrinsics given, or read from the bag's
    /tf_static (a camera link to both optical frames): the frames' depth is the colour camera's
    depth within millimetres wherever the depth camera saw. A coarser depth camera (0.7x the pixels,
    0.6x the focal length) reads aligned too (the median), its splats constant across 1.7 colour
    pixels; ROS 1 and 2 bags."""
    from h3edge.geometry.camera import Intrinsics
    from h3edge.geometry.poses import pose_from_tq

    seq = ReplicaSequence(tiny_scene)
    i = seq[0].intrinsics
    q = np.array([0.0, np.sin(np.radians(1.0)), 0.0, np.cos(np.radians(1.0))])  # 2 degrees about y
    spec = "0.025 -0.004 0.002 " + " ".join(f"{v:.12f}" for v in q)
    extr = pose_from_tq(np.array([0.025, -0.004, 0.002]), q)
    beside = Intrinsics(i.width, i.height, i.fx * 1.02, i.fy * 1.02, i.cx + 1.5, i.cy - 2.0)
    coarse = Intrinsics(int(i.width * 0.7), int(i.height * 0.7), i.fx * 0.6, i.fy * 0.6, i.cx * 0.7 + 1.5,
                        i.cy * 0.7 - 2.0)
    for name, cam, within_2cm, storage in (("beside.bag", beside, 0.98, "ros1"), ("coarse.mcap", coarse, 0.5, "mcap")):
        bag = write_rosbag(seq, tmp_path / name, RosConfig(base_to_camera=EXTRINSIC), storage, frames=2,
                           depth_intrinsics=cam, depth_to_color=extr)
        by_flag = open_sequence(bag, RosConfig(base_to_camera=EXTRINSIC, depth_to_color=spec,  # depth: its own frame
                                               camera_frame="camera_color_optical_frame"))
        by_tf = open_sequence(bag, RosConfig(base_to_camera=EXTRINSIC))  # the bag's /tf_static
        for k in range(2):
            got, want = by_flag[k].depth, seq[k].depth
            assert np.array_equal(by_tf[k].depth, got) and by_flag[k].intrinsics == i
            assert got.shape == want.shape
            both = (got > 0) & (want > 0)
            assert both.sum() > 0.5 * (want > 0).sum()
            err = np.abs(got[both] - want[both])
            assert np.median(err) < 0.002 and np.mean(err < 0.02) > within_2cm, name
    from h3edge.cli import main  # the same through the command line

    profile = Path(__file__).parent / "data" / "service-test.toml"
    rc = main(["map", str(bag), "--out", str(tmp_path / "run"), "--profile", str(profile), "--frames", "2",
               "--no-eval", "--base-to-camera", EXTRINSIC, "--depth-to-color", spec,
               "--depth-camera-info-topic", RosConfig().depth_camera_info_topic])
    assert rc == 0 and json.loads((tmp_path / "run" / "run.json").read_text())["stats"]["frames_mapped"] == 2
    with pytest.raises(ValueError, match="depth_to_color"):
        RosConfig(depth_to_color="0 0 0 0 0 0 0")


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
