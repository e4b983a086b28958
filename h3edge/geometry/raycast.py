"""CPU mesh renderer: ray casting of a triangle mesh through pixel centres (Open3D).

One job: given a mesh, a pose and intrinsics, return z-depth, the hit triangle and barycentrics
per pixel, and shade them from vertex colours or a mip-mapped texture atlas. The simulator draws
its frames with it and evaluation renders GT / reconstructed meshes with it, so both share the
pixel convention of :mod:`h3edge.geometry.camera`.

The ray casting itself is Open3D's ``RaycastingScene`` (Embree inside, wheels for linux x86-64
and aarch64), imported only when a :class:`MeshRaycaster` is built: the service and the query
client never load it. It comes with the ``eval`` extra (``pip install 'h3edge[eval]'``).
Measured against the embreex binding it replaced: research/bench_raycast.md (the one-off script
that measured it, ``benchmarks/raycast.py``, is in git history).
"""

from __future__ import annotations

import ctypes
import os
from dataclasses import dataclass

import cv2
import numpy as np

from h3edge.geometry.camera import Intrinsics, pixel_rays_camera

INSTALL_HINT = "install the 'eval' extra: pip install 'h3edge[eval]' (Open3D)"


def import_open3d():
    """Import Open3D, or raise ImportError naming the extra to install.

    Open3D's x86-64 CPU wheel links ``libusb-1.0.so.0``; on machines without the system library the
    ``libusb-package`` wheel (part of the extra there) provides it and is loaded first. On a Jetson
    JetPack ships libusb.
    """
    try:
        import libusb_package

        ctypes.CDLL(os.path.join(os.path.dirname(libusb_package.__file__), "libusb-1.0.so"), mode=ctypes.RTLD_GLOBAL)
    except (ImportError, OSError):
        pass
    try:
        import open3d
    except ImportError as e:
        raise ImportError(f"Open3D is not importable ({e}); {INSTALL_HINT}") from e
    return open3d


@dataclass
class Hits:
    """Per-pixel ray hits, each array (H, W). ``prim`` is -1 and ``depth`` 0 where the ray missed."""

    depth: np.ndarray  # float32 camera z-depth in metres
    prim: np.ndarray  # int32 triangle index
    bary_u: np.ndarray  # float32 weight of the triangle's 2nd vertex
    bary_v: np.ndarray  # float32 weight of the triangle's 3rd vertex
    cos_incidence: np.ndarray  # float32 |cos| between the ray and the face normal (0 on a miss)

    @property
    def valid(self) -> np.ndarray:
        return self.prim >= 0


