"""The map file's envelope (``.h3ckpt``), readable without the mapping stack: the magic, the JSON
header and the payload's checksum. :mod:`h3edge.mapping.map_file` writes and reads whole maps
through it; a process that only keeps or moves checkpoints (``h3edge fleet keep``) checks them
here without torch.

Layout: the 12-byte magic ``H3EDGE-CKPT\\n``, a little-endian uint32 header length, a UTF-8 JSON
header (``format_version``, ``map_id``, ``frames_mapped``, ``payload_bytes``, ``payload_sha256``,
...), then the payload.
"""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path

from h3edge.errors import InputError

MAGIC = b"H3EDGE-CKPT\n"
FORMAT_VERSION = 1
CHECKPOINT_NAME = "map.h3ckpt"  # the checkpoint a service resumes from, under <state dir>/<map id>/


class CheckpointError(InputError):
    """A checkpoint that cannot be used; the message says why."""


def previous_path(path: Path) -> Path:
    """Where the checkpoint before ``path``'s newest is kept."""
    path = Path(path)
    return path.with_name(path.name + ".prev")


def read_header(path: Path) -> tuple[dict, int]:
    """(header, payload offset) of a checkpoint file."""
    with open(path, "rb") as f:
        start = f.read(len(MAGIC) + 4)
        if len(start) < len(MAGIC) + 4 or start[:len(MAGIC)] != MAGIC:
            raise CheckpointError(f"{path}: not an h3edge checkpoint (bad magic)")
        (n,) = struct.unpack("<I", start[len(MAGIC):])
        raw = f.read(n)
    if len(raw) != n:
        raise CheckpointError(f"{path}: truncated header")
    try:
        header = json.loads(raw)
    except json.JSONDecodeError as e:
        raise CheckpointError(f"{path}: header is not JSON ({e})") from None
    version = header.get("format_version") if isinstance(header, dict) else None
    if version != FORMAT_VERSION:
        raise CheckpointError(f"{path}: format version {version!r}, this build reads {FORMAT_VERSION}")
    return header, len(MAGIC) + 4 + n


def verify_checkpoint(path: Path) -> dict:
    """The header of a whole, intact checkpoint file: its payload's length and SHA-256 as the header
    says (read in 1 MiB pieces); CheckpointError naming what is wrong otherwise."""
    header, offset = read_header(path)
    digest, size = hashlib.sha256(), 0
    with open(path, "rb") as f:
        f.seek(offset)
        for piece in iter(lambda: f.read(1 << 20), b""):
            digest.update(piece)
            size += len(piece)
    if size != header.get("payload_bytes"):
        raise CheckpointError(f"{path}: payload is {size} bytes, header says {header.get('payload_bytes')}")
    if digest.hexdigest() != header.get("payload_sha256"):
        raise CheckpointError(f"{path}: payload checksum mismatch (corrupt file)")
    return header
