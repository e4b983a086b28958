"""The fleet: every h3edge service on a zenoh network, found with one query and asked as one map.

Each service answers its status on ``h3edge/<map-id>/status``; one query on the wildcard key
``h3edge/*/status`` reaches them all (``QueryTarget.ALL``), and with no consolidation every service's
reply comes back, not one per key (:func:`fleet_status`). Zenoh routes it: through the routers of a
site, or peer to peer. Nothing is registered anywhere; a service is in the fleet while it answers.

One map over many (:class:`Fleet`, or the functions under it): each status says where its map's
world frame lies in the site frame the fleet shares (``[service] site_from_world``) and the box its
voxels fill. A request in the site frame goes to the maps it touches, moved into each map's frame,
all maps at once within one deadline, and the answers merge:

- signed distance (:func:`fleet_sdf`): the nearest surface any map knows (:func:`merge_distances`);
- a slice (:func:`fleet_slice`): the merged signed distance at the slice's cell centres, turned into
  occupancy and distance cell by cell as one map's slice is;
- a render (:func:`fleet_render`): every map seen from the camera, composited by depth;
- a mesh (:func:`fleet_mesh`): each map's mesh moved into the site frame, one per map.

A map that does not answer in time is named in the result (``missing``), not waited for; a map the
request does not come near is not asked (``skipped``).
"""

from __future__ import annotations

import concurrent.futures
import io
import json
import time
from dataclasses import dataclass, field

import numpy as np
import zenoh

from h3edge.geometry.camera import Intrinsics, invert_pose, rigid_error
from h3edge.io.distance_types import (
    FREE,
    INSIDE,
    NEAR,
    UNKNOWN,
    DistanceSlice,
    slice_cells,
    slice_from_sample,
    slice_grid,
)
from h3edge.io.protocol import Keys, decode_frame
from h3edge.serving.client import RemoteError, SessionUser, query, read_npz, render_request

FLEET_STATUS_KEY = "h3edge/*/status"


def fleet_status(session: zenoh.Session, timeout: float = 2.0) -> list[dict]:
    """The status of every service that answers within ``timeout`` seconds, one entry per map
    sorted by map id: ``{"map_id", "status"}`` (the service's status document), or ``{"map_id",
    "error"}`` for a reply that is not a status document, or one whose map id is not that of the key it
    came on (error replies are left out)."""
    entries: list[dict] = []
    replies = session.get(FLEET_STATUS_KEY, target=zenoh.QueryTarget.ALL,
                          consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout)
    for reply in replies:
        if reply.ok is None:
            continue  # an error reply names no map: nothing to list it under
        # a service answers on its own key, h3edge/<map-id>/status, and names its map in the document
        key = str(reply.ok.key_expr).split("/")
        keyed = key[1] if len(key) == 3 and key[0] == "h3edge" and key[2] == "status" and key[1] != "*" else None
        try:
            status = json.loads(reply.ok.payload.to_bytes())
            named = str(status["map_id"])
        except (ValueError, KeyError, TypeError) as e:
            entries.append({"map_id": f"? ({keyed or reply.ok.key_expr})",
                            "error": f"not a status document: {e!r}"[:200]})
            continue
        if keyed is not None and keyed != named:  # an answer under one map's key for another map: not listed as it
            entries.append({"map_id": f"? ({keyed})", "error": f"answered on {keyed}'s key for map {named[:64]!r}"})
            continue
        entries.append({"map_id": named, "status": status})
    return sorted(entries, key=lambda e: e["map_id"])


def format_fleet(entries: list[dict], seconds: float | None = None) -> str:
    """A table of :func:`fleet_status`'s entries: one row per map."""
    rows = ["| map | world frame | frames mapped | voxels | memory [MB] | last frame [s ago] | mapper |",
            "|---|---|---|---|---|---|---|"]
    for e in entries:
        st = e.get("status")
        if st is None:
            rows.append(f"| {e['map_id']} | {e['error']} | | | | | |")
            continue
        age = st.get("last_frame_age_s")
        rows.append(f"| {e['map_id']} | {st.get('world_frame', '?')} | {st['map'].get('frames_mapped') or 0} | "
                    f"{st['map'].get('voxels') or 0} | {st['memory']['total_bytes'] / 2**20:.0f} | "
                    f"{'-' if age is None else age} | {'alive' if st.get('mapper_alive') else 'stopped'} |")
    tail = f"\n{len(entries)} map(s)" + (f" answered in {seconds * 1000:.0f} ms" if seconds is not None else "")
    return "\n".join(rows) + tail


