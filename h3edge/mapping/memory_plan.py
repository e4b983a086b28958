"""A map's memory plan in a byte budget (the service sizes itself with it): the budget split up
front into the hash tables, the voxel cap, a query's map copy and scratch, the checkpoint capture,
the largest admitted frame's buffers, the observed free space at its cap, and what is left for
keyframes (the keyframe set's byte cap)."""

from __future__ import annotations

from h3edge.mapping.color_base import ROW_BYTES
from h3edge.mapping.device_frames import CHUNK
from h3edge.mapping.engine import RAY_TABLES, MapSettings
from h3edge.mapping.residual_check import KEPT_BYTES

# Peak bytes per pixel of decoding and mapping one frame beyond the ray table (decoded images,
# cleaned depth, back-projected points, texture-pattern images, keyframe payload), measured with
# python -m benchmarks.frame_memory: +253 MB at 1920x1080, +1638 MB at 4096x3072 (128-136 B/px,
# research/bench_frame_memory.md), rounded up.
FRAME_SCRATCH_BYTES_PER_PIXEL = 144
RAY_TABLE_BYTES_PER_PIXEL = 12  # float32 (x, y, z) per pixel, RAY_TABLES of them kept
ENCODED_BYTES_PER_PIXEL = 7  # the largest encodings: raw_rgb8 + raw_f32


def memory_plan(settings: MapSettings, budget_mb: int, keyframe_bytes: int, frame_pixels: int = 1920 * 1080,
                ingest_queue: int = 2) -> dict:
    """Split the byte budget: fixed parts first, keyframes get what is left (at least 8).
    ``frame_pixels``: the largest frame admitted (``max_frame_pixels``): its decode and mapping
    scratch, the ray tables of a few cameras that size, and the queued encoded frames."""
    f = settings.field
    tables = 0
    for log2, levels, feats in ((f.geo_log2_table, f.geo_levels, f.geo_features),
                                (f.tex_log2_table, f.tex_levels, f.tex_features)):
        rows = levels * (1 << log2)
        tables += rows * feats * 4 * 4 + rows  # table, Adam m, v, gradient scratch; touched flags
    per_voxel = 370  # keys, index, 8 vertex ids, trained rays, ~1.5 vertices (key, prior, Adam, seen_behind), texture
    voxels = settings.voxels.max_voxels * per_voxel
    snapshot = tables // 4 + voxels // 2  # a query's frozen copy: the tables and the voxel map
    budget = int(budget_mb) << 20
    working = max(64 << 20, budget * 15 // 100)  # scratch of one mesh / render query (meshes above it are refused)
    checkpoint = tables * 3 // 4 + voxels // 2  # the state captured for the checkpoint writer
    frames = frame_pixels * (FRAME_SCRATCH_BYTES_PER_PIXEL + RAY_TABLES * RAY_TABLE_BYTES_PER_PIXEL
                             + (ingest_queue + 1) * ENCODED_BYTES_PER_PIXEL)
    # observed free space at its cap (keys, sorted keys, ids), twice: the map and a query's copy
    free = 2 * 24 * settings.free_space.max_cells if settings.free_space.enabled else 0
    # fine free-space votes at the voxel cap, one byte a cell: the map's and the checkpoint's copy (a
    # query's map copy shares the map's)
    votes = 2 * settings.voxels.max_voxels * settings.votes.cells_per_side(settings.voxels.voxel_size) ** 3
    # the fused colour base at its cap: the map's (a query's map copy shares it) and the checkpoint's rows
    base = settings.color_base.nbytes()
    base = base + settings.color_base.max_cells * ROW_BYTES
    # the residual check's kept probes, the map's and the checkpoint's (D53-14)
    base += 2 * KEPT_BYTES if settings.color_base.enabled and settings.render.checked_residual else 0
    left = budget - tables - voxels - snapshot - working - checkpoint - frames - free - votes - base
    cap = max(8, left // max(1, keyframe_bytes))  # keyframes of the largest frame, at least 8
    return {"budget": budget, "hash_tables": tables, "voxels_at_cap": voxels, "query_snapshot": snapshot,
            "query_working_set": working, "checkpoint_capture": checkpoint, "frame_buffers": frames,
            "free_space": free, "cell_votes": votes, "color_base": base,
            "keyframes": max(0, left),
            "keyframe_bytes": keyframe_bytes, "max_keyframes": int(cap),
            "keyframe_cap_bytes": max(left, 8 * keyframe_bytes),  # the keyframe set's byte cap (max_bytes)
            "fits": left >= 8 * keyframe_bytes}


def keyframe_bytes(settings: MapSettings, frame_pixels: int = 640 * 480) -> int:
    """Bytes one keyframe of ``frame_pixels`` keeps (:class:`~h3edge.mapping.keyframes.StoredFrame`),
    with, on the torch backend, its copy for the ray draw on the device
    (:class:`~h3edge.mapping.device_frames.DeviceFrame`: the valid-pixel counts; on a GPU its images
    too)."""
    kept = frame_pixels * (3 + 2) + 4096  # RGB, uint16 depth; voxel ids and scores
    if settings.field.backend == "torch":
        kept += -(-frame_pixels // CHUNK) * 8 + (0 if settings.mapper.device == "cpu" else frame_pixels * (3 + 2))
    return kept
