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


def test_depth_registered_into_another_camera_lands_where_the_points_project():
    """A plane 2 m ahead seen by a coarser depth camera 5 cm to the left of the colour camera:
    every colour pixel it covers reads 2 m, the covered columns and rows are where the depth
    camera's view edges project, and nothing outside; a slanted plane reads its own depth at the
    pixel centres within what one depth pixel's splat spans; a non-rigid transform is refused."""
    from h3edge.geometry.registration import register_depth

    color = Intrinsics(640, 480, 613.0, 613.0, 320.0, 240.0)
    depth_cam = Intrinsics(424, 240, 390.0, 390.0, 212.0, 120.0)
    t = np.eye(4)
    t[0, 3] = 0.05  # the depth camera's origin in the colour camera
    out = register_depth(np.full((240, 424), 2.0, np.float32), depth_cam, color, t)
    assert out.shape == (480, 640) and np.all(np.isin(out, (0.0, 2.0)))
    cols, rows = np.flatnonzero((out > 0).any(0)), np.flatnonzero((out > 0).any(1))
    half_w, half_h = 212.0 / 390.0 * 2.0, 120.0 / 390.0 * 2.0  # m: the depth camera's half view at 2 m
    assert abs(cols.min() - (613.0 * (0.05 - half_w) / 2.0 + 320.0)) <= 1 and cols.max() == 639
    assert abs(rows.min() - (240.0 - 613.0 * half_h / 2.0)) <= 1
    assert abs(rows.max() - (240.0 + 613.0 * half_h / 2.0)) <= 1
    assert (out[rows.min() + 1:rows.max(), cols.min() + 1:] > 0).all()  # no gaps from the coarser camera
    # a plane z = 2 + 0.5 x (camera frame of the depth camera)
    u, v = np.meshgrid(np.arange(424) + 0.5, np.arange(240) + 0.5)
    xn = (u - 212.0) / 390.0
    z_d = (2.0 / (1.0 - 0.5 * xn)).astype(np.float32)
    slanted = register_depth(z_d, depth_cam, color, t)
    a, b = np.meshgrid(np.arange(640) + 0.5, np.arange(480) + 0.5)
    # the plane in the colour camera: z = 2 + 0.5 (x - 0.05), x = (a - cx) / fx * z
    z_c = (2.0 - 0.025) / (1.0 - 0.5 * (a - 320.0) / 613.0)
    hit = slanted > 0
    assert hit.mean() > 0.5
    # a splat holds its pixel centre's depth over up to 2 colour pixels, ~2 mm of this plane's depth each
    assert np.abs(slanted[hit] - z_c[hit]).max() < 0.006
    with pytest.raises(ValueError, match="transform"):
        register_depth(np.ones((240, 424), np.float32), depth_cam, color, np.diag([1.0, 1.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="camera info"):
        register_depth(np.ones((10, 10), np.float32), depth_cam, color, t)