SDF_MARGIN = 0.5  # m: a map is asked about points this far outside its voxels' box too (its free space, votes)
SAME_SURFACE_M = 0.05  # m: near answers of several maps this close to the least are one surface: averaged


@dataclass
class FleetDistance:
    """Signed distance at site-frame points merged over the maps of a fleet."""

    sdf: np.ndarray
    """(N,) float32 metres: the nearest known surface (NaN where no map knows the point)"""
    state: np.ndarray
    """(N,) uint8: the answering map's state there (0 unknown, 1 free, 2 near, 3 inside)"""
    gradient: np.ndarray | None
    """(N, 3) float32 in the site frame, where asked"""
    source: np.ndarray
    """(N,) int: index into ``maps`` of the map whose answer was taken, the least where several near
    answers were averaged (-1: none)"""
    maps: list[str] = field(default_factory=list)
    """the maps that answered, in the order ``source`` indexes"""
    missing: dict[str, str] = field(default_factory=dict)
    """map id -> why it gave no answer (its deadline passed, an error reply)"""
    skipped: list[str] = field(default_factory=list)
    """maps the points do not come near (not asked)"""


def merge_distances(answers: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]], n: int,
                    same_surface: float = SAME_SURFACE_M
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """(sdf, state, gradient, source) over ``n`` points from each map's (sdf (n,), state (n,),
    gradient (n, 3) or None) in the site frame, per point:

    - inside where any map knows the point inside (the least such distance: a planner's
      conservative reading);
    - else, where some maps see a surface near it, the nearest surface: the near answers within
      ``same_surface`` metres of the least are one surface seen by several maps and are averaged,
      distance and gradient (as a map of all their frames would fuse them); farther ones are
      another surface behind it;
    - else free where any map knows it free (a lower bound: at least the truncation);
    - else unknown: NaN, -1.

    ``source``: the map of the least answer taken. ``gradient``: None unless every map gave one."""
    sdf = np.full(n, np.nan, np.float32)
    state = np.full(n, UNKNOWN, np.uint8)
    source = np.full(n, -1, np.int64)
    grad = np.full((n, 3), np.nan, np.float32) if answers and all(a[2] is not None for a in answers) else None
    if not answers:
        return sdf, state, grad, source
    d = np.stack([np.asarray(a[0], np.float64).reshape(n) for a in answers])
    st = np.stack([np.asarray(a[1]).reshape(n) for a in answers])
    known = (st != UNKNOWN) & np.isfinite(d)
    for kind in (INSIDE, NEAR, FREE):  # the first kind any map answers wins
        mask = known & (st == kind)
        open_ = (state == UNKNOWN) & mask.any(0)
        if not open_.any():
            continue
        masked = np.where(mask, d, np.inf)
        least = masked.argmin(0)
        cols = np.flatnonzero(open_)
        source[cols] = least[cols]
        state[cols] = kind
        if kind == NEAR:
            same = mask & (masked <= masked.min(0) + same_surface)
            sdf[cols] = (np.where(same, d, 0).sum(0) / np.maximum(same.sum(0), 1))[cols]
            if grad is not None:
                g = np.stack([np.asarray(a[2], np.float32).reshape(n, 3) for a in answers])  # (m, n, 3)
                with np.errstate(invalid="ignore"):
                    g_same = np.where(same[..., None], g, np.nan)
                    ok = np.isfinite(g_same).all(2) & same
                    mean = np.where(ok[..., None], g_same, 0).sum(0) / np.maximum(ok.sum(0), 1)[:, None]
                grad[cols] = np.where(ok.any(0)[:, None], mean, np.nan)[cols]
        else:
            sdf[cols] = masked.min(0)[cols]
            if grad is not None:
                g = np.stack([np.asarray(a[2], np.float32).reshape(n, 3) for a in answers])
                grad[cols] = g[least[cols], cols]
    return sdf, state, grad, source


@dataclass(frozen=True)
class _Place:
    """Where one map lies in the site frame: its id, site_from_world (4, 4), world_from_site and its
    voxels' box (2, 3) in its own world frame (None: no voxel yet)."""

    map_id: str
    site_from_world: np.ndarray
    world_from_site: np.ndarray
    box: np.ndarray | None

    def to_local(self, pts: np.ndarray) -> np.ndarray:
        """Site-frame points (N, 3) in this map's world frame."""
        return pts @ self.world_from_site[:3, :3].T + self.world_from_site[:3, 3]

    def site_box_corners(self) -> np.ndarray:
        """The 8 corners (8, 3) of the voxels' box in the site frame."""
        return _box_corners(self.box) @ self.site_from_world[:3, :3].T + self.site_from_world[:3, 3]


