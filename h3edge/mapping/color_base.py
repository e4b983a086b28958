"""The fused colour base under the colour field: fine surface cells whose colour every integrated
frame updates as a running average, as TSDF fusion does, read back wherever the field is coloured.

Why: the texture hash grids learn colour only through training steps, and their finest level fills
up at a few square metres of surface; at the camera's rate most frames get no step at all. A
colour per surface centimetre, fused at integration, renders a room's texture the moment a frame
has seen it (TSDF colour at 1 cm: 24.4 dB on a photographic room, 20.9 at 2 cm, 18.2 at 4 cm), and
the neural colour field learns only what the base cannot hold (view-consistent shading, sub-cell
detail, unseen cells).

Cells (``cell`` metres a side) live in 4^3 blocks, as a TSDF's voxel block grid: an open-addressed
hash table of the blocks and each block's 64 cells in consecutive rows
(:mod:`h3edge.mapping._color_base_kernel`), at most ``max_cells`` / 24 blocks (the points of frames
that would reach further blocks are refused and counted). A frame is fused in two passes. First its
valid pixels (every ``stride``-th in both axes; more at depths where those would lie > 2 cells
apart) reach the points at their measured depth and ``band`` cells in front of and behind it along
their ray, and the blocks those fall in (made where new). Then, as TSDF fusion does, every cell of
those blocks whose centre projects into a pixel with depth fuses that pixel once: a cell held
already where its centre lies within ``trunc`` of that depth, in front or behind (D53-13: each
frame that sees a cell near its surface updates it, not only those whose sparse pixel samples
fell into it; on the real set a surface cell's colour averaged a few noisy frames), and a new one
where it lies within the ``band`` + 1/2 cells the pixels reach (cells exist only where depth put a
surface, in the volume the render weights live in). A cell takes the colour where the surface point
nearest its centre projects (its foot on the plane the pixel's neighbours ``normal_px`` away span,
D53-12; the centre's own projection, as TSDF fusion takes it, blurs the base by up to the centre's
distance from the surface times the tangent of each view's incidence). Colour is read with
trilinear weights between cell centres, renormalised over the cells that hold one (or, in a gap
between fused pixels, the mean of the known cells around).

Each cell also fuses its centre's signed distance in front of that pixel's depth (along the fusing
camera's z axis), a TSDF whose band is the colour's: :meth:`ColorBase.sample_distance` reads it,
and a render (``render.base_surface``, :mod:`h3edge.mapping.raymarch`) places a surface at its zero
crossing where the field has not (yet) put one there: the geometry every integrated frame measured,
before training catches up.

Composition (:func:`compose`): where the base knows a colour b, the field's colour is
sigmoid(logit(b) + z - z0) with z the colour MLP's logit and z0 its logit at zero texture features
(what a texture cell no step has reached reads), i.e. the MLP's output acts as odds multiplying the
base's, relative to its output where it has learned nothing: a cell the texture grids have not
learned renders the base unchanged; elsewhere the MLP's colour is used as it is.

Cost: a block is 1,312 bytes (64 rows of RGB + weight + distance, its key, touch stamp and slots at most a
quarter full); a frame's band fills 27-32 cells of a block (loft, real: 41 MB for the real set's 1.0 M cells), and
the memory plan counts 24 (54 bytes a cell). On the real set on this 2-core machine, fusing a 640x480 frame at
stride 3 with band 1 takes 2.9 ms to reach ~6,000 blocks and 8.1 ms to fuse their cells (11 ms; 10.5 ms before
D53-13, which fused only the cells the pixels reached, through a hash table of cells). A cell's lookup is one
probe of the block table (small: it stays in cache) and its row sits beside its block's other cells; the plane
a cell's colour is taken on is computed once a block and reused for every cell whose pixel lies on it.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from h3edge.geometry.camera import Intrinsics
from h3edge.mapping._color_base_kernel import (
    distance_volume,
    fuse_cells,
    held_cells,
    load_cells,
    reach_blocks,
    rebuild_block_slots,
    sample_cells,
    sample_distance,
)

# block slots per block, at least: the slot table at most a quarter full. Most reads miss (a render's
# search samples in front of the surface), and a miss walks the run of occupied slots from its home
_SLOTS_PER_BLOCK = 4
ROW_BYTES = 28  # a held cell in a checkpoint: key 8 + RGB 12 + weight 4 + signed distance 4
ROW_BLOCK_BYTES = 20  # a cell's row in the table: RGB 12 + weight 4 + signed distance 4 (held or not)
BLOCK_BYTES = 64 * ROW_BLOCK_BYTES + 8 + 8 + 4 * _SLOTS_PER_BLOCK  # a 4^3 block: its 64 rows, key, stamp, slots
PLANNED_CELLS_PER_BLOCK = 24  # blocks at most max_cells / this (a frame's band fills 27-32 a block: loft, real)
BYTES_PER_CELL = BLOCK_BYTES // PLANNED_CELLS_PER_BLOCK  # at the block cap
REACH_CELLS = 2.0  # fused pixels lie at most this many cells apart on the surface (the reads bridge gaps)
_MIN_BLOCKS = 1 << 12  # blocks at least (5.4 MB)


@dataclass(frozen=True)
class ColorBaseConfig:
    cell: float = 0.0
    """m, side of a fused colour cell (0: no base, the paper's: colour only from the trained field)"""
    band: int = 1
    """cells in front of and behind each measured depth along its ray that take its colour"""
    stride: int = 3
    """pixel stride (both axes) of the pixels a frame fuses, at most: less at depths where the fused pixels would lie
    more than 2 cells apart on the surface"""
    max_cells: int = 4_000_000
    """cells planned at most: the base holds up to max_cells / 24 4^3 blocks of cells (BYTES_PER_CELL a cell
    there); the points of frames that would reach further blocks are refused and counted"""
    max_weight: float = 64.0
    """observations a cell's running average remembers (lighting drift)"""
    normal_px: int = 4
    """px: a cell takes the colour where the surface point nearest its centre projects, on the plane the reaching
    pixel's neighbours this far away span (0: where its centre projects, as TSDF fusion; 1-2 px normals, noisier,
    cost the photographic scene about 0.2 dB); paper: no base; D53-12"""
    trunc: float = 0.04
    """m: a frame fuses its colour and signed distance into every cell it sees with its centre this near its
    depth, in front or behind (in the 4^3 blocks its pixels reach), once a frame; Open3D's TSDF peer: 0.04 (4
    voxels); paper: no base; D53-13"""
    fuse_edges: bool = False
    """fuse the near side of depth edges too, which ``mapper.edge_radius`` leaves out of the rest of the map (the
    outline of a foreground object); paper: no base (false); D53-11"""
    interleave: int = 1
    """frames one round of cell fusion is spread over: a frame fuses the cells (i, j, k) with (i + j + k) %
    interleave equal to its count % interleave, the next frames the others (its blocks are reached every frame);
    1: every cell every frame; paper: no base"""

    def __post_init__(self) -> None:
        if not self.cell >= 0:
            raise ValueError(f"color_base.cell must be >= 0 m (0: off), got {self.cell}")
        if self.band < 0 or self.stride < 1 or self.max_cells < 1 or not self.max_weight >= 1 or self.normal_px < 0:
            raise ValueError("color_base: band >= 0, stride >= 1, max_cells >= 1, max_weight >= 1 and normal_px >= 0 "
                             "are required")
        if not self.trunc > 0:
            raise ValueError(f"color_base.trunc must be > 0 m, got {self.trunc}")
        if self.interleave < 1:
            raise ValueError(f"color_base.interleave must be >= 1, got {self.interleave}")

    @property
    def enabled(self) -> bool:
        return self.cell > 0

    def nbytes(self) -> int:
        """Bytes of the base at its cap (0 when off)."""
        return BYTES_PER_CELL * self.max_cells if self.enabled else 0


class ColorBase:
    """The fused colour cells (host numpy arrays; CPU numba kernels) in 4^3 blocks, as a voxel block
    grid: :meth:`fuse` per integrated frame, :meth:`sample` wherever colour is read."""

    def __init__(self, cfg: ColorBaseConfig):
        self.cfg = cfg
        self.n = 0  # cells held (weight > 0)
        self.refused = 0  # points of frames whose block the block cap refused
        self._frames = 0  # frames fused (the blocks' touch stamps)
        self._fused = 0  # frames fused: which of the interleaved cell sets the next frame fuses
        self.nblocks = 0  # blocks held
        self._alloc(min(_MIN_BLOCKS, self.max_blocks))

    @property
    def max_blocks(self) -> int:
        """Blocks at most: ``max_cells`` / :data:`PLANNED_CELLS_PER_BLOCK` (at least :data:`_MIN_BLOCKS`)."""
        return max(_MIN_BLOCKS, self.cfg.max_cells // PLANNED_CELLS_PER_BLOCK)

    def _alloc(self, blocks: int) -> None:
        """Room for ``blocks`` blocks, the blocks held kept (new arrays: a reader holding the old ones
        keeps them whole)."""
        nb_ = self.nblocks
        bkeys, cells = np.zeros(blocks, np.int64), np.zeros((64 * blocks, 5), np.float32)
        stamp = np.full(blocks, -1, np.int64)  # the frame that last touched each block
        if nb_:
            bkeys[:nb_], cells[:64 * nb_], stamp[:nb_] = self.bkeys[:nb_], self.cells[:64 * nb_], self.stamp[:nb_]
        capacity = 1 << max(1, int(np.ceil(np.log2(_SLOTS_PER_BLOCK * blocks))))
        bslots = rebuild_block_slots(bkeys, nb_, capacity)
        # what readers on other threads take, in one assignment: a slot table and the arrays it indexes
        self._table = (bslots, bkeys, cells)
        self.bslots, self.bkeys, self.cells, self.stamp = bslots, bkeys, cells, stamp  # row: R, G, B, weight, distance

    def __len__(self) -> int:
        return self.n

    @property
    def nbytes(self) -> int:
        return self.bkeys.nbytes + self.bslots.nbytes + self.cells.nbytes + self.stamp.nbytes

    def fuse(self, color: np.ndarray, depth: np.ndarray, intr: Intrinsics, c2w: np.ndarray) -> None:
        """Fuse colour uint8 (H, W, 3) at depth float32 (H, W) metres (0 = invalid), camera-to-world
        ``c2w`` (4x4, OpenCV optical), host arrays."""
        c = self.cfg
        pose = np.asarray(c2w, np.float64)
        rot, trans = np.ascontiguousarray(pose[:3, :3]), np.ascontiguousarray(pose[:3, 3])
        depth = np.ascontiguousarray(depth, np.float32)
        reach = REACH_CELLS * c.cell * min(intr.fx, intr.fy)
        fx, fy, cx, cy = float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy)
        while True:  # until the block table held every block the frame reached (or is at its cap)
            touched = np.empty(len(self.bkeys), np.int32)
            grow = len(self.bkeys) < self.max_blocks
            self.nblocks, ntouched, refused, full = reach_blocks(
                self.bslots, self.bkeys, self.cells, self.nblocks, depth, rot, trans, fx, fy, cx, cy, c.stride, reach,
                c.cell, c.band, self.stamp, self._frames, touched, grow)
            self._frames += 1  # (a pass run again touches every block afresh)
            self.refused += refused
            if not full:
                break
            self._alloc(min(self.max_blocks, 2 * len(self.bkeys)))
        self.n += fuse_cells(touched[:ntouched], self.bkeys, self.cells, depth, np.ascontiguousarray(color, np.uint8),
                             rot, trans, fx, fy, cx, cy, c.cell, c.band, c.trunc, c.max_weight, c.normal_px,
                             c.interleave, self._fused % c.interleave)
        self._fused += 1

    def sample(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Colour (N, 3) float32 in [0, 1] at world points (N, 3) metres and whether the base knows
        it there (N,) bool, on the points' device (read on the host)."""
        p = points.detach().to("cpu", torch.float64).numpy()
        out = np.zeros((len(p), 3), np.float32)
        known = np.zeros(len(p), np.bool_)
        if self.n and len(p):
            sample_cells(*self._table, p, self.cfg.cell, out, known)
        dev = points.device
        return torch.from_numpy(out).to(dev), torch.from_numpy(known).to(dev)

    def sample_distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fused signed distance (N,) float64 metres (positive in front of the surface, along the
        viewing rays that fused it) at world points (N, 3) metres, and where the base knows it (N,)
        bool: within about a cell of a fused surface (``band`` + 1/2 cells). Host arrays."""
        p = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        out = np.zeros(len(p), np.float64)
        known = np.zeros(len(p), np.bool_)
        if self.n and len(p):
            # every fused cell counts: requiring 2, 4 or 8 observations cost the sim scene's last
            # frame 0.2-1.1 dB and gained the real set nothing once seen-free cells are lifted (D53-4)
            sample_distance(*self._table, p, self.cfg.cell, out, known)
        return out, known

    def distances(self) -> FusedDistances:
        """A read-only handle on the fused signed distances as they are now, for meshing
        (:class:`FusedDistances`: the base's own table, no copy of its cells)."""
        return FusedDistances(self)

    def state_dict(self) -> dict[str, np.ndarray]:
        """The cells held as host arrays (keys int64 (N,) (packed cell coordinates,
        :func:`h3edge.mapping.voxels.pack`), rgb float32 (N, 3) in [0, 1], weight float32 (N,), signed
        distance float32 (N,) m) and the refused count; what a checkpoint holds of the base."""
        keys, rows = held_cells(self.bkeys, self.cells, self.nblocks)
        return {"keys": keys, "rgb": rows[:, :3].copy(), "weight": rows[:, 3].copy(), "distance": rows[:, 4].copy(),
                "refused": np.asarray(self.refused, np.int64)}

    def load_state_dict(self, arrays: dict[str, np.ndarray]) -> None:
        """Take what :meth:`state_dict` captured (empty ``arrays``: an empty base)."""
        if "keys" not in arrays:
            arrays = {"keys": np.zeros(0, np.int64), "rgb": np.zeros((0, 3), np.float32),
                      "weight": np.zeros(0, np.float32), "distance": np.zeros(0, np.float32)}
        keys = np.asarray(arrays["keys"], np.int64).reshape(-1)
        # a state from before the distances: NaN, none known (the colours still are)
        distance = arrays.get("distance", np.full(len(keys), np.nan, np.float32))
        rows = np.concatenate([np.asarray(arrays["rgb"], np.float32).reshape(-1, 3),
                               np.asarray(arrays["weight"], np.float32).reshape(-1, 1),
                               np.asarray(distance, np.float32).reshape(-1, 1)], axis=1)
        if len(rows) != len(keys):
            raise ValueError(f"colour base state: {len(keys)} keys but {len(rows)} rows")
        keep = rows[:, 3] > 0
        keys, rows = keys[keep], rows[keep]
        blocks = max(_MIN_BLOCKS, len(np.unique(keys_to_blocks(keys))))
        if blocks > self.max_blocks:
            raise ValueError(f"colour base of {blocks} blocks exceeds max_cells / {PLANNED_CELLS_PER_BLOCK} "
                             f"({self.max_blocks})")
        self.nblocks = 0
        self._alloc(min(self.max_blocks, 2 * blocks))  # room to grow
        self.nblocks = load_cells(self.bslots, self.bkeys, self.cells, keys, rows)
        self.n = len(keys)
        self.refused = int(arrays.get("refused", 0))


def keys_to_blocks(keys: np.ndarray) -> np.ndarray:
    """Packed keys of the 4^3 blocks holding the cells of packed ``keys`` (N,) int64."""
    from h3edge.mapping.voxels import pack, unpack

    return pack(unpack(keys) >> 2)


class FusedDistances:
    """The fused signed distances of a :class:`ColorBase`, read in place from the arrays it held
    when this was taken: its cells a batch at a time (:meth:`batches`: the blocks held then) and
    dense volumes of them by block lookups (:meth:`volume`: what the table holds at the read). What
    a mesh fills the cubes it leaves out from (:func:`~h3edge.mapping.mesh.left_out_surface`,
    D53-9), in scratch that does not grow with the base. Safe beside :meth:`ColorBase.fuse` on
    another thread (the slot table and the arrays it indexes are taken together, and a base that
    grows moves to new arrays: these stay whole); a cell fused meanwhile may read at its old or new
    value."""

    def __init__(self, base: ColorBase):
        self._table = base._table
        self.bkeys, self.cells = self._table[1], self._table[2]
        self.nblocks = min(base.nblocks, len(self.bkeys))
        self.n = base.n
        self.cell = base.cfg.cell  # m, a cell's side

    def __len__(self) -> int:
        return self.n

    def batches(self, rows: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """The cells held, about ``rows`` at a time: integer coordinates (n, 3) int64 (centre ``(ijk +
        1/2) * cell`` m) and fused signed distance (n,) float32 m (NaN where a cell holds none)."""
        from h3edge.mapping.voxels import unpack

        step = max(1, rows // 64)  # blocks a batch
        for b in range(0, self.nblocks, step):
            e = min(self.nblocks, b + step)
            keys, held = held_cells(self.bkeys[b:e], self.cells[64 * b:64 * e], e - b)
            if len(keys):
                yield unpack(keys), held[:, 4].copy()

    def volume(self, origin: np.ndarray, size: int) -> np.ndarray:
        """The fused signed distance (size, size, size) float32 m of the cells ``origin + (a, b, c)``
        (``origin`` (3,) int cell coordinates), NaN where no cell holds one."""
        out = np.empty((size,) * 3, np.float32)
        o = np.asarray(origin, np.int64).reshape(3)
        distance_volume(*self._table, int(o[0]), int(o[1]), int(o[2]), out)
        return out


_EPS = 1.0 / 512  # the base's colour is kept inside (eps, 1 - eps) so that its odds stay finite


def compose(field_rgb: torch.Tensor, base_rgb: torch.Tensor, known: torch.Tensor,
            neutral: torch.Tensor | None = None, gain: float = 1.0) -> torch.Tensor:
    """sigmoid(logit(base) + gain (logit(field) - logit(neutral))) where ``known``, ``field_rgb``
    elsewhere; (N, 3) in [0, 1]. ``neutral`` (1, 3) or (N, 3): the field colour that leaves the base
    unchanged (default 0.5); the field passes the colour MLP's output at zero texture features, so
    that a global tint the MLP learns early (real set, last frame: 0.43 / 0.45 / 0.43 after 33 steps)
    does not darken every surface the texture grids have not learned yet (D53-8). ``gain`` in [0, 1]:
    how much of the field's residual over the base is applied (training: 1; renders: what fresh
    frames confirm, :mod:`h3edge.mapping.residual_check`)."""
    b = base_rgb.clamp(_EPS, 1 - _EPS)
    n = (torch.full_like(b[:1], 0.5) if neutral is None else neutral).clamp(_EPS, 1 - _EPS)
    if gain == 1.0:  # odds products: finite wherever the field saturates, and their gradients too
        odds = field_rgb * b * (1 - n)
        rest = (1 - field_rgb) * (1 - b) * n
        mixed = odds / (odds + rest)
    else:
        f = field_rgb.clamp(_EPS * _EPS, 1 - _EPS * _EPS)
        mixed = torch.sigmoid(torch.logit(b) + gain * (torch.logit(f) - torch.logit(n)))
    return torch.where(known[:, None], mixed, field_rgb)
