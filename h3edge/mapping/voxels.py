"""Sparse leaf voxels with optimisable SDF priors at their vertices (the coarse level of H2/H3).

Leaf voxels of side ``voxel_size`` are allocated where a frame's back-projected valid depth puts
at least ``min_points`` points, plus the face neighbour when the voxel's mean point lies within
``neighbour_margin`` (a fraction of the side) of that face. Voxels and their 8 corner vertices
have stable ids in insertion order (append-only arrays, so optimiser state indexed by id stays
valid as the map grows); int64 keys (coordinates packed 21 bits per axis) are found through a
sorted index with ``searchsorted``, so the map is unbounded in space. Inserting k voxels costs
O(k log k) plus an O(map) memory move, never a rebuild. A voxel cap bounds memory; voxels past it
are refused and counted.

SDF priors are stored in truncation units (metres / ``truncation``), as the authors do. A vertex
is initialised once, projectively: prior = (measured depth - vertex z) / truncation, when it lies
within ``init_range`` of the surface (or anywhere in front of it, truncated to ``prior_clamp``, when
that is set) and projects inside the image onto valid depth, only when all 8 corners of its voxel
do (the paper). With ``prior_retry`` every frame retries the unset vertices of the voxels it
observes, as the authors' code does (one try at allocation fails most of the time on real depth,
which has holes at every edge). Until then a vertex reads ``unset_prior``.
The coarse SDF of a point is the trilinear interpolation of its voxel's 8 priors.

Every frame also records, per vertex of the voxels it observes, how far behind its measured
surface it saw the vertex (``seen_behind``, the least over frames): the meshes and distance queries
trust the field only within ``observed_behind`` of a surface some frame saw
(:meth:`~h3edge.mapping.raymarch.PriorLookup.support`).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import torch

from h3edge.geometry.camera import Intrinsics, backproject, project
from h3edge.mapping.sparse_adam import lazy_adam_rows
from h3edge.mapping.trilinear import CORNERS, corner_weights, corners_on

_BITS = 21
_OFF = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def pack(ijk: np.ndarray) -> np.ndarray:
    """Integer coordinates (N, 3) -> int64 keys (order-preserving along z, then y, then x)."""
    v = ijk.astype(np.int64) + _OFF
    if (v < 0).any() or (v > _MASK).any():
        raise ValueError("voxel coordinate outside the +-2^20 range")
    return (v[:, 2] << (2 * _BITS)) | (v[:, 1] << _BITS) | v[:, 0]


def unpack(keys: np.ndarray) -> np.ndarray:
    return np.stack([keys & _MASK, (keys >> _BITS) & _MASK, (keys >> (2 * _BITS)) & _MASK], -1) - _OFF


def lookup(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Index of each key in ``sorted_keys``, -1 where absent."""
    if len(sorted_keys) == 0:
        return np.full(len(keys), -1, np.int64)
    i = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return np.where(sorted_keys[i] == keys, i, -1)


