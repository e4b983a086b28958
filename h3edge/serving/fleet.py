"""The fleet: every h3edge service on a zenoh network, found with one query.

Each service answers its status on ``h3edge/<map-id>/status``; one query on the wildcard key
``h3edge/*/status`` reaches them all (``QueryTarget.ALL``), and with no consolidation every service's
reply comes back, not one per key (:func:`fleet_status`). Zenoh routes it: through the routers of a
site, or peer to peer. Nothing is registered anywhere; a service is in the fleet while it answers.

One signed distance over many maps (:func:`fleet_sdf`): each status says where its map's world frame
lies in the site frame the fleet shares (``[service] site_from_world``) and the box its voxels fill;
the site-frame points are moved into each map whose box (plus a margin) they touch and asked of it,
all maps at once, within one deadline; the answers merge into the nearest known surface
(:func:`merge_distances`). A map that does not answer in time is named in the result, not waited for.
"""

from __future__ import annotations

import concurrent.futures
import json
import time
from dataclasses import dataclass, field

import numpy as np
import zenoh

from h3edge.geometry.camera import invert_pose, rigid_error
from h3edge.io.distance_types import UNKNOWN
from h3edge.io.protocol import Keys
from h3edge.serving.client import RemoteError, query, read_npz

FLEET_STATUS_KEY = "h3edge/*/status"


def fleet_status(session: zenoh.Session, timeout: float = 2.0) -> list[dict]:
    """The status of every service that answers within ``timeout`` seconds, one entry per map
    sorted by map id: ``{"map_id", "status"}`` (the service's status document), or ``{"map_id",
    "error"}`` for a reply that is not a status document (error replies are left out)."""
    entries: list[dict] = []
    replies = session.get(FLEET_STATUS_KEY, target=zenoh.QueryTarget.ALL,
                          consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout)
    for reply in replies:
        if reply.ok is None:
            continue  # an error reply names no map: nothing to list it under
        # a service answers on the query's key (the wildcard): its map id is in its status
        try:
            status = json.loads(reply.ok.payload.to_bytes())
            entries.append({"map_id": str(status["map_id"]), "status": status})
        except (ValueError, KeyError, TypeError) as e:
            entries.append({"map_id": f"? ({reply.ok.key_expr})", "error": f"not a status document: {e!r}"[:200]})
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
        rows.append(f"| {e['map_id']} | {st.get('world_frame', '?')} | {st['frames']['mapped']} | "
                    f"{st['map'].get('voxels') or 0} | {st['memory']['total_bytes'] / 2**20:.0f} | "
                    f"{'-' if age is None else age} | {'alive' if st.get('mapper_alive') else 'stopped'} |")
    tail = f"\n{len(entries)} map(s)" + (f" answered in {seconds * 1000:.0f} ms" if seconds is not None else "")
    return "\n".join(rows) + tail


SDF_MARGIN = 0.5  # m: a map is asked about points this far outside its voxels' box too (its free space, votes)


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
    """(N,) int: index into ``maps`` of the map whose answer was taken (-1: none)"""
    maps: list[str] = field(default_factory=list)
    """the maps that answered, in the order ``source`` indexes"""
    missing: dict[str, str] = field(default_factory=dict)
    """map id -> why it gave no answer (its deadline passed, an error reply)"""
    skipped: list[str] = field(default_factory=list)
    """maps the points do not come near (not asked)"""


