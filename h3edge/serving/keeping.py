"""A map that outlives its robot: checkpoints published on zenoh, kept by another host, fetched back.

- A service with ``[service] fleet_checkpoints`` publishes every checkpoint it writes
  (:class:`CheckpointPublisher`, :func:`publish_checkpoint`) under ``h3edge/<map-id>/checkpoint``:
  the file in 1 MiB chunks (``chunk/<k>``, reliable, blocking congestion control), then a manifest
  (``manifest``: JSON with the map id, frames mapped, bytes, chunk count and the file's SHA-256).
- A keeper stores the newest whole checkpoint of every map (:class:`CheckpointKeeper`, ``h3edge fleet
  keep --dir D``): the chunks land in a scratch file, and when the manifest arrives the file is kept
  only if every chunk came, its SHA-256 is the manifest's, the checkpoint's own header and payload
  checksum hold and its map id is the key's (a robot can put only a map of its own id; the routers'
  ACL lets it write only under its own key). It answers queries on the same keys, as a zenoh storage
  of ``h3edge/*/checkpoint/**`` would.
- A service whose disk is lost fetches its map back (:func:`fetch_checkpoint`, ``h3edge serve
  --resume-from-fleet``) and resumes from it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from h3edge.io.checkpoint_file import CHECKPOINT_NAME, CheckpointError, previous_path, read_header, verify_checkpoint
from h3edge.io.protocol import Keys, check_map_id
from h3edge.serving.client import RemoteError, query

log = logging.getLogger(__name__)
CHUNK_BYTES = 1 << 20
KEPT_NAME = CHECKPOINT_NAME  # <keeper dir>/<map-id>/ holds it and manifest.json
CHECKPOINT_KEYS = "h3edge/*/checkpoint/**"


def publish_checkpoint(session: zenoh.Session, map_id: str, path: Path) -> dict:
    """Put the checkpoint file ``path`` of map ``map_id`` on zenoh: its chunks, then its manifest
    (returned). The file is read from one open handle: a checkpoint written over it meanwhile does
    not tear what is sent."""
    keys = Keys.for_map(map_id)
    digest, size, n = hashlib.sha256(), 0, 0
    with open(path, "rb") as f:
        for piece in iter(lambda: f.read(CHUNK_BYTES), b""):
            session.put(keys.checkpoint_chunk(n), piece, congestion_control=zenoh.CongestionControl.BLOCK)
            digest.update(piece)
            size += len(piece)
            n += 1
    manifest = {"map_id": map_id, "bytes": size, "chunks": n, "chunk_bytes": CHUNK_BYTES,
                "sha256": digest.hexdigest(), "published_unix": time.time()}
    session.put(keys.checkpoint_manifest, json.dumps(manifest).encode(),
                congestion_control=zenoh.CongestionControl.BLOCK)
    return manifest


class CheckpointPublisher:
    """Publishes each new checkpoint a service writes (a thread polling ``latest()``: the newest
    write's info with ``path`` and ``unix``, or None) with :func:`publish_checkpoint`."""

    def __init__(self, session: zenoh.Session, map_id: str, latest: Callable[[], dict | None], poll_s: float = 0.5):
        self.session, self.map_id, self.latest, self.poll_s = session, map_id, latest, poll_s
        self.published: dict | None = None  # the last manifest sent
        self._sent_unix = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="h3edge-ckpt-publish", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.poll_s):
            self.publish_new()

    def publish_new(self) -> bool:
        """Publish the newest checkpoint if it was not yet; True when one went out."""
        info = self.latest()
        if not info or info.get("unix") == self._sent_unix:
            return False
        try:
            self.published = publish_checkpoint(self.session, self.map_id, Path(info["path"]))
            self._sent_unix = info.get("unix")
            log.info("checkpoint published for the fleet: %d frames, %d chunks", info.get("frames_mapped", 0),
                     self.published["chunks"])
            return True
        except (OSError, zenoh.ZError) as e:
            log.warning("could not publish the checkpoint for the fleet: %s", e)
            return False

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(10.0)


