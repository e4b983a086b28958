"""Typed query requests, parsed and bounded at the edge: a mesh or render request arrives as a
JSON object (plus selector parameters for the mesh) and leaves as a dataclass the service can use
without further checks; anything malformed or over the service's caps is a :class:`QueryError`
(an error reply)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from h3edge.errors import QueryError
from h3edge.geometry.camera import Intrinsics
from h3edge.io.distance_types import slice_cells
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
            except (ValueError, TypeError, OverflowError):
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
        except (ProtocolError, KeyError, TypeError, ValueError, OverflowError) as e:
            raise QueryError(f"render request: {e}") from None
        return cls(intr, pose, bool(req.get("raw", False)))


def _flag(value) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.lower() in ("1", "true", "yes", "0", "false", "no"):
        return value.lower() in ("1", "true", "yes")
    raise QueryError(f"expected true or false, got {value!r}")


@dataclass(frozen=True)
class SdfRequest:
    points: np.ndarray  # float64 (N, 3) metres, finite
    gradient: bool

    @classmethod
    def parse(cls, request: dict, raw_points: bytes | None, max_points: int) -> SdfRequest:
        """From ``{"points": [[x, y, z], ...], "gradient"}`` or, for large batches, the points as raw
        little-endian float32 x, y, z triples in the payload (``gradient`` then a selector
        parameter); at most ``max_points``."""
        req = _fields(request, {"points", "gradient"}, "sdf")
        if raw_points is not None:
            if len(raw_points) % 12:
                raise QueryError(f"sdf payload of {len(raw_points)} bytes is not float32 x, y, z triples")
            if len(raw_points) // 12 > max_points:
                raise QueryError(f"{len(raw_points) // 12} points exceeds this service's cap of {max_points}")
            pts = np.frombuffer(raw_points, "<f4").reshape(-1, 3).astype(np.float64)
        else:
            raw = req.get("points")
            if not isinstance(raw, list) or len(raw) > max_points:
                raise QueryError(f'sdf request needs "points": a list of at most {max_points} [x, y, z]')
            if not all(isinstance(p, list) and len(p) == 3 and all(type(v) in (int, float) for v in p) for p in raw):
                raise QueryError("sdf points must be [x, y, z] triples of numbers (not strings, not flat lists)")
            try:
                pts = np.asarray(raw, np.float64).reshape(-1, 3) if raw else np.zeros((0, 3))
            except OverflowError:  # a JSON integer of hundreds of digits
                raise QueryError("sdf points must be finite coordinates within 1000 km") from None
        if len(pts) == 0:
            raise QueryError("sdf request has no points")
        if not np.isfinite(pts).all() or np.abs(pts).max() > 1e6:
            raise QueryError("sdf points must be finite coordinates within 1000 km")
        return cls(pts, _flag(req.get("gradient", False)))


@dataclass(frozen=True)
class SliceRequest:
    z: float  # m, the slice's height
    lo: tuple[float, float]  # (x, y) m
    hi: tuple[float, float]
    resolution: float  # m per cell

    @classmethod
    def parse(cls, request: dict, max_cells: int) -> SliceRequest:
        """From ``{"z", "aabb": "x0,y0,x1,y1" | [[x0, y0], [x1, y1]], "resolution"}`` (selector
        parameters or JSON); at most ``max_cells`` cells."""
        req = _fields(request, {"z", "aabb", "resolution"}, "slice")
        try:
            z = float(req["z"])
            res = float(req.get("resolution", 0.05))
            box = req["aabb"]
            v = [float(x) for x in box.split(",")] if isinstance(box, str) else [float(x) for p in box for x in p]
        except KeyError as e:
            raise QueryError(f"slice request needs {e.args[0]!r}") from None
        except (ValueError, TypeError, OverflowError):
            raise QueryError('slice needs numbers: "z", "resolution" and "aabb" x0,y0,x1,y1') from None
        if len(v) != 4 or not np.isfinite(v + [z, res]).all() or v[0] >= v[2] or v[1] >= v[3]:
            raise QueryError("slice aabb must be x0,y0,x1,y1 with x0 < x1 and y0 < y1")
        if not 0.005 <= res <= 10.0:
            raise QueryError(f"slice resolution must be 0.005..10 m, got {res:g}")
        cells = slice_cells((v[0], v[1]), (v[2], v[3]), res)  # a box of +-1e308 m: inf cells, refused below
        if not cells <= max_cells:
            raise QueryError(f"a slice of {cells:.4g} cells exceeds this service's cap of {max_cells}: a coarser "
                             "resolution or a smaller aabb")
        return cls(z, (v[0], v[1]), (v[2], v[3]), res)


@dataclass(frozen=True)
class NamedRequest:
    """``save`` / ``load`` / ``export``: an optional file name under the state directory."""

    name: str | None
    format: str  # export only: ply | glb | obj

    @classmethod
    def parse(cls, request: dict, what: str) -> NamedRequest:
        req = _fields(request, {"name", "format"} if what == "export" else {"name"}, what)
        name = req.get("name")
        if name is not None and not isinstance(name, str):
            raise QueryError(f"{what}: name must be a string")
        fmt = str(req.get("format", "ply"))
        if fmt not in MESH_FORMATS:
            raise QueryError(f"format must be ply, glb or obj, got {fmt!r}")
        if what == "export" and not name:
            raise QueryError("export needs a name")
        return cls(name, fmt)