def _box_corners(box: np.ndarray) -> np.ndarray:
    """The 8 corners (8, 3) of an axis-aligned box (2, 3)."""
    return np.array([[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def _map_geometry(status: dict) -> tuple[np.ndarray, np.ndarray | None]:
    """A status's site_from_world (4, 4) (identity where it has none) and its map's voxel box (2, 3)
    in its world frame (None: no voxel yet); ValueError where either is malformed."""
    try:
        t = np.asarray(status.get("site_from_world") or np.eye(4), np.float64).reshape(4, 4)
        box = (status.get("map") or {}).get("bounds")
        box = None if box is None else np.asarray(box, np.float64).reshape(2, 3)
    except (TypeError, ValueError, AttributeError) as e:
        raise ValueError(f"malformed site_from_world or map bounds: {e}") from None
    err = rigid_error(t)
    if err or (box is not None and not np.isfinite(box).all()):
        raise ValueError(f"site_from_world is not a rigid transform ({err})" if err else "map bounds not finite")
    return t, box


def _places(entries: list[dict], missing: dict[str, str]) -> list[_Place]:
    """The maps of ``entries`` with their place in the site frame; a status whose site transform or
    box is malformed costs that map (named in ``missing``), not the request."""
    places = []
    for e in entries:
        st = e.get("status")
        if st is None:
            continue
        try:
            site_from_world, box = _map_geometry(st)
        except ValueError as err:
            missing[e["map_id"]] = str(err)[:200]
            continue
        places.append(_Place(e["map_id"], site_from_world, invert_pose(site_from_world), box))
    return places


def _ask_all(session: zenoh.Session, asks: dict[str, tuple[str, dict | bytes, str]], deadline: float,
             read, missing: dict[str, str]) -> dict[str, object]:
    """Each map's query ``(key, payload, params)`` at once, all before the monotonic ``deadline``;
    ``read(map_id, reply bytes)`` of each answer, by map id. A map with no answer by then, an error
    reply or an answer ``read`` refuses (ValueError, KeyError) is named in ``missing``."""
    out: dict[str, object] = {}
    if not asks:
        return out
    left = max(0.05, deadline - time.monotonic())
    with concurrent.futures.ThreadPoolExecutor(len(asks)) as pool:
        futures = {mid: pool.submit(query, session, key, payload, params, left)
                   for mid, (key, payload, params) in asks.items()}
        for mid, fut in futures.items():
            try:
                out[mid] = read(mid, fut.result())
            except (TimeoutError, RemoteError, OSError, ValueError, KeyError) as err:
                missing[mid] = f"{type(err).__name__}: {err}"[:200]
    return out


def _start(session: zenoh.Session, timeout: float, entries: list[dict] | None) -> tuple[float, list[_Place], dict]:
    """(deadline, places, missing) of a fan-out that may take ``timeout`` seconds in all."""
    deadline = time.monotonic() + timeout
    if entries is None:
        entries = fleet_status(session, timeout)
    missing: dict[str, str] = {}
    return deadline, _places(entries, missing), missing


def fleet_sdf(session: zenoh.Session, points: np.ndarray, timeout: float = 2.0, gradient: bool = False,
              margin: float = SDF_MARGIN, entries: list[dict] | None = None) -> FleetDistance:
    """Signed distance at ``points`` (N, 3) metres in the site frame over every map that answers
    :func:`fleet_status` (or the given ``entries``), all asked at once within ``timeout`` seconds in
    all (the status query included): each map whose voxel box, grown by ``margin`` metres, holds some
    of the points is sent those points in its world frame; the answers merge with
    :func:`merge_distances` (gradients rotated back into the site frame). ValueError on points that
    are not finite."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if not np.isfinite(pts).all():
        raise ValueError("fleet sdf points must be finite coordinates")
    deadline, places, missing = _start(session, timeout, entries)
    jobs, skipped = {}, []
    for pl in places:
        local = pl.to_local(pts)
        near = (np.flatnonzero(((local >= pl.box[0] - margin) & (local <= pl.box[1] + margin)).all(1))
                if pl.box is not None else np.zeros(0, np.int64))
        if len(near) == 0:
            skipped.append(pl.map_id)
            continue
        jobs[pl.map_id] = (near, local[near], pl.site_from_world)

    def read(mid: str, data: bytes):
        near, _, site_from_world = jobs[mid]
        a = read_npz(data)
        d = np.full(len(pts), np.nan, np.float32)
        s = np.full(len(pts), UNKNOWN, np.uint8)
        d[near], s[near] = a["sdf"], a["state"]  # a reply of another length: ValueError, that map's error
        g = None
        if gradient:
            g = np.zeros((len(pts), 3), np.float32)
            local_g = np.asarray(a["gradient"], np.float64).reshape(len(near), 3)
            # rotated into the site frame; a gradient with a NaN in it has no direction (all NaN)
            g[near] = np.where(np.isfinite(local_g).all(1, keepdims=True), local_g @ site_from_world[:3, :3].T,
                               np.nan)
        return d, s, g

    asks = {mid: (Keys.for_map(mid).sdf, np.ascontiguousarray(local, "<f4").tobytes(),
                  "gradient=true" if gradient else "") for mid, (_, local, _) in jobs.items()}
    got = _ask_all(session, asks, deadline, read, missing)
    maps = [mid for mid in jobs if mid in got]
    sdf, state, grad, source = merge_distances([got[m] for m in maps], len(pts))
    return FleetDistance(sdf, state, grad if gradient else None, source, maps, missing, skipped)


@dataclass
class FleetSlice:
    """An occupancy / distance slice in the site frame merged over the maps of a fleet."""

    slice: DistanceSlice
    """occupancy and distance images (row 0 the lowest site y), as one map's slice"""
    source: np.ndarray
    """(H, W) int: index into ``maps`` of the map whose distance each cell took (-1: none)"""
    maps: list[str] = field(default_factory=list)
    """the maps that answered"""
    missing: dict[str, str] = field(default_factory=dict)
    """map id -> why it gave no answer"""
    skipped: list[str] = field(default_factory=list)
    """maps the slice does not come near (not asked)"""


def fleet_slice(session: zenoh.Session, z: float, lo: tuple[float, float], hi: tuple[float, float],
                resolution: float = 0.05, timeout: float = 2.0, max_cells: int = 1_000_000,
                entries: list[dict] | None = None) -> FleetSlice:
    """Occupancy and distance at site height ``z`` (m) over ``lo`` = (xmin, ymin) .. ``hi`` = (xmax,
    ymax) site metres, ``resolution`` metres a cell, merged over the fleet: the signed distance of
    every map at the cell centres (:func:`fleet_sdf`, each map's answer in its own frame, whatever its
    axes), merged cell by cell into the nearest known surface, then occupancy and the in-plane
    distance transform as one map's slice makes them (:func:`slice_from_sample`). ValueError on a box
    or resolution that is not finite and positive, or more than ``max_cells`` cells."""
    lo, hi = (float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1]))
    if not (np.isfinite([z, *lo, *hi, resolution]).all() and resolution > 0 and lo[0] < hi[0] and lo[1] < hi[1]):
        raise ValueError("fleet slice needs a finite z, lo < hi and a positive resolution")
    cells = slice_cells(lo, hi, resolution)
    if not cells <= max_cells:
        raise ValueError(f"a fleet slice of {cells:.4g} cells exceeds {max_cells}: a coarser resolution or a smaller "
                         "area")
    pts, shape = slice_grid(float(z), lo, hi, float(resolution))
    d = fleet_sdf(session, pts, timeout, entries=entries)
    merged = slice_from_sample(d.sdf, d.state, shape, float(z), lo, float(resolution))
    return FleetSlice(merged, d.source.reshape(shape), d.maps, d.missing, d.skipped)


@dataclass
class FleetRender:
    """The fleet's maps seen from one site-frame camera, composited by depth."""

    color: np.ndarray
    """(H, W, 3) uint8 RGB"""
    depth: np.ndarray
    """(H, W) float32 z-depth metres (0: no map saw anything there)"""
    source: np.ndarray
    """(H, W) int: index into ``maps`` of the map each pixel came from (-1: none)"""
    maps: list[str] = field(default_factory=list)
    """the maps that answered"""
    missing: dict[str, str] = field(default_factory=dict)
    """map id -> why it gave no answer"""
    skipped: list[str] = field(default_factory=list)
    """maps wholly behind the camera (not asked)"""


def fleet_render(session: zenoh.Session, c2w, width: int = 320, height: int = 240,
                 intrinsics: Intrinsics | None = None, fov_deg: float = 80.0, timeout: float = 5.0,
                 entries: list[dict] | None = None) -> FleetRender:
    """The fleet seen from camera-to-site ``c2w`` (4, 4, OpenCV optical axes): each map with voxels in
    front of the camera renders from the same camera in its own frame (``intrinsics``, or ``fov_deg``
    over ``width`` x ``height``), all at once within ``timeout`` seconds; per pixel the nearest
    surface wins (z-depth is the camera's, the same in every map's frame)."""
    c2w = np.asarray(c2w, np.float64).reshape(4, 4)
    err = rigid_error(c2w)
    if err or not np.isfinite(c2w).all():
        raise ValueError(f"fleet render pose is not a rigid transform ({err or 'not finite'})")
    deadline, places, missing = _start(session, timeout, entries)
    h, w = (intrinsics.height, intrinsics.width) if intrinsics is not None else (int(height), int(width))
    w2c = invert_pose(c2w)
    asks, skipped = {}, []
    for pl in places:
        corners = pl.site_box_corners() @ w2c[:3, :3].T + w2c[:3, 3] if pl.box is not None else None
        if corners is None or (corners[:, 2] <= 0).all():  # no voxel, or every voxel behind the camera
            skipped.append(pl.map_id)
            continue
        asks[pl.map_id] = (Keys.for_map(pl.map_id).render,
                           render_request(pl.world_from_site @ c2w, w, h, intrinsics, fov_deg), "")

    def read(mid: str, data: bytes):
        msg = decode_frame(data)
        if msg.depth.shape != (h, w) or msg.color.shape != (h, w, 3):
            raise ValueError(f"render of {msg.depth.shape} pixels, not {(h, w)}")
        return msg.color, msg.depth

    got = _ask_all(session, asks, deadline, read, missing)
    color, depth = np.zeros((h, w, 3), np.uint8), np.zeros((h, w), np.float32)
    source = np.full((h, w), -1, np.int64)
    maps = [mid for mid in asks if mid in got]
    for i, mid in enumerate(maps):
        c, d = got[mid]
        take = (d > 0) & np.isfinite(d) & ((source < 0) | (d < depth))
        color[take], depth[take], source[take] = c[take], d[take], i
    return FleetRender(color, depth, source, maps, missing, skipped)


@dataclass
class FleetMesh:
    """The fleet's meshes in the site frame, one per map (trimesh.Trimesh, metres, vertex colours)."""

    meshes: dict = field(default_factory=dict)
    """map id -> its mesh in the site frame"""
    missing: dict[str, str] = field(default_factory=dict)
    """map id -> why it gave no answer"""
    skipped: list[str] = field(default_factory=list)
    """maps with no voxel in the box asked for (not asked)"""

    @property
    def maps(self) -> list[str]:
        """the maps that answered"""
        return list(self.meshes)

    def export(self, format: str = "ply") -> bytes:
        """One file's bytes: ``glb``, a scene with one node per map (named by its id); ``ply`` or
        ``obj``, the maps' meshes concatenated."""
        import trimesh

        if format == "glb":
            scene = trimesh.Scene()
            for mid, mesh in self.meshes.items():
                scene.add_geometry(mesh, node_name=mid, geom_name=mid)
            return scene.export(file_type="glb")
        meshes = list(self.meshes.values())
        whole = trimesh.util.concatenate(meshes) if meshes else trimesh.Trimesh()
        return whole.export(file_type=format)


def fleet_mesh(session: zenoh.Session, resolution: int | None = None, aabb=None, timeout: float = 30.0,
               entries: list[dict] | None = None) -> FleetMesh:
    """Every map's mesh (each service's ``mesh`` query, ``resolution`` cells per voxel edge) moved into
    the site frame, all asked at once within ``timeout`` seconds. ``aabb`` (2, 3) site metres: only
    the maps whose voxels meet it, each asked for the box in its own frame that holds it (so a map
    turned against the site may give a little more than the box)."""
    import trimesh

    box = None
    if aabb is not None:
        box = np.asarray(aabb, np.float64).reshape(2, 3)
        if not np.isfinite(box).all() or np.any(box[0] >= box[1]):
            raise ValueError("fleet mesh aabb must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max")
    deadline, places, missing = _start(session, timeout, entries)
    asks, skipped = {}, []
    for pl in places:
        payload: dict = {"format": "ply"}
        if resolution is not None:
            payload["resolution"] = int(resolution)
        if pl.box is None:  # no voxel yet
            skipped.append(pl.map_id)
            continue
        if box is not None:
            corners = pl.to_local(_box_corners(box))
            local = np.stack([np.maximum(corners.min(0), pl.box[0]), np.minimum(corners.max(0), pl.box[1])])
            if np.any(local[0] >= local[1]):
                skipped.append(pl.map_id)
                continue
            payload["aabb"] = local.tolist()
        asks[pl.map_id] = (Keys.for_map(pl.map_id).mesh, payload, "")
    site = {pl.map_id: pl.site_from_world for pl in places}

    def read(mid: str, data: bytes):
        mesh = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
        if not isinstance(mesh, trimesh.Trimesh):
            raise ValueError(f"mesh reply is a {type(mesh).__name__}, not a triangle mesh")
        return mesh.apply_transform(site[mid])

    got = _ask_all(session, asks, deadline, read, missing)
    return FleetMesh({mid: got[mid] for mid in asks if mid in got}, missing, skipped)


class Fleet(SessionUser):
    """Every h3edge service on a zenoh network, asked as one map in the site frame the fleet shares.

    Usage::

        from h3edge import Fleet

        with Fleet(connect=["tcp/site-router:7447"], mode="client") as fleet:
            fleet.status()                                      # one entry per map
            d = fleet.signed_distance(points)                   # FleetDistance, site frame
            s = fleet.slice(0.4, (-10, -10), (10, 10), 0.05)    # FleetSlice
            r = fleet.render(c2w, 640, 480)                     # FleetRender: composited by depth
            open("site.glb", "wb").write(fleet.mesh().export("glb"))

    Points, poses and boxes are in the site frame (metres; poses camera-to-site, OpenCV optical
    axes); each map is asked in its own frame (its status's ``site_from_world``). Every answer names
    the maps that gave it (``maps``), those with no answer by the deadline (``missing``: they are
    never waited for past ``timeout`` seconds) and those the request does not come near
    (``skipped``)."""

    def __init__(self, config: str | zenoh.Config | None = None, *, connect: list[str] | None = None,
                 mode: str | None = None, multicast: bool | None = None, timeout: float = 5.0,
                 session: zenoh.Session | None = None):
        """``config``: a zenoh JSON5 file or a ``zenoh.Config`` (default zenoh's: peer, multicast
        scouting); ``connect`` / ``mode`` / ``multicast`` override it. ``timeout``: seconds a fan-out
        may take in all, the status query included (a mesh: at least 30). ``session``: an open
        session to use instead (not closed by the fleet)."""
        super().__init__(config, connect, mode, multicast, session)
        self.timeout = timeout

    def status(self) -> list[dict]:
        """Every map that answers: ``{"map_id", "status"}`` (its status document), sorted by id."""
        return fleet_status(self.session, self.timeout)

    def signed_distance(self, points, gradient: bool = False) -> FleetDistance:
        """Signed distance at site points (N, 3) metres: the nearest surface any map knows
        (:func:`fleet_sdf`); ``.gradient`` (N, 3) in the site frame when asked."""
        return fleet_sdf(self.session, points, self.timeout, gradient)

    def slice(self, z: float, lo, hi, resolution: float = 0.05) -> FleetSlice:
        """Occupancy and distance at site height ``z`` over ``lo`` = (xmin, ymin) .. ``hi`` = (xmax,
        ymax) metres, ``resolution`` m a cell (:func:`fleet_slice`)."""
        return fleet_slice(self.session, z, lo, hi, resolution, self.timeout)

    def render(self, c2w, width: int = 320, height: int = 240, intrinsics: Intrinsics | None = None,
               fov_deg: float = 80.0) -> FleetRender:
        """The fleet seen from camera-to-site ``c2w`` (4, 4): colour uint8 (H, W, 3), z-depth float32
        (H, W) metres (0: nothing), composited by depth (:func:`fleet_render`)."""
        return fleet_render(self.session, c2w, width, height, intrinsics, fov_deg, self.timeout)

    def mesh(self, resolution: int | None = None, aabb=None) -> FleetMesh:
        """Every map's mesh in the site frame (:func:`fleet_mesh`); ``.export("glb" | "ply" | "obj")``."""
        return fleet_mesh(self.session, resolution, aabb, max(self.timeout, 30.0))