class MeshRaycaster:
    """Ray-casting scene over one triangle mesh (vertices (V, 3), faces (F, 3)).

    ``threads`` caps Open3D's worker threads (0 or None: all cores).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, threads: int | None = None):
        vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        faces = np.ascontiguousarray(faces, dtype=np.int32)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"expected vertices (V, 3) and faces (F, 3), got {vertices.shape}, {faces.shape}")
        if len(faces) == 0:
            raise ValueError("mesh has no faces")
        o3d = import_open3d()
        self._o3c = o3d.core
        self.vertices, self.faces = vertices, faces
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(faces.astype(np.uint32)))
        tri = vertices[faces].astype(np.float64)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.face_normals = (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)).astype(np.float32)
        self._threads = int(threads or 0)
        self._ray_cache: tuple[Intrinsics, np.ndarray] | None = None
        self._ray_norms = np.zeros(0, np.float32)

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> dict:
        """Cast rays (N, 3); returns 'tfar' (distance in units of |direction|, inf on a miss), 'primID'
        (int32, -1 on a miss) and the barycentric weights 'u', 'v' of the triangle's 2nd and 3rd vertex."""
        d = np.asarray(directions, dtype=np.float32)
        rays = np.empty((len(d), 6), np.float32)
        rays[:, :3] = np.broadcast_to(np.asarray(origins, np.float32), d.shape)
        rays[:, 3:] = d
        r = self._scene.cast_rays(self._o3c.Tensor(rays), nthreads=self._threads)
        prim = r["primitive_ids"].numpy().astype(np.int64)
        prim[prim == self._scene.INVALID_ID] = -1
        uv = r["primitive_uvs"].numpy()
        return {"tfar": r["t_hit"].numpy(), "primID": prim.astype(np.int32), "u": uv[:, 0], "v": uv[:, 1]}

    def _camera_rays(self, intr: Intrinsics) -> np.ndarray:
        if self._ray_cache is None or self._ray_cache[0] != intr:
            rays = pixel_rays_camera(intr).reshape(-1, 3)
            self._ray_cache = (intr, rays.astype(np.float32))
            self._ray_norms = np.linalg.norm(rays, axis=1).astype(np.float32)
        return self._ray_cache[1]

    def hits(self, intr: Intrinsics, c2w: np.ndarray) -> Hits:
        flat = self._camera_rays(intr) @ c2w[:3, :3].T.astype(np.float32)
        r = self.cast(c2w[:3, 3], flat)
        prim = r["primID"].astype(np.int32)
        hit = prim >= 0
        t = np.where(hit, r["tfar"], 0.0).astype(np.float32)
        cos = np.zeros(len(prim), np.float32)
        if hit.any():
            n = self.face_normals[prim[hit]]
            cos[hit] = np.abs((n * flat[hit]).sum(1)) / self._ray_norms[hit]
        shape = (intr.height, intr.width)
        return Hits(t.reshape(shape), prim.reshape(shape), r["u"].reshape(shape).astype(np.float32),
                    r["v"].reshape(shape).astype(np.float32), cos.reshape(shape))

    def render_depth(self, intr: Intrinsics, c2w: np.ndarray) -> np.ndarray:
        """Z-depth image (H, W) float32 in metres, 0 where nothing is hit."""
        return self.hits(intr, c2w).depth

    def interpolate(self, hits: Hits, per_vertex: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """Barycentric interpolation of a per-vertex attribute (V, C) at every hit, shape (H, W, C)."""
        out = np.full(hits.prim.shape + (per_vertex.shape[1],), fill, dtype=np.float32)
        m = hits.valid
        f = self.faces[hits.prim[m]]
        u, v = hits.bary_u[m][:, None], hits.bary_v[m][:, None]
        a = per_vertex.astype(np.float32)
        out[m] = (1 - u - v) * a[f[:, 0]] + u * a[f[:, 1]] + v * a[f[:, 2]]
        return out

    def render_vertex_colors(self, intr: Intrinsics, c2w: np.ndarray, colors: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray]:
        """Colour (H, W, 3) uint8 from per-vertex RGB(A) uint8 colours, and z-depth (H, W)."""
        h = self.hits(intr, c2w)
        rgb = self.interpolate(h, colors[:, :3].astype(np.float32))
        return np.clip(np.rint(rgb), 0, 255).astype(np.uint8), h.depth


@dataclass
class TextureAtlas:
    """Mip-mapped RGB texture atlas with per-face texture coordinates.

    ``levels[k]`` is the atlas at 1/2^k resolution (uint8, Hk x Wk x 3). ``face_uv`` holds, per
    face and corner, level-0 texel coordinates (x right, y down, texel centres at +0.5);
    ``face_texel`` the size of one level-0 texel in metres. Every face's atlas cell must carry a
    replicated border of >= 2^(levels-1) texels, so bilinear filtering never bleeds across
    surfaces at any level.
    """

    levels: list[np.ndarray]
    face_uv: np.ndarray  # (F, 3, 2) float32
    face_texel: np.ndarray  # (F,) float32

    def sample(self, hits: Hits, intr: Intrinsics) -> np.ndarray:
        """Trilinearly filtered colour (H, W, 3) float32 in [0, 255] at every hit (0 elsewhere)."""
        valid = hits.valid
        prim = np.where(valid, hits.prim, 0)
        u, v = hits.bary_u[..., None], hits.bary_v[..., None]
        uv = self.face_uv[prim]  # (H, W, 3, 2)
        p = uv[..., 0, :] + u * (uv[..., 1, :] - uv[..., 0, :]) + v * (uv[..., 2, :] - uv[..., 0, :])
        # Pixel footprint on the surface, in level-0 texels, picks a continuous mip level.
        f = np.float32(0.5 * (intr.fx + intr.fy))
        footprint = hits.depth / (f * np.maximum(hits.cos_incidence, np.float32(0.2)) * self.face_texel[prim])
        lod = np.clip(np.log2(np.maximum(footprint, np.float32(1.0))), 0, len(self.levels) - 1)
        out = np.zeros(hits.prim.shape + (3,), np.float32)
        for level, img in enumerate(self.levels):
            w = np.clip(1.0 - np.abs(lod - level), 0.0, 1.0) * valid  # trilinear weight of this level
            if not w.any():
                continue
            # Texel centres on integers, as cv2.remap expects. No clamping is needed: every atlas
            # cell has >= 1 texel of replicated border at the coarsest level (class docstring).
            q = p * np.float32(0.5 ** level) - np.float32(0.5)
            col = cv2.remap(img, q[..., 0], q[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            out += w[..., None] * col
        return out
