"""Pinhole camera model and the project's single pixel convention.

Convention (used by back-projection, rendering and evaluation alike): pixel (u, v) — column u,
row v, both integers starting at 0 — is the square [u, u+1) x [v, v+1) in image coordinates, and
its ray goes through the pixel *centre* (u + 0.5, v + 0.5):

    x_cam = ((u + 0.5) - cx) / fx * z,    y_cam = ((v + 0.5) - cy) / fy * z

Camera frame is OpenCV's (x right, y down, z forward); poses are camera-to-world 4x4 matrices.
A half-pixel slip alone costs ~0.2 cm Depth L1 on Replica, so nothing else in the package may
build rays or project points: call these functions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PIXEL_CENTER_OFFSET = 0.5
MAX_RAY_ANGLE_DEG = 85.0  # a pinhole image's edge rays: a 170-degree field of view at most
MIN_FIELD_OF_VIEW_DEG = 1.0  # across the image, each way: fx = 1e9 px would put every pixel on one ray


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics for an image of ``width`` x ``height`` pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(vals)) or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"invalid intrinsics fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}")
        # a pinhole camera: the principal point within an image size of the image, every pixel's ray
        # less than MAX_RAY_ANGLE_DEG off the optical axis (fx = 1e-6 or cx = 1e300 would make rays
        # of 1e300 m per metre of depth)
        if not (-self.width <= self.cx <= 2 * self.width and -self.height <= self.cy <= 2 * self.height):
            raise ValueError(f"principal point ({self.cx:g}, {self.cy:g}) is more than an image size outside the "
                             f"{self.width}x{self.height} image")
        reach = np.tan(np.radians(MAX_RAY_ANGLE_DEG))
        if max(abs(self.cx), abs(self.width - self.cx)) > reach * self.fx or \
                max(abs(self.cy), abs(self.height - self.cy)) > reach * self.fy:
            raise ValueError(f"focal lengths fx={self.fx:g} fy={self.fy:g} px put the {self.width}x{self.height} "
                             f"image's edge rays more than {MAX_RAY_ANGLE_DEG} degrees off the optical axis")
        narrowest = 2 * np.tan(np.radians(MIN_FIELD_OF_VIEW_DEG / 2))
        if self.width < narrowest * self.fx or self.height < narrowest * self.fy:
            raise ValueError(f"focal lengths fx={self.fx:g} fy={self.fy:g} px give the {self.width}x{self.height} "
                             f"image a field of view under {MIN_FIELD_OF_VIEW_DEG} degree")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, width: int, height: int) -> Intrinsics:
        """Intrinsics for the same camera resampled to ``width`` x ``height`` (pixel-area scaling).

        With pixel-centre rays, scaling maps pixel edges onto pixel edges, so cx, cy scale with
        the image size exactly as fx, fy do.
        """
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy)

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy}


def pixel_rays_camera(intr: Intrinsics, step: int = 1) -> np.ndarray:
    """Per-pixel ray directions in the camera frame with z = 1, shape (H, W, 3), float64; with
    ``step`` > 1 only every ``step``-th pixel of each axis from ``step // 2`` on, as
    ``image[step // 2::step, step // 2::step]`` picks them (without building the full table)."""
    u = np.arange(step // 2, intr.width, step, dtype=np.float64) + PIXEL_CENTER_OFFSET
    v = np.arange(step // 2, intr.height, step, dtype=np.float64) + PIXEL_CENTER_OFFSET
    uu, vv = np.meshgrid(u, v)
    return np.stack([(uu - intr.cx) / intr.fx, (vv - intr.cy) / intr.fy, np.ones_like(uu)], axis=-1)


def pixel_rays_world(intr: Intrinsics, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-frame ray origins (3,) and directions (H, W, 3) with unit camera-z component.

    A hit at ray parameter t has camera z-depth exactly t, since the camera-frame direction has z = 1.
    """
    d = pixel_rays_camera(intr) @ c2w[:3, :3].T
    return c2w[:3, 3].copy(), d


def pixels_to_camera(u: np.ndarray, v: np.ndarray, z: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Camera-frame points (..., 3) at z-depths ``z`` on the rays of integer pixels (u, v)."""
    x = (np.asarray(u, np.float64) + PIXEL_CENTER_OFFSET - intr.cx) / intr.fx
    y = (np.asarray(v, np.float64) + PIXEL_CENTER_OFFSET - intr.cy) / intr.fy
    z = np.asarray(z, np.float64)
    return np.stack([x * z, y * z, z], -1)


def backproject(depth: np.ndarray, intr: Intrinsics, c2w: np.ndarray | None = None) -> np.ndarray:
    """Back-project a depth image (metres, 0 = invalid) to points, shape (H, W, 3).

    Invalid pixels give NaN. With ``c2w`` the points are in the world frame, else the camera frame.
    """
    if depth.shape != (intr.height, intr.width):
        raise ValueError(f"depth shape {depth.shape} does not match intrinsics {intr.height}x{intr.width}")
    from h3edge.geometry._backproject_kernel import backproject_into

    pose = np.eye(4) if c2w is None else np.asarray(c2w, np.float64)
    out = np.empty((intr.height, intr.width, 3), np.float64)
    backproject_into(np.ascontiguousarray(depth), float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy),
                     PIXEL_CENTER_OFFSET, np.ascontiguousarray(pose[:3, :3]), np.ascontiguousarray(pose[:3, 3]), out)
    return out


def project(points_world: np.ndarray, intr: Intrinsics, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points (N, 3) into the image.

    Returns continuous pixel coordinates (N, 2) in the convention's frame — the pixel containing
    a point is ``floor(uv)`` — and camera z-depths (N,).
    """
    w2c = invert_pose(c2w)
    pc = points_world @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = pc[:, 0] / z * intr.fx + intr.cx
        v = pc[:, 1] / z * intr.fy + intr.cy
    return np.stack([u, v], axis=-1), z


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def rigid_error(T: np.ndarray) -> str | None:
    """Why ``T`` is not a finite rigid 4x4 transform, or None when it is one."""
    T = np.asarray(T)
    if T.shape != (4, 4):
        return f"shape {T.shape}, expected (4, 4)"
    if not np.all(np.isfinite(T)):
        return "non-finite entries"
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
        return f"last row {T[3].tolist()} is not [0, 0, 0, 1]"
    R = T[:3, :3]
    ortho = np.abs(R.T @ R - np.eye(3)).max()
    if ortho > 1e-3:
        return f"rotation is not orthonormal (max |R^T R - I| = {ortho:.2e})"
    det = np.linalg.det(R)
    if abs(det - 1.0) > 1e-3:
        return f"rotation determinant {det:.4f} != 1"
    return None


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """Camera-to-world pose (OpenCV camera axes) at ``eye`` looking at ``target`` with world ``up``."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:  # looking straight up/down: pick any horizontal x
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T
