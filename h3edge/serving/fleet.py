"""The fleet: every h3edge service on a zenoh network, found with one query.

Each service answers its status on ``h3edge/<map-id>/status``; one query on the wildcard key
``h3edge/*/status`` reaches them all (``QueryTarget.ALL``), and with no consolidation every service's
reply comes back, not one per key (:func:`fleet_status`). Zenoh routes it: through the routers of a
site, or peer to peer. Nothing is registered anywhere; a service is in the fleet while it answers.
"""

from __future__ import annotations

import json

import zenoh

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