class CheckpointKeeper:
    """Keeps the newest whole checkpoint of every map published on ``h3edge/*/checkpoint`` under
    ``directory/<map-id>/`` and answers the same keys from it.

    At most ``max_maps`` maps and ``max_bytes`` per checkpoint: chunks beyond either are dropped
    (counted in ``refused``)."""

    def __init__(self, session: zenoh.Session, directory: Path, max_bytes: int = 1 << 30, max_maps: int = 64):
        self.session, self.dir = session, Path(directory)
        self.max_bytes, self.max_maps = max_bytes, max_maps
        self.dir.mkdir(parents=True, exist_ok=True)
        self.kept: dict[str, dict] = {}  # map id -> manifest of the checkpoint kept
        for manifest in self.dir.glob("*/manifest.json"):
            try:
                m = json.loads(manifest.read_text())
                self.kept[check_map_id(m["map_id"])] = m
            except (OSError, ValueError, KeyError) as e:
                log.warning("ignoring %s: %s", manifest, e)
        self.refused: dict[str, int] = {}  # reason -> count
        self._incoming: dict[str, set[int]] = {}  # map id -> chunks of the checkpoint arriving
        self._lock = threading.Lock()
        self._entities: list = []

    def start(self) -> None:
        self._entities.append(self.session.declare_subscriber(CHECKPOINT_KEYS, self._on_sample))
        self._entities.append(self.session.declare_queryable(CHECKPOINT_KEYS, self._on_query))

    def close(self) -> None:
        for e in self._entities:
            e.undeclare()
        self._entities.clear()

    def _refuse(self, reason: str, detail: str = "") -> None:
        self.refused[reason] = self.refused.get(reason, 0) + 1
        log.warning("checkpoint refused (%s) %s", reason, detail[:200])

    @staticmethod
    def _parse(key: str) -> tuple[str, list[str]]:
        parts = key.split("/")
        if len(parts) < 4 or parts[0] != "h3edge" or parts[2] != "checkpoint":
            raise ValueError(f"not a checkpoint key: {key[:100]}")
        return check_map_id(parts[1]), parts[3:]

    def _scratch(self, map_id: str) -> Path:
        return self.dir / map_id / "incoming.tmp"

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            map_id, rest = self._parse(str(sample.key_expr))
        except ValueError as e:
            return self._refuse("bad_key", str(e))
        with self._lock:
            if map_id not in self.kept and map_id not in self._incoming and len(
                    set(self.kept) | set(self._incoming)) >= self.max_maps:
                return self._refuse("too_many_maps", map_id)
            if rest[0] == "chunk" and len(rest) == 2 and rest[1].isdigit():
                self._chunk(map_id, int(rest[1]), sample.payload.to_bytes())
            elif rest == ["manifest"]:
                self._manifest(map_id, sample.payload.to_bytes())
            else:
                self._refuse("bad_key", str(sample.key_expr))

    def _chunk(self, map_id: str, k: int, data: bytes) -> None:
        if len(data) > CHUNK_BYTES or (k + 1) * CHUNK_BYTES > self.max_bytes:
            self._incoming.pop(map_id, None)
            return self._refuse("too_large", f"{map_id} chunk {k}")
        scratch = self._scratch(map_id)
        if k == 0 or map_id not in self._incoming:  # chunk 0 starts a checkpoint (a later one without it is moot)
            if k != 0:
                return self._refuse("incomplete", f"{map_id} chunk {k} without chunk 0")
            scratch.parent.mkdir(parents=True, exist_ok=True)
            scratch.write_bytes(b"")
            self._incoming[map_id] = set()
        with open(scratch, "r+b") as f:
            f.seek(k * CHUNK_BYTES)
            f.write(data)
        self._incoming[map_id].add(k)

    def _manifest(self, map_id: str, data: bytes) -> None:
        got = self._incoming.pop(map_id, None)
        scratch = self._scratch(map_id)
        try:
            m = json.loads(data)
            n, size, sha = int(m["chunks"]), int(m["bytes"]), str(m["sha256"])
            if m.get("map_id") != map_id:
                raise ValueError(f"manifest names map {str(m.get('map_id'))[:64]!r}")
            if got != set(range(n)) or scratch.stat().st_size != size:
                raise ValueError(f"{len(got or ())} of {n} chunks arrived")
            digest = hashlib.sha256()
            with open(scratch, "rb") as f:
                for piece in iter(lambda: f.read(CHUNK_BYTES), b""):
                    digest.update(piece)
            if digest.hexdigest() != sha:
                raise ValueError("the chunks' SHA-256 is not the manifest's")
            header = verify_checkpoint(scratch)
            if header.get("map_id") != map_id:
                raise ValueError(f"the checkpoint is of map {str(header.get('map_id'))[:64]!r}")
        except (ValueError, KeyError, TypeError, OSError, CheckpointError) as e:
            scratch.unlink(missing_ok=True)
            return self._refuse("invalid", f"{map_id}: {e}")
        m = {"map_id": map_id, "bytes": size, "chunks": n, "chunk_bytes": CHUNK_BYTES, "sha256": sha,
             "frames_mapped": header.get("frames_mapped"), "created_unix": header.get("created_unix"),
             "profile": header.get("profile"), "kept_unix": time.time()}
        os.replace(scratch, self.dir / map_id / KEPT_NAME)
        tmp = self.dir / map_id / "manifest.json.tmp"
        tmp.write_text(json.dumps(m))
        os.replace(tmp, self.dir / map_id / "manifest.json")
        self.kept[map_id] = m
        log.info("kept map %r: %d frames, %.1f MB", map_id, m["frames_mapped"] or 0, size / 1e6)

    def _on_query(self, q: zenoh.Query) -> None:
        with q:
            try:
                map_id, rest = self._parse(str(q.key_expr))
            except ValueError:
                return
            with self._lock:
                m = self.kept.get(map_id)
                if m is None:
                    q.reply_err(f"this keeper holds no checkpoint of map {map_id!r}".encode())
                    return
                if rest == ["manifest"]:
                    q.reply(q.key_expr, json.dumps(m).encode())
                elif rest[0] == "chunk" and len(rest) == 2 and rest[1].isdigit() and int(rest[1]) < m["chunks"]:
                    with open(self.dir / map_id / KEPT_NAME, "rb") as f:
                        f.seek(int(rest[1]) * CHUNK_BYTES)
                        q.reply(q.key_expr, f.read(CHUNK_BYTES))


