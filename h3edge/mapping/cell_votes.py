"""Fine free-space votes: inside every allocated leaf voxel, a grid of small cells (1 cm by default)
that every mapped frame's full-resolution depth votes on, as a TSDF fuses its signs.

Why: a band sample behind its own ray's measured depth takes a negative SDF target. Behind a thin
object (a chair's slats, a shelf's edge) those targets lie in the space other views see through,
and they fill it (research/silhouettes.md). A test against the views of one training batch, from
their pooled depth (``train.carve_behind``, measured and replaced by these votes, D49-1), is blind
within a few pixels of an outline, and a batch holds few views. These votes keep what every frame
saw, at every pixel:

- a cell whose centre projects onto valid depth more than ``margin`` beyond it gains a vote (the
  ray passed through it);
- a cell within ``behind`` behind the measured depth loses one (where the band puts its targets).

A band sample behind the depth whose cell's net vote is at least ``min_votes`` takes no SDF target
(:class:`h3edge.mapping.trainer.Trainer`): the majority of the frames that looked at the cell
saw through it. Each frame's vote is one per cell (the pixel its centre falls on), so many frames
that saw a cell free outvote a few that put it just behind a surface, and noise that reads a
surface a little too far now and then does not carve it.

Cost: one int8 a cell (1,000 bytes a 10 cm voxel at 1 cm cells); per frame one parallel pass over
the cells of the voxels in the view frustum (:mod:`h3edge.mapping._vote_kernel`), or over one in
``interleave`` of them, the next frames over the others (at 30 Hz consecutive frames see nearly the
same cells; x86-cpu votes on half a frame, D53-19).

Usage::

    votes = CellVotes(VoteConfig(cell=0.01), voxel_size=0.1, behind=0.05)
    votes.mark(voxels, depth, intrinsics, pose)         # per frame, after allocation
    free = votes.seen_free(vox, frac)                   # (N,) bool for located points
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import torch

from h3edge.geometry.camera import Intrinsics, invert_pose
from h3edge.mapping.trilinear import corner_weights
from h3edge.mapping.voxels import VoxelMap, unpack

MAX_CELLS_PER_SIDE = 32  # 32 KB of votes a voxel
DEVICE_TRIES = 8  # random cells drawn per wanted point by the device draw (sample_free_tensor)


@dataclass(frozen=True)
class VoteConfig:
    cell: float = 0.0
    """m, side of a vote cell (0: no votes, the paper's: every band sample behind the depth is a target); must divide
    the leaf voxel into whole cells"""
    margin: float = 0.03
    """m beyond a cell the measured depth must lie for a free vote (noise, pose error)"""
    min_votes: int = 1
    """net votes (free minus just-behind) for a cell to count as seen free"""
    interleave: int = 1
    """frames that share one full vote: each votes on the cells whose indices in the voxel (a, b, c) have (a + b + c) %
    interleave equal to its count % interleave; 1: every cell every frame (paper: no votes)"""
    points: int = 0
    """points per training step drawn in cells seen free, where the field must not read inside (weights.seen_free); 0:
    the votes only take band targets away"""

    def __post_init__(self) -> None:
        if not (self.cell >= 0):
            raise ValueError(f"votes.cell must be >= 0 m, got {self.cell}")
        if not (self.margin >= 0):
            raise ValueError(f"votes.margin must be >= 0 m, got {self.margin}")
        if not 1 <= self.min_votes <= 127:
            raise ValueError(f"votes.min_votes must be in 1..127, got {self.min_votes}")
        if self.interleave < 1:
            raise ValueError(f"votes.interleave must be >= 1, got {self.interleave}")
        if self.points < 0:
            raise ValueError(f"votes.points must be >= 0, got {self.points}")

    def cells_per_side(self, voxel_size: float) -> int:
        """Cells along a leaf voxel's side (0: votes off); ValueError unless ``cell`` divides the
        voxel into at most ``MAX_CELLS_PER_SIDE`` cells a side (1 byte a cell)."""
        if self.cell == 0:
            return 0
        n = int(round(voxel_size / self.cell))
        if n < 1 or abs(n * self.cell - voxel_size) > 1e-6:
            raise ValueError(f"votes.cell {self.cell} m does not divide the {voxel_size} m voxel")
        if n > MAX_CELLS_PER_SIDE:
            raise ValueError(f"votes.cell {self.cell} m: {n} cells a voxel side, more than {MAX_CELLS_PER_SIDE}")
        return n


class CellVotes:
    """Net free votes per cell of every allocated voxel (rows by voxel id); ``mark`` per frame,
    ``seen_free`` per training step."""

    def __init__(self, cfg: VoteConfig, voxel_size: float, behind: float, max_voxels: int = 1 << 62):
        self.cfg, self.voxel_size, self.behind = cfg, voxel_size, behind
        self.n = cfg.cells_per_side(voxel_size)
        self.max_voxels = max_voxels  # the map's voxel cap: storage never grows past it
        self._store = np.zeros((0, self.n ** 3), np.int8)  # rows by voxel id, capacity >= rows
        self.rows = 0
        self._frames = 0  # frames marked: which of the interleaved cell sets the next frame votes on
        # the votes on a training device other than the host (:meth:`on_device`): the mirror and the
        # rows marked since it was last brought up to date
        self._mirror: torch.Tensor | None = None
        self._dirty: list[np.ndarray] = []
        self._dirty_lock = threading.Lock()

    def __getstate__(self) -> dict:  # copies take the votes, not the device mirror or its lock
        state = dict(self.__dict__)
        state.update(_mirror=None, _dirty=[])
        state.pop("_dirty_lock")
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._dirty_lock = threading.Lock()

    @property
    def votes(self) -> np.ndarray:
        """(voxels voted on, cells) int8 net free votes (a view of the storage)."""
        return self._store[:self.rows]

    @votes.setter
    def votes(self, value: np.ndarray) -> None:
        self._store, self.rows = np.asarray(value, np.int8), len(value)
        with self._dirty_lock:
            self._mirror, self._dirty = None, []

    @property
    def enabled(self) -> bool:
        return self.n > 0

    @property
    def nbytes(self) -> int:
        return self._store.nbytes

    def _grow(self, n_voxels: int) -> None:
        """Rows for ``n_voxels`` voxels; the storage doubles (up to the voxel cap), so a growing
        map copies its votes O(log n) times, not every frame."""
        if n_voxels > len(self._store):
            cap = max(n_voxels, min(2 * len(self._store), self.max_voxels))
            grown = np.zeros((cap, self.n ** 3), np.int8)
            grown[:self.rows] = self._store[:self.rows]
            self._store = grown
        self.rows = max(self.rows, n_voxels)

    def mark(self, voxels: VoxelMap, depth: np.ndarray, intr: Intrinsics, pose: np.ndarray) -> int:
        """Vote with one frame: ``depth`` cleaned z-depth (0 = invalid) measured from ``pose``
        (camera to world) on the voxels of ``voxels``; returns how many voxels were in view."""
        if not self.enabled or len(voxels) == 0:
            return 0
        from h3edge.mapping import _vote_kernel as k

        self._grow(len(voxels))
        corners = unpack(voxels.voxel_keys).astype(np.float64) * self.voxel_size
        w2c = invert_pose(np.asarray(pose, np.float64))
        rot, trans = np.ascontiguousarray(w2c[:3, :3]), np.ascontiguousarray(w2c[:3, 3])
        h, w = depth.shape
        seen = np.empty(len(corners), np.bool_)
        k.in_view(corners, rot, trans, intr.fx, intr.fy, intr.cx, intr.cy, w, h, self.voxel_size, seen)
        ids = np.flatnonzero(seen)
        if len(ids):
            k.vote_cells(np.ascontiguousarray(corners[ids]), ids, self._store, np.ascontiguousarray(depth, np.float32),
                         rot, trans, intr.fx, intr.fy, intr.cx, intr.cy, self.cfg.cell, self.n,
                         self.cfg.margin, self.behind, self.cfg.interleave, self._frames % self.cfg.interleave)
            with self._dirty_lock:  # after the write: a mirror update that copied a half-written row copies it again
                if self._mirror is not None:
                    self._dirty.append(ids)
        self._frames += 1
        return len(ids)

    def on_device(self, device: torch.device) -> torch.Tensor:
        """The votes (rows, cells) int8 on ``device``: on the host a view of the storage; elsewhere
        a mirror brought up to date with the rows :meth:`mark` wrote since the last call (one
        host-to-device copy of those rows; the whole storage when the mirror is first made or
        outgrown). Never a device-to-host copy."""
        device = torch.device(device)
        if device.type == "cpu":
            return torch.from_numpy(self._store[:self.rows])
        return self._mirrored(device)

    def _mirrored(self, device: torch.device) -> torch.Tensor:
        """The votes in a mirror on ``device``, brought up to date (:meth:`on_device`)."""
        with self._dirty_lock:
            mirror, dirty, self._dirty = self._mirror, self._dirty, []
            rows = self.rows
            if mirror is None or mirror.device != device or len(mirror) < rows:
                self._mirror = mirror = torch.from_numpy(self._store).to(device, copy=True)
                dirty = []
        if dirty:
            ids = np.unique(np.concatenate(dirty))
            mirror[torch.from_numpy(ids).to(device)] = torch.from_numpy(self._store[ids]).to(device)
        return mirror[:rows]

    def seen_free_tensor(self, votes: torch.Tensor, vox: torch.Tensor, frac: torch.Tensor) -> torch.Tensor:
        """:meth:`seen_free` in torch on the points' device: ``votes`` from :meth:`on_device`, ``vox``
        (N,) int64 voxel ids (-1: none), ``frac`` (N, 3) positions in the voxel; (N,) bool."""
        ok = (vox >= 0) & (vox < len(votes))
        if not self.enabled or len(votes) == 0:
            return torch.zeros_like(ok)
        c = (frac * self.n).floor().long().clamp(0, self.n - 1)
        flat = (c[:, 0] * self.n + c[:, 1]) * self.n + c[:, 2]
        return ok & (votes[torch.where(ok, vox, 0), flat] >= self.cfg.min_votes)

    def seen_free(self, vox: np.ndarray, frac: np.ndarray) -> np.ndarray:
        """(N,) bool: the cell at each located point (``vox`` voxel id, -1 = none; ``frac`` its
        position in the voxel, [0, 1]^3, as :meth:`VoxelMap.locate` returns) has at least
        ``min_votes`` net free votes."""
        return self.seen_free_tensor(torch.from_numpy(self.votes), torch.from_numpy(np.asarray(vox, np.int64)),
                                     torch.from_numpy(np.asarray(frac))).numpy()  # the one rule, on the host

    def seen_free_points(self, voxels: VoxelMap, pts: np.ndarray, vox: np.ndarray) -> np.ndarray:
        """(N,) bool: :meth:`seen_free` at world points ``pts`` (N, 3) metres located in voxel ids
        ``vox`` (N,) of ``voxels`` (-1: none)."""
        out = np.zeros(len(vox), bool)
        ok = np.flatnonzero((vox >= 0) & (vox < min(len(self.votes), len(voxels))))
        if not self.enabled or len(ok) == 0:
            return out
        frac = pts[ok] / self.voxel_size - unpack(voxels.voxel_keys[vox[ok]])
        out[ok] = self.seen_free(vox[ok], frac)
        return out

    def sample_free_tensor(self, n: int, voxels: VoxelMap, generator: torch.Generator,
                           near_prior: float = 1.0, tries: int = DEVICE_TRIES
                           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`sample_free` on the generator's device in fixed-shape tensor operations (no host
        transfer, no sync): ``tries * n`` random (voxel, cell) pairs, and of those that pass (votes
        and prior as there) ``n`` at random; (n, 3) world points, (n,) voxel ids and (n, 3) positions
        in the voxel, the voxel id -1 where fewer than ``n`` passed (callers mask those)."""
        dev = generator.device
        votes = self.on_device(dev)
        rows = min(len(votes), len(voxels))
        if not self.enabled or n <= 0 or rows == 0:
            return (torch.zeros((0, 3), device=dev), torch.zeros(0, dtype=torch.long, device=dev),
                    torch.zeros((0, 3), device=dev))
        m, cells = tries * n, self.n ** 3
        row = torch.randint(0, rows, (m,), generator=generator, device=dev)
        cell = torch.randint(0, cells, (m,), generator=generator, device=dev)
        ijk = torch.stack([cell // (self.n * self.n), (cell // self.n) % self.n, cell % self.n], 1)
        centre = (ijk.to(torch.float32) + 0.5) / self.n
        corners = voxels.device_index(dev).voxel_vertices
        prior = (voxels.priors.detach()[corners[row]] * corner_weights(centre)).sum(1)
        passed = (votes[row, cell] >= self.cfg.min_votes) & (prior < near_prior)
        key = torch.rand(m, generator=generator, device=dev) + (~passed).to(torch.float32)  # passed first
        pick = torch.topk(key, min(n, m), largest=False).indices
        ok = passed[pick]
        jitter = torch.rand((len(pick), 3), generator=generator, device=dev)
        frac = (ijk[pick].to(torch.float32) + jitter) / self.n
        vox = torch.where(ok, row[pick], -1)
        origin = voxels.device_index(dev).origins[row[pick]]
        pts = (origin + frac.to(torch.float64) * self.voxel_size).to(torch.float32)
        return pts, vox, frac

    def sample_free(self, n: int, voxels: VoxelMap, generator: torch.Generator | None = None,
                    near_prior: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Up to ``n`` world points (P, 3), each uniform inside a cell drawn uniformly (with
        replacement) among the map's cells with at least ``min_votes`` net free votes whose centre's
        SDF prior reads less than ``near_prior`` (truncation units: near a surface the priors put
        there, where a wrong inside can be; open space reads +1); with their voxel ids (P,) and
        positions in the voxel (P, 3), as :meth:`VoxelMap.locate` returns them. Rejection from
        random cells, at most ``64 n`` tries, in one numba pass
        (:func:`h3edge.mapping._vote_kernel.draw_free_cells`): O(n), not O(map). The kernel reads
        the priors on the host: on CPU a view, on CUDA one copy a call of 4 bytes a vertex (at most
        8 a voxel: <= 12.8 MB at orin-agx's 400,000-voxel cap, a few MB in practice), the order of
        the step's own host copy of its sample points for :meth:`VoxelMap.locate`."""
        rows = min(len(self.votes), len(voxels))
        if not self.enabled or n <= 0 or rows == 0:
            return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 3))
        from h3edge.mapping import _vote_kernel as k

        dev = generator.device if generator is not None else "cpu"
        seed = int(torch.randint(0, 2 ** 31 - 1, (1,), generator=generator, device=dev))
        priors = np.ascontiguousarray(voxels.priors.detach().cpu().numpy(), np.float32)
        pick = k.draw_free_cells(self.votes[:rows], voxels.voxel_vertices, priors, self.n,
                                 self.cfg.min_votes, np.float32(near_prior), n, 64 * n, seed)
        jitter = torch.rand((len(pick), 3), generator=generator, device=dev, dtype=torch.float64).cpu().numpy()
        vox, cell = np.divmod(pick, self.n ** 3)
        frac = (np.stack(np.unravel_index(cell, (self.n,) * 3), 1) + jitter) / self.n
        pts = (unpack(voxels.voxel_keys[vox]) + frac) * self.voxel_size
        return pts, vox, frac

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"votes": self.votes.copy()}

    def load_state_dict(self, arrays: dict[str, np.ndarray]) -> None:
        """Restore saved votes; a state saved without votes, or at another cell size, starts with
        none (every cell undecided)."""
        v = arrays.get("votes")
        ok = v is not None and v.ndim == 2 and v.shape[1] == self.n ** 3
        self.votes = np.asarray(v, np.int8).copy() if ok else np.zeros((0, self.n ** 3), np.int8)

