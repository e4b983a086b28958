"""Readers: the own format (from the simulator), Replica-layout errors, TUM association."""

import json
import shutil

import cv2
import numpy as np
import pytest

from h3edge.geometry.camera import look_at
from h3edge.geometry.poses import interpolate_pose
from h3edge.io import DatasetError, open_sequence
from h3edge.io.replica import ReplicaSequence
from h3edge.io.sequence import write_depth
from h3edge.io.tum import TUMSequence


def test_own_format_roundtrip(tiny_scene, tiny_spec):
    seq = open_sequence(tiny_scene)
    assert isinstance(seq, ReplicaSequence)
    assert len(seq) == tiny_spec.frames
    f = seq[3]
    assert f.color.shape == (tiny_spec.height, tiny_spec.width, 3) and f.color.dtype == np.uint8
    assert f.depth.dtype == np.float32 and f.depth.shape == (tiny_spec.height, tiny_spec.width)
    assert f.timestamp == pytest.approx(3 / tiny_spec.fps)
    assert seq.gt_mesh_path is not None
    held = seq.heldout
    assert held is not None and len(held) == len(range(0, tiny_spec.frames - 1, tiny_spec.heldout_every))
    assert seq[-1].index == tiny_spec.frames - 1
    with pytest.raises(IndexError):
        seq[tiny_spec.frames]


@pytest.fixture
def scene_copy(tiny_scene, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(tiny_scene, dst, ignore=shutil.ignore_patterns("heldout", "gt_mesh.ply"))
    return dst


def test_missing_depth_file_names_it(scene_copy):
    (scene_copy / "results" / "depth000002.png").unlink()
    seq = open_sequence(scene_copy)
    with pytest.raises(DatasetError, match="depth000002.png: depth image missing"):
        seq[2]


def test_size_mismatch_names_file(scene_copy):
    p = scene_copy / "results" / "depth000001.png"
    write_depth(p, np.ones((10, 10), np.float32), 6553.5)
    with pytest.raises(DatasetError, match=r"depth000001.png: depth is 10x10"):
        open_sequence(scene_copy)[1]


def test_corrupt_image_names_file(scene_copy):
    (scene_copy / "results" / "frame000004.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(DatasetError, match="frame000004.jpg: cannot decode"):
        open_sequence(scene_copy)[4]


@pytest.mark.parametrize("row, msg", [
    ("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0", "has 15 numbers"),
    ("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 x", "not numeric"),
    ("2 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1", "not a rigid transform"),
    ("1 0 0 0 0 1 0 0 0 0 1 nan 0 0 0 1", "not a rigid transform"),
])
def test_bad_pose_row_names_file_and_line(scene_copy, row, msg):
    traj = scene_copy / "traj.txt"
    lines = traj.read_text().splitlines()
    lines[6] = row
    traj.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=rf"traj.txt:7: .*{msg}"):
        open_sequence(scene_copy)


def test_too_few_pose_rows(scene_copy):
    traj = scene_copy / "traj.txt"
    traj.write_text("\n".join(traj.read_text().splitlines()[:5]) + "\n")
    with pytest.raises(DatasetError, match="traj.txt: 5 pose rows"):
        open_sequence(scene_copy)


def test_bad_intrinsics_named(scene_copy):
    (scene_copy / "intrinsics.json").write_text(json.dumps({"width": 160}))
    with pytest.raises(DatasetError, match="intrinsics.json: intrinsics field missing"):
        open_sequence(scene_copy)


def test_not_a_dataset(tmp_path):
    with pytest.raises(DatasetError, match="not a dataset"):
        open_sequence(tmp_path)


def _write_tum(root, rgb_t, depth_t, gt_rows):
    root.mkdir()
    (root / "rgb").mkdir()
    (root / "depth").mkdir()
    img = np.zeros((480, 640, 3), np.uint8)
    dep = np.full((480, 640), 2.0, np.float32)
    with open(root / "rgb.txt", "w") as f:
        f.write("# colour images\n")
        for t in rgb_t:
            cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), img)
            f.write(f"{t:.6f} rgb/{t:.6f}.png\n")
    with open(root / "depth.txt", "w") as f:
        for t in depth_t:
            write_depth(root / "depth" / f"{t:.6f}.png", dep, 5000.0)
            f.write(f"{t:.6f} depth/{t:.6f}.png\n")
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(gt_rows))


def _tq_row(t, T):
    from scipy.spatial.transform import Rotation
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return f"{t:.4f} " + " ".join(f"{v:.9f}" for v in [*T[:3, 3], *q]) + "\n"


def test_tum_association_and_interpolation(tmp_path):
    A = look_at(np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 1.0]))
    B = look_at(np.array([1.0, 0.0, 1.0]), np.array([1.0, 1.0, 1.0]))
    root = tmp_path / "rgbd_dataset_freiburg1_test"
    # frame 1.045 has depth 1.055 (10 ms away) and lies midway between GT rows 1.0 and 1.09;
    # frame 2.00 has no depth within 20 ms; frame 3.00 is past the GT's end
    _write_tum(root, [1.0, 1.045, 2.0, 3.0], [1.001, 1.055, 2.5, 3.0],
               [_tq_row(1.0, A), _tq_row(1.09, B), _tq_row(2.05, B)])
    seq = TUMSequence(root)
    assert seq.intrinsics.fx == pytest.approx(517.3)
    assert len(seq) == 2 and seq.skipped == {"no_depth": 1, "no_pose": 1}
    assert np.allclose(seq.poses[0], A, atol=1e-6)
    assert np.allclose(seq.poses[1], interpolate_pose(A, B, 0.5), atol=1e-6)
    f = seq[1]
    assert f.timestamp == pytest.approx(1.045)
    assert np.allclose(f.depth, 2.0)


def test_tum_bad_gt_row(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg2_x"
    _write_tum(root, [1.0], [1.0], ["1.0 0 0 0 0 0 0 1\n", "1.1 0 0 0 0 0 0\n"])
    with pytest.raises(DatasetError, match="groundtruth.txt:3: expected 8 columns"):
        TUMSequence(root)


def test_tum_needs_intrinsics(tmp_path):
    root = tmp_path / "mystery"
    _write_tum(root, [1.0], [1.0], ["1.0 0 0 0 0 0 0 1\n"])
    with pytest.raises(DatasetError, match="no intrinsics.json"):
        TUMSequence(root)
