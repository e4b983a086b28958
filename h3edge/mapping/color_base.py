"""The fused colour base under the colour field: fine surface cells whose colour every integrated
frame updates as a running average, as TSDF fusion does, read back wherever the field is coloured.

Why: the texture hash grids learn colour only through training steps, and their finest level fills
up at a few square metres of surface; at the camera's rate most frames get no step at all. A
colour per surface centimetre, fused at integration, renders a room's texture the moment a frame
has seen it (TSDF colour at 1 cm: 24.4 dB on a photographic room, 20.9 at 2 cm, 18.2 at 4 cm), and
the neural colour field learns only what the base cannot hold (view-consistent shading, sub-cell
detail, unseen cells).

Cells (``cell`` metres a side) exist only where depth put a surface: each frame's valid pixels
(every ``stride``-th in both axes; more at depths where those would lie > 2 cells apart) reach
the cells at their measured depth and ``band`` cells in front of and behind it along their ray
(the volume the render weights live in); each cell reached takes the colour of the pixel that the
surface point nearest its centre projects into (its foot on the plane the pixel's neighbours
``normal_px`` away span, D53-12; the reaching ray's own colour blurs the base by up to a cell, more
at grazing angles, and the centre's projection, as TSDF fusion takes it, by up to the centre's
distance from the surface times the tangent of each view's incidence). The cells live in an open-addressed hash table
(:mod:`h3edge.mapping._color_base_kernel`), at most ``max_cells`` of them (new cells past it are
refused and counted). Colour is read with trilinear weights between cell centres, renormalised over
the cells that hold one (or, in a gap between fused pixels, the mean of the known cells around).

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

Cost: 44 bytes a cell (a key, one RGB + weight + distance row, and the slot table at most a quarter full); a
640x480 frame at stride 3 with band 1 touches ~100k cells (5-10 ms in one numba pass on this
2-core machine). The pass is bound by memory latency, so the layout keeps a cell's lookup to few
cache lines: a probe starts where its 4^3 block's cells sit side by side in the slot table, and a
cell's colour, weight and distance share a row (a warm frame re-fused on the photographic scene: 10.6 ->
7.5 and 9.8 -> 9.0 ms).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from h3edge.geometry.camera import Intrinsics
from h3edge.mapping._color_base_kernel import distance_volume, fuse_frame, rebuild_slots, sample_cells, sample_distance

# slots per row, at least: the slot table at most a quarter full. Most reads miss (a render's search
# samples in front of the surface), and a miss walks the run of occupied slots from its home, which
# the 4^3 blocks' neighbouring homes make long at half load: a restored real map (878k cells), 1M
# points read at load 0.42 / 0.21 / 0.10: 2.52 / 0.53 / 0.35 s, its render 48 -> 22 s at 0.10
_SLOTS_PER_ROW = 4
ROW_BYTES = 28  # a cell's row: key 8 + RGB 12 + weight 4 + signed distance 4 (what a checkpoint holds)
BYTES_PER_CELL = ROW_BYTES + 4 * _SLOTS_PER_ROW  # the row and its slots
REACH_CELLS = 2.0  # fused pixels lie at most this many cells apart on the surface (the reads bridge gaps)
_MIN_ROWS = 1 << 15


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
    """cells at most (BYTES_PER_CELL each); new ones past it are refused"""
    max_weight: float = 64.0
    """observations a cell's running average remembers (lighting drift)"""
    normal_px: int = 4
    """px: a cell takes the colour where the surface point nearest its centre projects, on the plane the reaching
    pixel's neighbours this far away span (0: where its centre projects, as TSDF fusion; 1-2 px normals, noisier,
    cost the photographic scene about 0.2 dB); paper: no base; D53-12"""
    fuse_edges: bool = False
    """fuse the near side of depth edges too, which ``mapper.edge_radius`` leaves out of the rest of the map (the
    outline of a foreground object); paper: no base (false); D53-11"""

    def __post_init__(self) -> None:
        if not self.cell >= 0:
            raise ValueError(f"color_base.cell must be >= 0 m (0: off), got {self.cell}")
        if self.band < 0 or self.stride < 1 or self.max_cells < 1 or not self.max_weight >= 1 or self.normal_px < 0:
            raise ValueError("color_base: band >= 0, stride >= 1, max_cells >= 1, max_weight >= 1 and normal_px >= 0 "
                             "are required")

    @property
    def enabled(self) -> bool:
        return self.cell > 0

    def nbytes(self) -> int:
        """Bytes of the base at its cap (0 when off)."""
        return BYTES_PER_CELL * self.max_cells if self.enabled else 0


