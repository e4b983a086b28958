"""Test-only helpers: rays through chosen pixels of a frame, voxels near an analytic surface."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from h3edge.geometry.camera import pixel_rays_camera
from h3edge.mapping.mesh import SdfFn
from h3edge.mapping.trainer import RayBatch
from h3edge.mapping.trilinear import CORNERS
from h3edge.mapping.voxels import pack


def rays_from_frame(frame, pixels: torch.Tensor, device="cpu") -> RayBatch:
    """Rays through the given flat pixel indices of a :class:`~h3edge.io.sequence.Frame`."""
    intr = frame.intrinsics
    pix = pixels.cpu().numpy()
    cam = pixel_rays_camera(intr).reshape(-1, 3)[pix]
    R = frame.pose[:3, :3]
    dirs = torch.from_numpy((cam @ R.T).astype("float32"))
    o = torch.from_numpy(frame.pose[:3, 3].astype("float32")).expand(len(pix), 3)
    depth = torch.from_numpy(frame.depth.reshape(-1)[pix].astype("float32"))
    color = torch.from_numpy(frame.color.reshape(-1, 3)[pix].astype("float32") / 255.0)
    return RayBatch(o.to(device), dirs.to(device), depth.to(device), color.to(device))


def voxels_near_surface(sdf_fn: SdfFn, bound: np.ndarray, voxel_size: float, margin: float) -> np.ndarray:
    """Keys of voxels in ``bound`` whose corners' |SDF| (metres) stays under ``margin`` somewhere:
    analytic test scenes."""
    lo = np.floor(bound[0] / voxel_size).astype(int)
    hi = np.ceil(bound[1] / voxel_size).astype(int)
    ijk = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), -1).reshape(-1, 3)
    corners = (ijk[:, None, :] + CORNERS[None]) * voxel_size
    d = sdf_fn(corners.reshape(-1, 3)).reshape(-1, 8)
    near = (d.min(1) < margin) & (d.max(1) > -margin)
    return np.sort(pack(ijk[near]))


# The departures from the paper every device profile ships (D0-2..D0-7 and D53-1), which were the
# dataclass defaults before the defaults became the paper's values (issue [2/5]): tests of those
# fixes build small settings with them on.
SHIPPED_FIXES = {
    "mapper": {"edge_radius": 2, "edge_rays": 0.125, "edge_rays_near_too": True, "mesh_min_support": 0.25,
               "train_between_frames": True},
    "voxels": {"prior_clamp": 1.0, "observed_behind": 0.1},
    "train": {"free_in_voxels": False, "color_weight_floor": 0.001},
    "texture": {"scaling_everywhere": True, "anchor_scale": 2.0},
}


def with_shipped_fixes(settings, **tables):
    """``settings`` (a MapSettings) with :data:`SHIPPED_FIXES` on; ``tables``: section name -> dict
    of further fields to set there (e.g. ``mapper={"train_between_frames": False}``)."""
    out = settings
    for table in set(SHIPPED_FIXES) | set(tables):
        values = {**SHIPPED_FIXES.get(table, {}), **tables.get(table, {})}
        out = dataclasses.replace(out, **{table: dataclasses.replace(getattr(out, table), **values)})
    return out
