"""Depth from its own camera registered into the colour camera: what a driver's "aligned depth"
topic does, for recordings and robots that publish depth as the depth camera measured it.

Each valid depth pixel is back-projected at its depth (depth camera intrinsics), moved into the
colour camera's frame (``color_from_depth``: the depth camera's optical frame in the colour
camera's optical frame, 4x4, metres) and projected with the colour intrinsics. A depth pixel covers
a rectangle of colour pixels (its two opposite corners projected at its depth, as librealsense's
``align`` does), so a depth camera coarser than the colour camera leaves no gaps; where several
depth pixels land on one colour pixel the nearest wins (a z-buffer: the foreground occludes).
Colour pixels no depth pixel reaches read 0 (invalid), as do points behind the colour camera.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from h3edge.geometry.camera import Intrinsics, rigid_error

MAX_SPLAT_PX = 8  # colour pixels a side one depth pixel may cover (a grazing or very near point covers no more)


@nb.njit(cache=True, nogil=True)
def _register(depth, dfx, dfy, dcx, dcy, rot, trans, cfx, cfy, ccx, ccy, out):
    h, w = depth.shape
    oh, ow = out.shape
    for v in range(h):
        for u in range(w):
            z = depth[v, u]
            if not (z > 0.0) or not np.isfinite(z):
                continue
            # the pixel's two opposite corners at its depth, in the colour camera
            lo_u, lo_v, hi_u, hi_v = np.inf, np.inf, -np.inf, -np.inf
            zc_min = np.inf
            for k in range(2):
                x = (u + k - dcx) / dfx * z
                y = (v + k - dcy) / dfy * z
                pc0 = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z + trans[0]
                pc1 = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z + trans[1]
                pc2 = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z + trans[2]
                if not pc2 > 1e-6:
                    zc_min = -1.0
                    break
                pu = cfx * pc0 / pc2 + ccx
                pv = cfy * pc1 / pc2 + ccy
                lo_u, hi_u = min(lo_u, pu), max(hi_u, pu)
                lo_v, hi_v = min(lo_v, pv), max(hi_v, pv)
                zc_min = min(zc_min, pc2)
            if zc_min <= 0.0:
                continue
            # the pixel centre's depth in the colour camera
            x = (u + 0.5 - dcx) / dfx * z
            y = (v + 0.5 - dcy) / dfy * z
            zc = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z + trans[2]
            u0, u1 = int(np.floor(lo_u + 0.5)), int(np.floor(hi_u - 0.5))
            v0, v1 = int(np.floor(lo_v + 0.5)), int(np.floor(hi_v - 0.5))
            if u1 < u0:  # narrower than a colour pixel: the one its centre falls in
                u0 = u1 = int(np.floor(0.5 * (lo_u + hi_u)))
            if v1 < v0:
                v0 = v1 = int(np.floor(0.5 * (lo_v + hi_v)))
            if u1 - u0 >= MAX_SPLAT_PX or v1 - v0 >= MAX_SPLAT_PX:
                continue
            for b in range(max(v0, 0), min(v1, oh - 1) + 1):
                for a in range(max(u0, 0), min(u1, ow - 1) + 1):
                    if out[b, a] == 0.0 or zc < out[b, a]:
                        out[b, a] = zc


def register_depth(depth: np.ndarray, depth_intr: Intrinsics, color_intr: Intrinsics,
                   color_from_depth: np.ndarray) -> np.ndarray:
    """Depth (``depth_intr.height``, ``depth_intr.width``) float32 metres (0 / NaN = invalid) seen by
    the depth camera, as the colour camera would see it: float32 (``color_intr.height``,
    ``color_intr.width``) z-depths in the colour camera's frame, 0 where no depth pixel reaches.
    ``color_from_depth``: 4x4 rigid transform taking depth-camera optical coordinates (OpenCV: x
    right, y down, z forward) to colour-camera ones. ValueError on a depth image of another size
    than ``depth_intr`` or a transform that is not rigid."""
    depth = np.asarray(depth)
    if depth.shape != (depth_intr.height, depth_intr.width):
        raise ValueError(f"depth {depth.shape[1]}x{depth.shape[0]} does not match its camera info "
                         f"{depth_intr.width}x{depth_intr.height}")
    t = np.asarray(color_from_depth, np.float64)
    err = rigid_error(t)
    if err:
        raise ValueError(f"depth -> colour transform: {err}")
    out = np.zeros((color_intr.height, color_intr.width), np.float32)
    _register(np.ascontiguousarray(depth, np.float32), float(depth_intr.fx), float(depth_intr.fy),
              float(depth_intr.cx), float(depth_intr.cy), np.ascontiguousarray(t[:3, :3]),
              np.ascontiguousarray(t[:3, 3]), float(color_intr.fx), float(color_intr.fy), float(color_intr.cx),
              float(color_intr.cy), out)
    return out