class ColorBase:
    """The fused colour cells (host numpy arrays; CPU numba kernels). :meth:`fuse` per integrated
    frame, :meth:`sample` wherever colour is read."""

    def __init__(self, cfg: ColorBaseConfig):
        self.cfg = cfg
        self.n = 0  # rows in use
        self.refused = 0  # new cells refused at max_cells
        self._alloc(min(_MIN_ROWS, cfg.max_cells))

    def _alloc(self, rows: int) -> None:
        keys, cells = np.zeros(rows, np.int64), np.zeros((rows, 5), np.float32)
        if self.n:
            keys[:self.n], cells[:self.n] = self.keys[:self.n], self.cells[:self.n]
        self.keys, self.cells = keys, cells  # a cell's row: R, G, B in [0, 1], weight, signed distance (m)
        capacity = 1 << max(1, int(np.ceil(np.log2(_SLOTS_PER_ROW * rows))))
        self.slots = rebuild_slots(self.keys, self.n, capacity)

    def __len__(self) -> int:
        return self.n

    @property
    def nbytes(self) -> int:
        return self.keys.nbytes + self.cells.nbytes + self.slots.nbytes

    def fuse(self, color: np.ndarray, depth: np.ndarray, intr: Intrinsics, c2w: np.ndarray) -> None:
        """Fuse colour uint8 (H, W, 3) at depth float32 (H, W) metres (0 = invalid), camera-to-world
        ``c2w`` (4x4, OpenCV optical), host arrays."""
        c = self.cfg
        worst = depth.size * (2 * c.band + 1)  # every pixel at stride 1
        if self.n + worst > len(self.keys) and len(self.keys) < c.max_cells:
            self._alloc(min(c.max_cells, max(2 * len(self.keys), self.n + worst)))
        pose = np.asarray(c2w, np.float64)
        reach = REACH_CELLS * c.cell * min(intr.fx, intr.fy)
        self.n, refused = fuse_frame(self.slots, self.keys, self.cells, self.n,
                                     np.ascontiguousarray(depth, np.float32), np.ascontiguousarray(color, np.uint8),
                                     np.ascontiguousarray(pose[:3, :3]), np.ascontiguousarray(pose[:3, 3]),
                                     float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy),
                                     c.stride, reach, c.cell, c.band, c.max_weight, c.normal_px)
        self.refused += refused

    def sample(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Colour (N, 3) float32 in [0, 1] at world points (N, 3) metres and whether the base knows
        it there (N,) bool, on the points' device (read on the host)."""
        p = points.detach().to("cpu", torch.float64).numpy()
        out = np.zeros((len(p), 3), np.float32)
        known = np.zeros(len(p), np.bool_)
        if self.n and len(p):
            sample_cells(self.slots, self.keys, self.cells, p, self.cfg.cell, out, known)
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
            sample_distance(self.slots, self.keys, self.cells, p, self.cfg.cell, out, known)
        return out, known

    def distances(self) -> FusedDistances:
        """A read-only handle on the fused signed distances as they are now, for meshing
        (:class:`FusedDistances`: the base's own table, no copy of its cells)."""
        return FusedDistances(self)

    def state_dict(self) -> dict[str, np.ndarray]:
        """The cells in use as host arrays (keys int64 (N,), rgb float32 (N, 3) in [0, 1], weight
        float32 (N,), signed distance float32 (N,) m) and the refused count; what a checkpoint holds
        of the base."""
        return {"keys": self.keys[:self.n].copy(), "rgb": self.cells[:self.n, :3].copy(),
                "weight": self.cells[:self.n, 3].copy(), "distance": self.cells[:self.n, 4].copy(),
                "refused": np.asarray(self.refused, np.int64)}

    def load_state_dict(self, arrays: dict[str, np.ndarray]) -> None:
        """Take what :meth:`state_dict` captured (empty ``arrays``: an empty base)."""
        if "keys" not in arrays:
            arrays = {"keys": np.zeros(0, np.int64), "rgb": np.zeros((0, 3), np.float32),
                      "weight": np.zeros(0, np.float32), "distance": np.zeros(0, np.float32)}
        keys = np.asarray(arrays["keys"], np.int64)
        if len(keys) > self.cfg.max_cells:
            raise ValueError(f"colour base of {len(keys)} cells exceeds color_base.max_cells ({self.cfg.max_cells})")
        self.n = len(keys)
        self.keys = keys
        # a state from before the distances: NaN, none known (the colours still are)
        distance = arrays.get("distance", np.full(self.n, np.nan, np.float32))
        self.cells = np.concatenate([np.asarray(arrays["rgb"], np.float32).reshape(-1, 3),
                                     np.asarray(arrays["weight"], np.float32).reshape(-1, 1),
                                     np.asarray(distance, np.float32).reshape(-1, 1)], axis=1)
        self._alloc(max(min(_MIN_ROWS, self.cfg.max_cells), self.n))  # room to grow, the slots rebuilt
        self.refused = int(arrays.get("refused", 0))


class FusedDistances:
    """The fused signed distances of a :class:`ColorBase`, read in place from the arrays it held
    when this was taken: its cells a batch at a time (:meth:`batches`: the rows in use then) and
    dense volumes of them by hash lookups (:meth:`volume`: what the table holds at the read). What
    a mesh fills the cubes it leaves out from (:func:`~h3edge.mapping.mesh.left_out_surface`,
    D53-9), in scratch that does not grow with the base. Safe beside :meth:`ColorBase.fuse` on
    another thread (the slot table is taken before the rows it indexes, and a base that grows
    moves to new arrays: these stay whole); a cell fused meanwhile may read at its old or new value."""

    def __init__(self, base: ColorBase):
        self.slots = base.slots  # first: the rows it indexes are in the arrays taken after it
        self.keys, self.cells = base.keys, base.cells
        self.n = min(base.n, len(self.keys), len(self.cells))
        self.cell = base.cfg.cell  # m, a cell's side

    def __len__(self) -> int:
        return self.n

    def batches(self, rows: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """The cells, ``rows`` at a time: integer coordinates (n, 3) int64 (centre ``(ijk + 1/2) *
        cell`` m) and fused signed distance (n,) float32 m, NaN where a cell holds none."""
        from h3edge.mapping.voxels import unpack

        for s in range(0, self.n, rows):
            part = self.cells[s:min(self.n, s + rows)]
            dist = part[:, 4].copy()
            dist[~(part[:, 3] > 0)] = np.nan
            yield unpack(self.keys[s:s + len(part)]), dist

    def volume(self, origin: np.ndarray, size: int) -> np.ndarray:
        """The fused signed distance (size, size, size) float32 m of the cells ``origin + (a, b, c)``
        (``origin`` (3,) int cell coordinates), NaN where no cell holds one."""
        out = np.empty((size,) * 3, np.float32)
        o = np.asarray(origin, np.int64).reshape(3)
        distance_volume(self.slots, self.keys, self.cells, int(o[0]), int(o[1]), int(o[2]), out)
        return out


_EPS = 1.0 / 512  # the base's colour is kept inside (eps, 1 - eps) so that its odds stay finite


def compose(field_rgb: torch.Tensor, base_rgb: torch.Tensor, known: torch.Tensor,
            neutral: torch.Tensor | None = None) -> torch.Tensor:
    """sigmoid(logit(base) + logit(field) - logit(neutral)) where ``known``, ``field_rgb`` elsewhere;
    (N, 3) in [0, 1]. ``neutral`` (1, 3) or (N, 3): the field colour that leaves the base unchanged
    (default 0.5); the field passes the colour MLP's output at zero texture features, so that a
    global tint the MLP learns early (real set, last frame: 0.43 / 0.45 / 0.43 after 33 steps) does
    not darken every surface the texture grids have not learned yet (D53-8)."""
    b = base_rgb.clamp(_EPS, 1 - _EPS)
    odds = field_rgb * b
    rest = (1 - field_rgb) * (1 - b)
    if neutral is not None:
        n = neutral.clamp(_EPS, 1 - _EPS)
        odds, rest = odds * (1 - n), rest * n
    mixed = odds / (odds + rest)
    return torch.where(known[:, None], mixed, field_rgb)
