"""The map file (``.h3ckpt``): what a saved map holds and the crash-safe, versioned format it is
written in. The library's :meth:`h3edge.MapEngine.save` / :meth:`h3edge.MapEngine.load` and the
service's checkpoints (:mod:`h3edge.serving.checkpointing`) both write it here.

Contents (:func:`map_record`, :func:`read_map`): the mapper's ``state_dict`` (JSON meta in the
header, named arrays in the payload), its decoders as ONNX (versioned with the map), the mapping
settings it ran with, a map id and the profile name.

Layout: the 12-byte magic ``H3EDGE-CKPT\\n``, a little-endian uint32 header length, a UTF-8 JSON
header (``format_version``, ``map_id``, ``created_unix``, ``frames_mapped``, ``profile``, the mapping
settings, ``payload_bytes``, ``payload_sha256``, the mapper's JSON state), then the payload: the
mapper's arrays as an uncompressed ``.npz`` (read back with ``allow_pickle=False``).

Writing streams the payload through ``<name>.payload.tmp``, then goes to ``<name>.tmp`` in the same
directory, is flushed and fsync'ed, renamed over
``<name>`` and the directory is fsync'ed: a reader sees the previous checkpoint or the new one,
never a torn file, whatever moment the process is killed at. Reading checks the magic, the
version, the length and the checksum, and names what is wrong.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import shutil
import struct
import time
from pathlib import Path

import numpy as np

from h3edge.io.checkpoint_file import (  # noqa: F401 (re-exported: the map file's envelope)
    CHECKPOINT_NAME,
    FORMAT_VERSION,
    MAGIC,
    CheckpointError,
    previous_path,
    read_header,
)
from h3edge.mapping.engine import MapEngine, MapSettings
from h3edge.mapping.onnx_decoders import export_decoders
from h3edge.mapping.raymarch import RenderConfig
from h3edge.mapping.settings_file import map_settings_from_saved


def check_writable(directory: Path) -> None:
    """Create ``directory`` and prove a file can be written, synced and removed there; otherwise
    CheckpointError (one line: the service must not map on without checkpoints)."""
    probe = Path(directory) / f".write-probe-{os.getpid()}"
    try:
        Path(directory).mkdir(parents=True, exist_ok=True)
        with open(probe, "wb") as f:
            f.write(b"h3edge")
            f.flush()
            os.fsync(f.fileno())
        probe.unlink()
    except OSError as e:
        raise CheckpointError(
            f"state directory {directory} is not writable ({type(e).__name__}: {e.strerror or e}); "
            "checkpoints could not be saved: fix its owner / permissions or pass --state-dir"
        ) from None


def remove_leftovers(directory: Path) -> list[Path]:
    """Delete the scratch files a write killed midway left in ``directory`` (``*.tmp``); returns them."""
    gone = sorted(Path(directory).glob("*.tmp")) if Path(directory).is_dir() else []
    for f in gone:
        f.unlink(missing_ok=True)
    return gone


def write_checkpoint(path: Path, header: dict, arrays: dict[str, np.ndarray]) -> int:
    """Atomically write a checkpoint; returns its size in bytes. The payload is streamed through
    a scratch file (no in-memory copy of it), hashed, then copied behind the header."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    scratch = path.with_name(path.name + ".payload.tmp")
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(scratch, "w+b") as pf:
            np.savez(pf, **arrays)
            size = pf.tell()
            pf.seek(0)
            digest = hashlib.sha256()
            for chunk in iter(lambda: pf.read(1 << 20), b""):
                digest.update(chunk)
            head = dict(header, format_version=FORMAT_VERSION, created_unix=time.time(), payload_bytes=size,
                        payload_sha256=digest.hexdigest())
            hb = json.dumps(head).encode()
            pf.seek(0)
            with open(tmp, "wb") as f:
                f.write(MAGIC + struct.pack("<I", len(hb)) + hb)
                shutil.copyfileobj(pf, f, 1 << 20)
                f.flush()
                os.fsync(f.fileno())
        if path.exists():  # the previous checkpoint stays as the fallback --resume uses
            os.replace(path, previous_path(path))
        os.replace(tmp, path)
    finally:
        for leftover in (scratch, tmp):
            leftover.unlink(missing_ok=True)
    dfd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)
    return len(MAGIC) + 4 + len(hb) + size


