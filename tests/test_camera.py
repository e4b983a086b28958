import numpy as np
import pytest

from h3edge.geometry.camera import (
    Intrinsics,
    backproject,
    invert_pose,
    look_at,
    pixel_rays_camera,
    project,
    rigid_error,
)
from h3edge.geometry.poses import interpolate_pose, pose_from_tq

K = Intrinsics(8, 6, 10.0, 12.0, 4.0, 3.0)


def test_rays_go_through_pixel_centres():
    rays = pixel_rays_camera(K)
    # pixel (0, 0) is the square [0, 1)^2: its ray passes through (0.5, 0.5)
    assert rays[0, 0, 0] == pytest.approx((0.5 - 4.0) / 10.0)
    assert rays[0, 0, 1] == pytest.approx((0.5 - 3.0) / 12.0)
    # the principal point lies on the corner between the four central pixels
    assert rays[2, 3, 0] == pytest.approx(-rays[2, 4, 0])


@pytest.mark.parametrize("step", [2, 3, 4])
def test_strided_rays_are_the_full_tables_strided_pixels(step):
    full = pixel_rays_camera(K)
    assert np.array_equal(pixel_rays_camera(K, step), full[step // 2::step, step // 2::step])


def test_backproject_project_roundtrip():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 3.0, (K.height, K.width)).astype(np.float32)
    depth[0, 0] = 0
    T = look_at(np.array([1.0, 2.0, 1.5]), np.array([3.0, 0.0, 1.0]))
    pts = backproject(depth, K, T)
    assert np.isnan(pts[0, 0]).all()
    uv, z = project(pts.reshape(-1, 3)[1:], K, T)
    vv, uu = np.divmod(np.arange(1, K.width * K.height), K.width)
    assert np.allclose(uv[:, 0], uu + 0.5) and np.allclose(uv[:, 1], vv + 0.5)
    assert np.allclose(z, depth.reshape(-1)[1:], atol=1e-5)


def test_backproject_rejects_wrong_size():
    with pytest.raises(ValueError, match="does not match"):
        backproject(np.ones((5, 5), np.float32), K)


def test_scaled_intrinsics_keep_pixel_edges():
    half = Intrinsics(640, 480, 500.0, 500.0, 320.0, 240.0).scaled(320, 240)
    assert (half.fx, half.cx, half.cy) == (250.0, 160.0, 120.0)


def test_rigid_error_and_pose_helpers():
    T = look_at(np.zeros(3), np.array([1.0, 1.0, 0.0]))
    assert rigid_error(T) is None
    assert np.allclose(invert_pose(T) @ T, np.eye(4))
    bad = T.copy()
    bad[:3, :3] *= 1.1
    assert "orthonormal" in rigid_error(bad)
    nan = T.copy()
    nan[0, 3] = np.nan
    assert "non-finite" in rigid_error(nan)
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    assert "determinant" in rigid_error(mirror)


def test_look_at_axes():
    T = look_at(np.array([0.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]))
    assert np.allclose(T[:3, 2], [1, 0, 0])  # camera z forward
    assert np.allclose(T[:3, 1], [0, 0, -1])  # camera y down
    straight_down = look_at(np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, 0.0]))
    assert rigid_error(straight_down) is None


def test_pose_interpolation_slerp():
    a = pose_from_tq(np.zeros(3), np.array([0, 0, 0, 1.0]))
    b = pose_from_tq(np.array([2.0, 0, 0]), np.array([0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)]))  # 90 deg about z
    m = interpolate_pose(a, b, 0.5)
    assert np.allclose(m[:3, 3], [1, 0, 0])
    ang = np.degrees(np.arccos((np.trace(m[:3, :3]) - 1) / 2))
    assert ang == pytest.approx(45.0)
    with pytest.raises(ValueError):
        pose_from_tq(np.zeros(3), np.zeros(4))


def test_intrinsics_must_describe_a_pinhole_camera():
    """Issue [4/5] 8: fx = 1e-6 or cx = 1e300 made rays of astronomical length (an overflow deep in
    integration); the constructor refuses them with the reason, and real cameras pass."""
    Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)  # Kinect
    Intrinsics(1280, 720, 390.0, 390.0, 640.0, 360.0)  # a wide RealSense depth camera
    Intrinsics(8, 6, 6.0, 6.0, 4.0, 3.0)
    for fx, cx in ((1e-300, 320.0), (1e-6, 320.0), (10.0, 320.0)):
        with pytest.raises(ValueError, match="degrees off the optical axis"):
            Intrinsics(640, 480, fx, 525.0, cx, 240.0)
    for cx in (1e300, -1e4, 2000.0):
        with pytest.raises(ValueError, match="principal point"):
            Intrinsics(640, 480, 525.0, 525.0, cx, 240.0)


def test_a_field_of_view_under_a_degree_is_no_camera():
    Intrinsics(640, 480, 20000.0, 20000.0, 320.0, 240.0)  # 1.4 degrees vertically: a long telephoto
    for fx in (1e6, 1e9, 1e300):
        with pytest.raises(ValueError, match="field of view"):
            Intrinsics(640, 480, fx, fx, 320.0, 240.0)