def merge_distances(answers: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]], n: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """(sdf, state, gradient, source) over ``n`` points from each map's (sdf (n,), state (n,),
    gradient (n, 3) or None) in the site frame: at each point the least signed distance among the
    maps that know it (state != unknown), its state, gradient and map index: the nearest surface any
    map knows, inside where any map knows the point inside (a planner's conservative reading); a
    free answer is a lower bound (at least the truncation) and gives way to any nearer one. NaN,
    unknown and -1 where no map knows the point."""
    sdf = np.full(n, np.inf, np.float64)
    state = np.full(n, UNKNOWN, np.uint8)
    source = np.full(n, -1, np.int64)
    grad = np.full((n, 3), np.nan, np.float32) if answers and all(a[2] is not None for a in answers) else None
    for i, (d, st, g) in enumerate(answers):
        take = (np.asarray(st) != UNKNOWN) & np.isfinite(d) & (np.asarray(d, np.float64) < sdf)
        sdf[take], state[take], source[take] = np.asarray(d, np.float64)[take], np.asarray(st)[take], i
        if grad is not None:
            grad[take] = np.asarray(g, np.float32)[take]
    sdf[source < 0] = np.nan
    return sdf.astype(np.float32), state, grad, source


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


def fleet_sdf(session: zenoh.Session, points: np.ndarray, timeout: float = 2.0, gradient: bool = False,
              margin: float = SDF_MARGIN, entries: list[dict] | None = None) -> FleetDistance:
    """Signed distance at ``points`` (N, 3) metres in the site frame over every map that answers
    :func:`fleet_status` (or the given ``entries``), all asked at once within ``timeout`` seconds in
    all (the status query included): each map whose voxel box, grown by ``margin`` metres, holds some
    of the points is sent those points in its world frame; the answers merge with
    :func:`merge_distances` (gradients rotated back into the site frame). ValueError on points that
    are not finite."""
    start = time.monotonic()
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if not np.isfinite(pts).all():
        raise ValueError("fleet sdf points must be finite coordinates")
    if entries is None:
        entries = fleet_status(session, timeout)
    jobs, skipped, missing = {}, [], {}
    for e in entries:
        st = e.get("status")
        if st is None:
            continue
        try:
            site_from_world, box = _map_geometry(st)
        except ValueError as err:  # one odd status costs that map, not the query
            missing[e["map_id"]] = str(err)[:200]
            continue
        world_from_site = invert_pose(site_from_world)
        local = pts @ world_from_site[:3, :3].T + world_from_site[:3, 3]
        near = (np.flatnonzero(((local >= box[0] - margin) & (local <= box[1] + margin)).all(1))
                if box is not None else np.zeros(0, np.int64))
        if len(near) == 0:
            skipped.append(e["map_id"])
            continue
        jobs[e["map_id"]] = (near, local[near], site_from_world)
    answers, maps = [], []
    if jobs:
        left = max(0.05, timeout - (time.monotonic() - start))
        with concurrent.futures.ThreadPoolExecutor(len(jobs)) as pool:
            futures = {mid: pool.submit(query, session, Keys.for_map(mid).sdf,
                                        np.ascontiguousarray(local, "<f4").tobytes(),
                                        "gradient=true" if gradient else "", left)
                       for mid, (_, local, _) in jobs.items()}
            for mid, fut in futures.items():
                near, _, site_from_world = jobs[mid]
                d = np.full(len(pts), np.nan, np.float32)
                s = np.full(len(pts), UNKNOWN, np.uint8)
                g = np.zeros((len(pts), 3), np.float32) if gradient else None
                try:
                    a = read_npz(fut.result())
                    d[near], s[near] = a["sdf"], a["state"]  # a reply of another length: that map's error
                    if gradient:
                        local_g = np.asarray(a["gradient"], np.float64).reshape(len(near), 3)
                        # rotated into the site frame; a gradient with a NaN in it has no direction (all NaN)
                        g[near] = np.where(np.isfinite(local_g).all(1, keepdims=True),
                                           local_g @ site_from_world[:3, :3].T, np.nan)
                except (TimeoutError, RemoteError, OSError, ValueError, KeyError) as err:
                    missing[mid] = f"{type(err).__name__}: {err}"[:200]
                    continue
                answers.append((d, s, g))
                maps.append(mid)
    sdf, state, grad, source = merge_distances(answers, len(pts))
    return FleetDistance(sdf, state, grad if gradient else None, source, maps, missing, skipped)