def points_by_voxel(points: np.ndarray, voxel_size: float, every: int = 1
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The voxels that hold ``points`` (N, 3; rows with NaN are skipped): their packed keys
    (sorted), point counts, coordinate sums (K, 3) and how many of their points are among every
    ``every``-th point (of the rows not skipped, from the first). One pass through a hash table."""
    from h3edge.mapping import _march_kernels as k

    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    pts = np.ascontiguousarray(points, np.float64)
    cap = 1 << 14
    while True:
        hkeys = np.full(cap, -1, np.int64)
        counts, sums, picked = np.zeros(cap, np.int64), np.zeros((cap, 3), np.float64), np.zeros(cap, np.int64)
        used = k.voxel_point_stats(pts, float(voxel_size), hkeys, counts, sums, int(every), picked)
        if used == -2:
            raise ValueError("voxel coordinate outside the +-2^20 range")
        if used >= 0:
            break
        cap *= 4
    slots = np.flatnonzero(hkeys >= 0)
    order = np.argsort(hkeys[slots])
    slots = slots[order]
    return hkeys[slots], counts[slots], sums[slots], picked[slots]


class KeyIndex:
    """Append-only key -> id map (ids in insertion order) over a sorted index. An insertion replaces
    the arrays, never writes into them, so a reader on another thread sees the old index or the new."""

    def __init__(self) -> None:
        self.keys = np.zeros(0, np.int64)  # by id
        self.index = (np.zeros(0, np.int64), np.zeros(0, np.int64))  # (sorted keys, the id of each)

    def __len__(self) -> int:
        return len(self.keys)

    def find(self, keys: np.ndarray) -> np.ndarray:
        """Ids of ``keys``, -1 where absent."""
        sorted_keys, ids = self.index
        if len(sorted_keys) == 0:
            return np.full(len(keys), -1, np.int64)
        i = lookup(sorted_keys, keys)
        return np.where(i >= 0, ids[np.maximum(i, 0)], -1)

    def state_dict(self) -> np.ndarray:
        """The keys by id (the sorted index is rebuilt from them)."""
        return self.keys.copy()

    def load_state_dict(self, keys: np.ndarray) -> None:
        order = np.argsort(keys, kind="stable")
        self.keys, self.index = keys.astype(np.int64), (keys[order].astype(np.int64), order.astype(np.int64))

    def add(self, new_keys: np.ndarray) -> np.ndarray:
        """Append keys that are not present yet (unique, absent); returns their ids."""
        ids = np.arange(len(self.keys), len(self.keys) + len(new_keys))
        order = np.argsort(new_keys)
        sorted_keys, sorted_ids = self.index
        pos = np.searchsorted(sorted_keys, new_keys[order])
        self.index = (np.insert(sorted_keys, pos, new_keys[order]), np.insert(sorted_ids, pos, ids[order]))
        self.keys = np.concatenate([self.keys, new_keys])
        return ids


@dataclass(frozen=True)
class VoxelConfig:
    voxel_size: float = 0.1
    """m, octree leaf size (paper / authors: 0.1)"""
    min_points: int = 10
    """depth points needed to allocate a voxel (authors: > 10)"""
    neighbour_margin: float = 0.1
    """allocate the face neighbour when the mean point is this close"""
    truncation: float = 0.05
    """m, SDF truncation = the unit SDF priors are stored in"""
    init_range: float = 0.245
    """m, sqrt(6) * voxel: vertices farther from the surface stay unset"""
    max_voxels: int = 200_000
    """cap (the authors' num_vertexes budget); memory bound"""
    prior_retry: bool = True
    """Retry, in every frame, the unset vertices of the voxels that frame observes (the authors' code does; one try at
    allocation leaves most priors unset on real depth with holes)"""
    prior_clamp: float = 0.0
    """truncation units: c > 0 sets priors to the projective SDF clamped to [-c, c] (as TSDF fusion), vertices seen
    more than init_range in front of the surface to +c; paper 0 (those vertices stay unset); D0-4"""
    unset_prior: float = 0.0
    """the value an unset prior reads as, truncation units (0 reads as "on the surface")"""
    observed_behind: float = float("inf")
    """m: meshes and distance queries trust the field only where some frame saw at most this far behind its measured
    surface (deeper, training never reaches and back shells form); authors inf (no limit); D0-3"""



class VoxelMap:
    """Leaf voxels and vertices with stable ids; SDF priors (a torch tensor) indexed by vertex id.

    ``voxel_vertices`` maps each voxel id to its 8 vertex ids. ``priors`` is replaced by a longer
    tensor when vertices are added (ids of existing vertices are unchanged, so an optimiser's
    per-element state can be carried over by padding).
    """

    def __init__(self, cfg: VoxelConfig = VoxelConfig(), device: str | torch.device = "cpu"):
        self.cfg = cfg
        self.device = torch.device(device)
        self.voxels = KeyIndex()
        self.vertices = KeyIndex()
        self.voxel_vertices = np.zeros((0, 8), np.int64)
        self.priors = torch.zeros(0, device=self.device, requires_grad=True)  # truncation units
        self.prior_set = np.zeros(0, bool)
        # m, per vertex: the least depth behind a frame's measured surface at which a frame saw it
        # (negative: in front of it); +inf: never seen on valid depth (see observed_behind)
        self.seen_behind = np.zeros(0, np.float32)
        # training rays whose measured surface point fell in each voxel (by voxel id): how far the
        # field has trained there, which decides where a render trusts the fused base over it
        self._trained = np.zeros(0, np.float32)
        self._trained_pending: torch.Tensor | None = None  # counts a training step added on the device, not yet read
        self.refused = 0  # voxels not allocated because of the cap
        self._table: tuple[np.ndarray, VoxelTable] | None = None  # (the keys it indexes, the table)
        # the lookup training uses: True on the torch backend (the index on the map's device,
        # :meth:`locate_tensor`), False on the numba backend (:meth:`locate`, on the host); set by the engine
        self.device_lookup = False
        # locate_tensor's default: compact the points on a face (True), or fixed shapes (False);
        # None: by device (compact on the CPU). Counting a GPU's syncs on a CPU sets False.
        self.compact_lookup: bool | None = None
        self._device_index: tuple[np.ndarray, np.ndarray, DeviceIndex] | None = None  # (keys, corners, index)

    def __len__(self) -> int:
        return len(self.voxels)

    def state_dict(self) -> tuple[dict, dict[str, np.ndarray]]:
        """(meta, arrays): voxel and vertex keys, corner ids, priors and their flags."""
        arrays = {"keys": self.voxels.state_dict(), "vertex_keys": self.vertices.state_dict(),
                  "voxel_vertices": self.voxel_vertices.copy(), "priors": self.priors.detach().cpu().numpy().copy(),
                  "prior_set": self.prior_set.copy(),
                  "seen_behind": self.seen_behind.copy(), "trained": self.trained.copy()}
        return {"voxels_refused": self.refused}, arrays

    def frozen_copy(self) -> VoxelMap:
        """An independent copy for queries (priors detached, no gradient)."""
        out = copy.copy(self)
        out.voxels, out.vertices = copy.deepcopy(self.voxels), copy.deepcopy(self.vertices)
        out.voxel_vertices = self.voxel_vertices.copy()
        out.priors = self.priors.detach().clone()
        out.prior_set = self.prior_set.copy()
        out.seen_behind = self.seen_behind.copy()
        out._trained, out._trained_pending = self.trained.copy(), None
        out._device_index = None
        return out

    def load_state_dict(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        self.voxels.load_state_dict(arrays["keys"])
        self.vertices.load_state_dict(arrays["vertex_keys"])
        self.voxel_vertices = arrays["voxel_vertices"].astype(np.int64)
        self.priors = torch.from_numpy(np.asarray(arrays["priors"], np.float32)).to(self.device).requires_grad_(True)
        self.prior_set = arrays["prior_set"].astype(bool)
        # a state from before the record: every vertex counts as seen (the support it was saved with)
        self.seen_behind = (arrays["seen_behind"].astype(np.float32) if "seen_behind" in arrays
                            else np.full(len(self.prior_set), -np.inf, np.float32))
        # a state from before the count: every voxel counts as trained (renders keep the field's surface)
        self.trained = (arrays["trained"].astype(np.float32) if "trained" in arrays
                        else np.full(len(self.voxel_vertices), np.inf, np.float32))
        if self.trained.shape != (len(self.voxel_vertices),):
            raise ValueError(f"voxel state: {self.trained.shape} trained-ray counts for "
                             f"{len(self.voxel_vertices)} voxels")
        self.refused = int(meta["voxels_refused"])

    @property
    def voxel_keys(self) -> np.ndarray:
        return self.voxels.keys

    @property
    def vertex_keys(self) -> np.ndarray:
        return self.vertices.keys

    def allocate(self, depth: np.ndarray, intr: Intrinsics, c2w: np.ndarray, points: np.ndarray | None = None
                 ) -> np.ndarray:
        """Allocate voxels seen by a frame; returns the keys of the newly created voxels.
        ``points``: the frame's world back-projection (H, W, 3), when the caller already has it."""
        return self.allocate_observing(depth, intr, c2w, points)[0]

    def allocate_observing(self, depth: np.ndarray, intr: Intrinsics, c2w: np.ndarray,
                           points: np.ndarray | None = None, every: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`allocate`, and the ids (sorted, int64) of the allocated voxels that hold one of
        every ``every``-th valid pixel's point (row-major, from the first): what the frame observes,
        from the same pass over its points (as :meth:`locate` places those points, but for a point
        within ``1e-5`` voxels of a face, which :meth:`locate` may give the voxel across it).
        ``depth`` float32 (H, W) z-depth in metres (0 = invalid), ``c2w`` (4, 4) camera-to-world
        (OpenCV optical), ``points`` its world back-projection (H, W, 3) metres if the caller has it;
        host numpy arrays. Returns (new voxel keys int64 (K,), observed voxel ids int64 (M,))."""
        pts = (backproject(depth, intr, c2w) if points is None else points).reshape(-1, 3)
        keys, counts, sums, picked = points_by_voxel(pts, self.cfg.voxel_size, every)
        if len(keys) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        observed_keys = keys[picked > 0]
        ok = counts >= self.cfg.min_points
        # mean point inside each voxel, in voxel units relative to its corner
        frac = sums / (counts[:, None] * self.cfg.voxel_size) - unpack(keys)
        cand = [keys[ok]]
        m = self.cfg.neighbour_margin
        base = unpack(keys[ok])
        for axis in range(3):
            for side, near in ((-1, frac[ok, axis] < m), (1, frac[ok, axis] > 1 - m)):
                nb = base[near].copy()
                nb[:, axis] += side
                cand.append(pack(nb))
        cand = np.unique(np.concatenate(cand))
        new = cand[self.voxels.find(cand) < 0]  # the sorted index answers; no re-sort of the map
        room = self.cfg.max_voxels - len(self.voxel_keys)
        if len(new) > room:
            self.refused += len(new) - max(room, 0)
            new = new[:max(room, 0)]
        if len(new):
            self._insert(new)
        ids = self.voxels.find(cand)
        ids = ids[ids >= 0]  # the allocated voxels this frame observes
        # their vertices' projective SDF, once: the record and the priors' retry both read it
        vid = np.unique(self.voxel_vertices[ids].reshape(-1))
        sdf, valid = self._projective_sdf(vid, depth, intr, c2w)
        self._record_seen(vid, sdf, valid)
        if self.cfg.prior_retry:  # every voxel this frame sees that still has an unset vertex
            todo = ids[~self.prior_set[self.voxel_vertices[ids]].all(1)]
        else:
            todo = self.voxels.find(new)
        if len(todo):
            self._init_priors(todo, vid, sdf, valid)
        observed = self.voxels.find(observed_keys)
        return new, np.sort(observed[observed >= 0])

    @property
    def trained(self) -> np.ndarray:
        """(V,) float32 on the host: training rays counted in each voxel (by id). Reading it folds in
        the counts training steps added on the device since the last read (one device-to-host copy
        a read, never one a step); read it under the map's lock (a training step adds counts
        under it)."""
        if self._trained_pending is not None:
            pending, self._trained_pending = self._trained_pending, None
            self._trained[:len(pending)] += pending.cpu().numpy()
        return self._trained

    @property
    def trained_nbytes(self) -> int:
        """Bytes of the trained-ray counts, read without folding the device's (no lock needed)."""
        return self._trained.nbytes

    @trained.setter
    def trained(self, value: np.ndarray) -> None:
        self._trained, self._trained_pending = value, None

    def count_trained(self, voxel_ids: np.ndarray | torch.Tensor) -> None:
        """Add one trained ray to each voxel in ``voxel_ids`` (int64, -1: none; repeats count): a
        numpy array counts on the host; a tensor counts on its device in fixed-shape operations (no
        host transfer) until :attr:`trained` is read."""
        n = len(self._trained)
        if isinstance(voxel_ids, torch.Tensor):
            pending = self._trained_pending
            if pending is None or pending.device != voxel_ids.device:
                self.trained  # noqa: B018 - folds what another device counted
                pending = torch.zeros(n, dtype=torch.float32, device=voxel_ids.device)
            elif len(pending) < n:  # voxels added since: their counts start at 0
                pending = torch.cat([pending, pending.new_zeros(n - len(pending))])
            ok = (voxel_ids >= 0) & (voxel_ids < n)
            self._trained_pending = pending.index_add_(0, torch.where(ok, voxel_ids, 0), ok.to(torch.float32))
            return
        ids = voxel_ids[(voxel_ids >= 0) & (voxel_ids < n)]
        if len(ids):
            u, c = np.unique(ids, return_counts=True)
            self._trained[u] += c

    def _record_seen(self, vid: np.ndarray, sdf: np.ndarray, valid: np.ndarray) -> None:
        """Lower ``seen_behind`` of vertices ``vid`` to how far behind this frame's measured surface
        they lie (``-sdf``), where they project onto valid depth."""
        seen = vid[valid]
        self.seen_behind[seen] = np.minimum(self.seen_behind[seen], -sdf[valid].astype(np.float32))

    def _insert(self, new_keys: np.ndarray) -> None:
        self.voxels.add(new_keys)
        corner_keys = pack((unpack(new_keys)[:, None, :] + CORNERS[None]).reshape(-1, 3))
        ids = self.vertices.find(corner_keys)
        missing = ids < 0
        fresh = np.unique(corner_keys[missing])
        fresh_ids = self.vertices.add(fresh)
        ids[missing] = fresh_ids[np.searchsorted(fresh, corner_keys[missing])]
        self.voxel_vertices = np.concatenate([self.voxel_vertices, ids.reshape(-1, 8)])
        # pending device counts stay pending (they cover the first voxels; no host copy at integration)
        self._trained = np.concatenate([self._trained, np.zeros(len(new_keys), np.float32)])
        grown = torch.full((len(fresh),), float(self.cfg.unset_prior), device=self.device)
        self.priors = torch.cat([self.priors.detach(), grown]).requires_grad_(True)  # a new leaf
        self.prior_set = np.concatenate([self.prior_set, np.zeros(len(fresh), bool)])
        self.seen_behind = np.concatenate([self.seen_behind, np.full(len(fresh), np.inf, np.float32)])

    def _projective_sdf(self, vertex_ids: np.ndarray, depth: np.ndarray, intr: Intrinsics, c2w: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
        """(measured depth - vertex z in metres, projects inside the image onto valid depth)."""
        pos = unpack(self.vertex_keys[vertex_ids]) * self.cfg.voxel_size
        uv, z = project(pos.astype(np.float64), intr, c2w)
        with np.errstate(invalid="ignore"):
            inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < intr.width) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.height)
        d = np.zeros(len(z))
        ui = np.clip(np.nan_to_num(uv[:, 0]), 0, intr.width - 1).astype(int)
        vi = np.clip(np.nan_to_num(uv[:, 1]), 0, intr.height - 1).astype(int)
        d[inside] = depth[vi[inside], ui[inside]]
        return d - z, inside & (d > 0)

    def _init_priors(self, voxel_ids: np.ndarray, frame_vid: np.ndarray, frame_sdf: np.ndarray,
                     frame_valid: np.ndarray) -> None:
        """Projective priors for the unset vertices of ``voxel_ids`` (see the module docstring), from
        this frame's projective SDF ``frame_sdf`` / ``frame_valid`` of the sorted vertices ``frame_vid``
        (which hold every corner of ``voxel_ids``)."""
        vid = self.voxel_vertices[voxel_ids]  # (n, 8)
        at = np.searchsorted(frame_vid, vid.reshape(-1))
        sdf, valid = frame_sdf[at], frame_valid[at]
        with np.errstate(invalid="ignore"):
            known = np.abs(sdf) < self.cfg.init_range
            if self.cfg.prior_clamp > 0:  # far in front of the surface: free, set to +clamp below
                known |= sdf > 0
            good = valid & known
        ok = np.repeat(good.reshape(-1, 8).all(1), 8)  # a voxel's 8 priors together (paper)
        targets = vid.reshape(-1)[ok]
        values = sdf[ok] / self.cfg.truncation
        if self.cfg.prior_clamp > 0:
            values = np.clip(values, -self.cfg.prior_clamp, self.cfg.prior_clamp)
        fresh = ~self.prior_set[targets]  # set once per vertex
        if fresh.any():
            t = torch.from_numpy(targets[fresh]).to(self.device)
            self.priors.data[t] = torch.from_numpy(values[fresh].astype(np.float32)).to(self.device)
            self.prior_set[targets[fresh]] = True

    def locate(self, points: np.ndarray, eps: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
        """Voxel id of each point (-1 outside the map) and its position inside that voxel in [0, 1]^3.

        A point on a voxel face (within ``eps`` voxels) belongs to either voxel sharing it: if the
        voxel ``floor`` picks is not allocated, the neighbour across that face is tried. Priors are
        shared at vertices, so the trilinear value is the same from both sides; this is what lets
        mesh extraction evaluate lattice points on the surface of the allocated region.
        One parallel pass through the voxel hash table (:meth:`table`).
        """
        from h3edge.mapping import _march_kernels as k

        pts = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        vox = np.full(len(pts), -1, np.int64)
        frac = np.empty((len(pts), 3), np.float64)
        tab = self.table()  # an empty map's table finds nothing: every point -1, frac from floor
        k.locate_cells(pts, tab.hkeys, tab.hids, float(self.cfg.voxel_size), float(eps), vox, frac)
        return vox, frac

    def locate_points(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`locate` of world points (N, 3) metres, a tensor: voxel ids (N,) int64 and positions
        in the voxel (N, 3) float32, on ``points``' device. With ``device_lookup`` (the torch backend)
        the lookup runs there (:meth:`locate_tensor`, no host transfer); otherwise the numba kernel
        runs on the host."""
        if self.device_lookup:
            return self.locate_tensor(points)
        vox, frac = self.locate(points.detach().cpu().numpy())
        return (torch.from_numpy(vox).to(points.device),
                torch.from_numpy(frac.astype(np.float32)).to(points.device))

    def locate_tensor(self, points: torch.Tensor, eps: float = 1e-5, compact: bool | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`locate`'s rule in torch on ``points``' device (N, 3) metres: voxel ids (N,) int64
        (-1 outside) and positions in the voxel (N, 3) float32 in [0, 1]. The sorted key index on the
        device answers with ``searchsorted``; a point on a face tries the up to 7 voxels across the
        faces it lies on, all in fixed-shape tensor operations (no host transfer, no sync); ``compact``
        (default: ``compact_lookup``, else on the CPU, where there is no device to stall) tries them
        only for the points on a face of a missing voxel."""
        index = self.device_index(points.device)
        p = points.detach().to(torch.float64).reshape(-1, 3) / self.cfg.voxel_size
        finite = torch.isfinite(p).all(1)
        p = torch.where(finite[:, None], p, torch.zeros_like(p))
        g = torch.floor(p)
        vox, corner = index.find(g), g
        if len(index.sorted_keys):
            a = torch.round(p)
            on = (p - a).abs() < eps
            compact = self.compact_lookup if compact is None else compact
            if p.device.type == "cpu" if compact is None else compact:
                sub = torch.nonzero((vox < 0) & on.any(1)).squeeze(1)
                v, c = _across_faces(index, g[sub], a[sub], on[sub], vox[sub], g[sub])
                vox, corner = vox.index_copy(0, sub, v), corner.index_copy(0, sub, c)
            else:  # fixed shapes: every point tries the candidates (no sync)
                vox, corner = _across_faces(index, g, a, on, vox, corner)
        vox = torch.where(finite, vox, torch.full_like(vox, -1))
        frac = (p - corner).clamp(0.0, 1.0).to(torch.float32)
        return vox, frac

    def device_index(self, device: torch.device) -> DeviceIndex:
        """The sorted voxel keys, their ids, the voxels' corner ids and origins on ``device``, rebuilt
        (one host-to-device copy) when voxels were added since. Safe beside an insertion on another
        thread: it indexes only voxels whose corners are already recorded."""
        keys, vv = self.voxels.keys, self.voxel_vertices
        cached = self._device_index
        if cached is None or cached[0] is not keys or cached[1] is not vv or \
                cached[2].sorted_keys.device != torch.device(device):
            sorted_keys, ids = self.voxels.index
            known = ids < min(len(vv), len(keys))
            index = DeviceIndex(torch.from_numpy(sorted_keys[known]).to(device),
                                torch.from_numpy(ids[known]).to(device), torch.from_numpy(vv).to(device),
                                torch.from_numpy(unpack(keys[:len(vv)]) * self.cfg.voxel_size).to(device))
            self._device_index = cached = (keys, vv, index)
        return cached[2]

    def coarse_sdf(self, points: torch.Tensor, located: tuple[torch.Tensor, torch.Tensor] | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        """Trilinear prior SDF (truncation units) at points (N, 3) and a mask of points in a voxel
        (0 outside); ``located`` = :meth:`locate_points`' answer for these points (tensors on their
        device), when the caller has it."""
        vox, frac = self.locate_points(points) if located is None else located
        inside = vox >= 0
        if len(self.voxel_vertices) == 0:  # an empty map: every point is outside
            return torch.zeros(len(points), dtype=self.priors.dtype, device=points.device), inside
        corners = self.device_index(points.device).voxel_vertices
        vid = corners[vox.clamp(min=0)]
        w = corner_weights(frac.to(torch.float32))  # (N, 8)
        return (self.priors[vid] * w).sum(1) * inside, inside

    def table(self) -> VoxelTable:
        """Open-addressed hash table of the voxel ids (constant-time lookups for ray marching, in
        memory proportional to the voxel count wherever the voxels are) and their bounding box.
        Built once per set of voxels (voxels are only ever added, which replaces the key array)."""
        keys = self.voxels.keys
        if self._table is None or self._table[0] is not keys:
            self._table = (keys, _build_table(keys))
        return self._table[1]


def _build_table(voxel_keys: np.ndarray) -> VoxelTable:
    from h3edge.mapping import _march_kernels as k

    n = len(voxel_keys)
    cap = 1 << max(4, int(np.ceil(np.log2(2 * max(n, 1)))))  # load factor <= 1/2
    hkeys = np.full(cap, -1, np.int64)
    hids = np.full(cap, -1, np.int32)
    if n == 0:
        return VoxelTable(hkeys, hids, np.zeros(3, np.int64), np.zeros(3, np.int64))
    k.build_table(np.ascontiguousarray(voxel_keys, np.int64), hkeys, hids)
    ijk = unpack(voxel_keys)
    return VoxelTable(hkeys, hids, ijk.min(0).astype(np.int64), ijk.max(0).astype(np.int64) + 1)


def _across_faces(index: DeviceIndex, g: torch.Tensor, a: torch.Tensor, on: torch.Tensor, vox: torch.Tensor,
                  corner: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Where ``vox`` < 0: the first allocated voxel across the faces each point lies on (``on``, per
    axis; ``g`` its floor cell, ``a`` its rounded coordinates), in :func:`cell_of`'s order, and that
    voxel's corner; the others unchanged."""
    for c in range(8):
        bits = corners_on(g.device)[1][c]
        cand = torch.where(on, torch.where(bits, a, a - 1), g)
        found = index.find(cand)
        take = (vox < 0) & ~(bits & ~on).any(1) & (found >= 0)
        vox, corner = torch.where(take, found, vox), torch.where(take[:, None], cand, corner)
    return vox, corner


@dataclass(frozen=True)
class DeviceIndex:
    """The voxel key index as tensors on one device: packed keys sorted, the voxel id of each, and
    the 8 corner vertex ids of every voxel (by id)."""

    sorted_keys: torch.Tensor  # (V,) int64
    ids: torch.Tensor  # (V,) int64
    voxel_vertices: torch.Tensor  # (V, 8) int64
    origins: torch.Tensor  # (V, 3) float64: each voxel's lower corner, metres

    def find(self, ijk: torch.Tensor) -> torch.Tensor:
        """Voxel ids (N,) int64 of integer coordinates ``ijk`` (N, 3) (float or int), -1 where
        not allocated or outside the packable +-2^20 range."""
        n = len(self.sorted_keys)
        if n == 0:
            return torch.full((len(ijk),), -1, dtype=torch.long, device=ijk.device)
        v = ijk.to(torch.float64) + _OFF
        ok = ((v >= 0) & (v <= _MASK)).all(1)
        v = torch.where(ok[:, None], v, torch.zeros_like(v)).to(torch.long)
        keys = (v[:, 2] << (2 * _BITS)) | (v[:, 1] << _BITS) | v[:, 0]
        i = torch.searchsorted(self.sorted_keys, keys).clamp(max=n - 1)
        return torch.where(ok & (self.sorted_keys[i] == keys), self.ids[i], torch.full_like(keys, -1))


@dataclass(frozen=True)
class VoxelTable:
    """Voxel ids by integer coordinates for the numba kernels: ``hkeys`` (packed keys, -1 = empty
    slot) and ``hids`` (voxel ids) of a power-of-two open-addressed table with linear probing,
    and the integer bounding box ``[box_lo, box_hi)`` of the voxels."""

    hkeys: np.ndarray
    hids: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray


class PriorAdam:
    """Lazy Adam (:mod:`h3edge.mapping.sparse_adam`) for the SDF priors: updates only vertices
    with a gradient, and keeps its state
    when :class:`VoxelMap` grows the prior tensor (state is padded, ids are stable)."""

    def __init__(self, lr: float = 1e-2, betas=(0.9, 0.999), eps: float = 1e-15):
        self.lr, self.betas, self.eps = lr, betas, eps
        self.m = torch.zeros(0)
        self.v = torch.zeros(0)
        self.steps = 0

    def state_dict(self) -> tuple[dict, dict[str, np.ndarray]]:
        arrays = {"m": self.m.detach().cpu().numpy().copy(), "v": self.v.detach().cpu().numpy().copy()}
        return {"steps": self.steps}, arrays

    def load_state_dict(self, meta: dict, arrays: dict[str, np.ndarray], device: str | torch.device = "cpu") -> None:
        self.m = torch.from_numpy(np.asarray(arrays["m"], np.float32)).to(device)
        self.v = torch.from_numpy(np.asarray(arrays["v"], np.float32)).to(device)
        self.steps = int(meta["steps"])

    @torch.no_grad()
    def step(self, voxels: VoxelMap, used: torch.Tensor | None = None) -> int:
        """One update of the vertices with a gradient; the number updated. ``used``: the prior
        tensor the gradient was computed on, when the map may have grown it since (its gradient
        carries over to the grown tensor: ids are stable)."""
        p = voxels.priors
        if used is not None and used is not p and used.grad is not None:
            g = torch.zeros_like(p)
            g[:len(used)] = used.grad
            p.grad, used.grad = g, None
        if p.grad is None:
            return 0
        if len(self.m) < len(p):
            pad = torch.zeros(len(p) - len(self.m), device=p.device)
            self.m = torch.cat([self.m.to(p.device), pad])
            self.v = torch.cat([self.v.to(p.device), pad])
        g = p.grad
        rows = torch.nonzero(g).squeeze(1)
        p.grad = None
        if len(rows) == 0:
            return 0
        self.steps += 1
        lazy_adam_rows(p, self.m, self.v, rows, g[rows], self.steps, self.lr, self.betas, self.eps)
        return len(rows)