def read_checkpoint(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    header, offset = read_header(path)
    with open(path, "rb") as f:
        f.seek(offset)
        payload = f.read()
    if len(payload) != header.get("payload_bytes"):
        raise CheckpointError(f"{path}: payload is {len(payload)} bytes, header says {header.get('payload_bytes')}")
    if hashlib.sha256(payload).hexdigest() != header.get("payload_sha256"):
        raise CheckpointError(f"{path}: payload checksum mismatch (corrupt file)")
    try:
        with np.load(io.BytesIO(payload), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (ValueError, OSError) as e:
        raise CheckpointError(f"{path}: payload is not a readable array archive ({e})") from None
    return header, arrays


def map_record(mapper: MapEngine, map_id: str, profile: str) -> tuple[dict, dict[str, np.ndarray]]:
    """(header, arrays) that :func:`write_checkpoint` writes for ``mapper`` now: its state, its
    decoders as ONNX, its settings, ``map_id`` and the ``profile`` name. Holds the map while it
    copies (:meth:`MapEngine.state_dict`); RuntimeError when nothing is mapped yet."""
    meta, arrays = mapper.state_dict()
    for name, model in export_decoders(mapper.field).items():
        arrays[f"onnx/{name}"] = np.frombuffer(model, np.uint8)
    header = {"map_id": map_id, "profile": profile, "frames_mapped": mapper.frames_mapped,
              "settings": dataclasses.asdict(mapper.settings), "state": meta}
    return json.loads(json.dumps(header, default=str)), arrays


def saved_settings(header: dict, path: Path) -> MapSettings:
    """The mapping settings a map file was written with (a setting this version no longer has is
    dropped with a warning); CheckpointError when the header has none."""
    saved = header.get("settings")
    if not isinstance(saved, dict):
        raise CheckpointError(f"{path}: the header holds no mapping settings")
    return map_settings_from_saved(saved, f"{path}: settings")


# how a map is read (rendered, meshed), not what it holds: a map saved under other values is read with
# the caller's (render.near also bounds the trainer's free-space samples, so it is not among them)
READ_SETTINGS = tuple(f"render.{f.name}" for f in dataclasses.fields(RenderConfig) if f.name != "near")


def settings_differences(saved: MapSettings, wanted: MapSettings, ignore: tuple[str, ...] = ("mapper.device",)
                         ) -> list[str]:
    """``"section.key: saved -> wanted"`` for every mapping setting that differs (nested tables
    dotted further), but those in ``ignore`` (where the map runs is not what it is)."""
    out: list[str] = []

    def walk(a, b, prefix: str) -> None:
        for f in dataclasses.fields(a):
            x, y, name = getattr(a, f.name), getattr(b, f.name), f"{prefix}{f.name}"
            if dataclasses.is_dataclass(x):
                walk(x, y, name + ".")
            elif x != y and name not in ignore and not (isinstance(x, float) and x != x and y != y):
                out.append(f"{name}: {x!r} -> {y!r}")

    walk(saved, wanted, "")
    return out


def read_map(path: Path, settings: MapSettings | None = None) -> tuple[MapEngine, dict]:
    """(the mapper saved in ``path``, the file's header). ``settings``: the ones to run it with
    (the same sections and sizes as it was saved with); default: the file's own. CheckpointError
    when the file is unreadable, ValueError / KeyError when its state does not fit ``settings``."""
    header, arrays = read_checkpoint(path)
    if "state" not in header:
        raise CheckpointError(f"{path}: the header holds no map state")
    settings = saved_settings(header, Path(path)) if settings is None else settings
    return MapEngine.from_state_dict(settings, header["state"], arrays), header
