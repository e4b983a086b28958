"""Mesh culling before Accuracy / Completion, as ESLAM evaluates.

A vertex is seen when, in at least one input view, it projects inside the image in front of the
camera and is not occluded: the mesh's own rendered depth at its pixel is no closer than the
vertex by more than ``eps``. A face survives only when all three of its vertices are seen
(ESLAM's rule), so faces outside every frustum or occluded in every view go.
"""

from __future__ import annotations

import numpy as np
import trimesh

from h3edge.geometry.camera import Intrinsics, project
from h3edge.geometry.raycast import MeshRaycaster


def visible_vertices(mesh: trimesh.Trimesh, poses: np.ndarray, intr: Intrinsics, eps: float = 0.03,
                     max_views: int = 60, render_scale: float = 0.5) -> np.ndarray:
    """Boolean (V,) mask of vertices seen unoccluded in at least one of ``poses``.

    At most ``max_views`` poses are used (evenly spread); occlusion depth is rendered at
    ``render_scale`` of the image size, which is plenty for a 3 cm test.
    """
    if len(poses) > max_views:
        poses = poses[np.linspace(0, len(poses) - 1, max_views).round().astype(int)]
    small = intr.scaled(max(8, int(intr.width * render_scale)), max(8, int(intr.height * render_scale)))
    rc = MeshRaycaster(mesh.vertices, mesh.faces)
    verts = np.asarray(mesh.vertices, np.float64)
    seen = np.zeros(len(verts), bool)
    for T in poses:
        uv, z = project(verts, small, T)
        with np.errstate(invalid="ignore"):
            inside = (
                (z > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] < small.width) & (uv[:, 1] >= 0) & (uv[:, 1] < small.height)
            )
        if not inside.any():
            continue
        depth = rc.render_depth(small, T)
        ui = uv[inside, 0].astype(int)
        vi = uv[inside, 1].astype(int)
        d = depth[vi, ui]
        ok = (d == 0) | (d + eps >= z[inside])
        idx = np.flatnonzero(inside)[ok]
        seen[idx] = True
    return seen


def cull_mesh(mesh: trimesh.Trimesh, poses: np.ndarray, intr: Intrinsics, eps: float = 0.03,
              max_views: int = 60) -> trimesh.Trimesh:
    """Copy of ``mesh`` keeping only faces whose three vertices are seen (see module docstring)."""
    seen = visible_vertices(mesh, poses, intr, eps, max_views)
    keep = seen[mesh.faces].all(axis=1)
    out = mesh.copy()
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    return out
