"""Typed query requests, parsed and bounded at the edge: a mesh or render request arrives as a
JSON object (plus selector parameters for the mesh) and leaves as a dataclass the service can use
without further checks; anything malformed or over the service's caps is a :class:`QueryError`
(an error reply)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from h3edge.errors import QueryError
from h3edge.geometry.camera import Intrinsics
from h3edge.io.protocol import MAX_SIDE, ProtocolError, pose_from_json

MESH_FORMATS = {"ply": "ply", "glb": "gltf-binary", "obj": "obj"}  # format -> model/<mime subtype>


def _fields(request: object, allowed: set[str], what: str) -> dict:
    if not isinstance(request, dict):
        raise QueryError(f"{what} request must be a JSON object")
    unknown = set(request) - allowed
    if unknown:
        raise QueryError(f"{what} request: unknown field(s) {', '.join(sorted(unknown))}")
    return request


@dataclass(frozen=True)
class MeshRequest:
    format: str  # ply | glb | obj
    resolution: int  # marching-cubes cells per voxel edge
    aabb: np.ndarray | None  # (2, 3) metres, min < max; None: the whole map

    @classmethod
    def parse(cls, request: dict, default_resolution: int, max_resolution: int) -> MeshRequest:
        """From ``{"format", "resolution", "aabb"}``; ``aabb`` may be a string ``x0,y0,z0,x1,y1,z1``
        and ``resolution`` a string (selector parameters)."""
        req = _fields(request, {"format", "resolution", "aabb"}, "mesh")
        fmt = str(req.get("format", "ply"))
        if fmt not in MESH_FORMATS:
            raise QueryError(f"format must be ply, glb or obj, got {fmt!r}")
        aabb = req.get("aabb")
        try:
            if isinstance(aabb, str):
                v = [float(x) for x in aabb.split(",")]
                if len(v) != 6:
                    raise ValueError("aabb needs 6 numbers")
                aabb = [v[:3], v[3:]]
            res = int(req["resolution"]) if "resolution" in req else default_resolution
        except (ValueError, TypeError, OverflowError) as e:
            raise QueryError(f"mesh request: {e}") from None
        if not 1 <= res <= max_resolution:
            raise QueryError(f"resolution must be 1..{max_resolution} cells per voxel, got {res}")
        box = None
        if aabb is not None:
            try:
                box = np.asarray(aabb, np.float64)
            except (ValueError, TypeError):
                box = np.zeros(0)
            if box.shape != (2, 3) or not np.all(np.isfinite(box)) or np.any(box[0] >= box[1]):
                raise QueryError("aabb must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max")
        return cls(fmt, res, box)


@dataclass(frozen=True)
class RenderRequest:
    intrinsics: Intrinsics
    pose: np.ndarray  # camera-to-world 4x4
    raw: bool  # raw_rgb8 + raw_f32 metres instead of PNG + png16 millimetres

    @classmethod
    def parse(cls, request: dict, max_pixels: int) -> RenderRequest:
        """From ``{"pose", "width", "height", "intrinsics" | "fov_deg", "raw"}``, at most
        ``max_pixels`` pixels and ``MAX_SIDE`` on a side."""
        req = _fields(request, {"pose", "width", "height", "intrinsics", "fov_deg", "raw"}, "render")
        try:
            w, h = int(req.get("width", 320)), int(req.get("height", 240))
        except (TypeError, ValueError, OverflowError):
            raise QueryError("width and height must be integers") from None
        if not (0 < w <= MAX_SIDE and 0 < h <= MAX_SIDE):
            raise QueryError(f"width and height must be in 1..{MAX_SIDE}, got {w}x{h}")
        if w * h > max_pixels:
            raise QueryError(f"{w}x{h} = {w * h} pixels exceeds this service's cap of {max_pixels}")
        if "pose" not in req or not isinstance(req["pose"], dict):
            raise QueryError('render request needs "pose": {"t": [...], "q": [x, y, z, w]} or {"matrix": [16]}')
        try:
            pose = pose_from_json(req["pose"], "pose")
            if "intrinsics" in req:
                k = req["intrinsics"]
                intr = Intrinsics(w, h, float(k["fx"]), float(k["fy"]), float(k["cx"]), float(k["cy"]))
            else:
                fov = float(req.get("fov_deg", 80.0))
                if not 1.0 <= fov <= 170.0:
                    raise QueryError("fov_deg must be in [1, 170]")
                f = (w / 2) / np.tan(np.radians(fov) / 2)
                intr = Intrinsics(w, h, f, f, w / 2, h / 2)
        except (ProtocolError, KeyError, TypeError, ValueError) as e:
            raise QueryError(f"render request: {e}") from None
        return cls(intr, pose, bool(req.get("raw", False)))