def fetch_checkpoint(session: zenoh.Session, map_id: str, dest: Path, timeout: float = 30.0) -> dict:
    """Fetch the checkpoint the fleet keeps of ``map_id`` into ``dest`` and return its manifest. It
    lands whole or not at all; a checkpoint already at ``dest`` becomes the previous one (``.prev``).
    TimeoutError when nobody keeps it; CheckpointError when what comes back is not whole, not
    ``map_id``'s or fails its checksum (after one retry: a newer one may have landed meanwhile)."""
    keys = Keys.for_map(map_id)
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(dest.name + ".fleet.tmp")
    err: Exception | None = None
    for _ in range(2):
        try:
            m = json.loads(query(session, keys.checkpoint_manifest, timeout=timeout))
            digest = hashlib.sha256()
            with open(tmp, "wb") as f:
                for k in range(int(m["chunks"])):
                    piece = query(session, keys.checkpoint_chunk(k), timeout=timeout)
                    digest.update(piece)
                    f.write(piece)
                f.flush()
                os.fsync(f.fileno())
            if digest.hexdigest() != m["sha256"]:
                raise CheckpointError("the fetched chunks' SHA-256 is not the manifest's")
            header = verify_checkpoint(tmp)
            if header.get("map_id") != map_id:
                raise CheckpointError(f"the fleet's checkpoint is of map {str(header.get('map_id'))[:64]!r}")
            if dest.exists():
                os.replace(dest, previous_path(dest))
            os.replace(tmp, dest)
            return m
        except (CheckpointError, ValueError, KeyError) as e:
            err = e
        finally:
            tmp.unlink(missing_ok=True)
    raise CheckpointError(f"cannot fetch map {map_id!r} from the fleet: {err}")


def restore_from_fleet(session: zenoh.Session, map_id: str, run_dir: Path, timeout: float = 30.0) -> str:
    """Before a service resumes: bring the fleet's checkpoint of ``map_id`` into ``run_dir`` when it
    holds more frames than the local one (none, after a lost disk). Returns what was done, one line.
    A keeper that answers it keeps no such map: a new map starts. ConnectionError when no keeper answers
    and there is no local checkpoint, CheckpointError when the fleet's cannot be used: the service
    must not start an empty map that would then be kept over the one the fleet could not give."""
    local = Path(run_dir) / CHECKPOINT_NAME
    try:
        mine = read_header(local)[0].get("frames_mapped", 0) if local.exists() else None
    except CheckpointError:
        mine = None
    try:
        m = json.loads(query(session, Keys.for_map(map_id).checkpoint_manifest, timeout=timeout))
        theirs = int(m.get("frames_mapped") or 0)
    except RemoteError as e:
        return (f"resuming from the local checkpoint ({mine} frames)" if mine is not None
                else "starting a new map") + f": the fleet keeps none of {map_id!r} ({e})"
    except (TimeoutError, ValueError, KeyError, TypeError) as e:
        if mine is not None:
            return f"no keeper answered for {map_id!r} ({e}); resuming from the local checkpoint ({mine} frames)"
        raise ConnectionError(f"--resume-from-fleet: no local checkpoint and no keeper answered for map {map_id!r} "
                              f"({e}); not starting an empty map") from None
    if mine is not None and mine >= theirs:
        return f"the local checkpoint ({mine} frames) is as new as the fleet's ({theirs}): resuming from it"
    m = fetch_checkpoint(session, map_id, local, timeout)
    return f"fetched map {map_id!r} from the fleet: {m['bytes'] / 1e6:.1f} MB, {theirs} frames"
