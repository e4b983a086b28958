"""Pose utilities: quaternion <-> matrix, SLERP + linear interpolation of rigid transforms."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def pose_from_tq(t: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 pose from a translation and a quaternion in (x, y, z, w) order (TUM, ROS)."""
    q = np.asarray(q_xyzw, float)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"invalid quaternion {q.tolist()}")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / n).as_matrix()
    T[:3, 3] = t
    return T


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix (the inverse of :func:`pose_from_tq`'s)."""
    return Rotation.from_matrix(np.asarray(R, float)[:3, :3]).as_quat()


def interpolate_pose(a: np.ndarray, b: np.ndarray, alpha: float) -> np.ndarray:
    """Rigid pose a fraction ``alpha`` of the way from ``a`` to ``b`` (SLERP rotation, linear translation)."""
    rots = Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]]))
    T = np.eye(4)
    T[:3, :3] = Slerp([0.0, 1.0], rots)([alpha]).as_matrix()[0]
    T[:3, 3] = (1 - alpha) * a[:3, 3] + alpha * b[:3, 3]
    return T
