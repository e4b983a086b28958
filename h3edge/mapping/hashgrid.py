"""Multiresolution hash encoding (instant-NGP math) with sparse, row-wise optimisation.

Math (as tiny-cuda-nn computes it): world points are normalised per axis to a reference cube
(``bound``: it sets the scale and where the dense levels lie, not a limit), x = (p - lo) / size,
so x in [0, 1]^3 inside the cube and anywhere outside it: the encoding covers all of space.
Level l has ``scale_l = base_resolution * per_level_scale**l - 1`` and grid position
``p = x * scale_l + 0.5``; the 8 corners of the cell containing p are looked up and trilinearly
interpolated. A level whose grid over the cube ((ceil(scale_l) + 2)^3 vertices) fits in the
table is indexed densely inside the cube, and everywhere else (and at every finer level) by the
spatial hash ``(v_x * pi_1) XOR (v_y * pi_2) XOR (v_z * pi_3) mod T`` (pi = 1, 2654435761,
805459861). Each level owns T rows of F features; a larger mapped area shares the same rows
(more collisions), which is the capacity trade-off of docs/map_extent.md.

One table can be read through several hash functions (H3-Mapping Sec. III-B: one per space-warp
type): function i hashes ``XOR_k (v_k * pi_ik + delta_ik) mod T`` with its own primes and
offsets. Function 0 is the plain instant-NGP hash (and keeps dense indexing for coarse levels);
the others always hash, so that two functions never index the same dense rows by construction.

Two interchangeable implementations give the same numbers:
- ``torch``: plain PyTorch gathers, runs on CPU and CUDA;
- ``numba``: fused CPU kernels (forward parallel over points; backward recomputes the corners,
  parallel over levels, so scatter-adds never race, and flags the rows it touches; the lazy Adam
  step walks those flags in address order, so that it streams through the table).
Neither produces a dense gradient: backward yields the touched rows and their gradients, and
:meth:`HashGrid.sparse_adam_step` updates only those rows (lazy Adam), never the whole table.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from h3edge.mapping.sparse_adam import lazy_adam_rows
from h3edge.mapping.trilinear import corner_weights, corners_on

PRIMES = (1, 2654435761, 805459861)


@dataclass(frozen=True)
class HashGridSpec:
    levels: int = 4  # L
    features: int = 2  # F per level
    log2_table: int = 19  # T = 2^19 rows per level
    base_resolution: int = 16  # cells along each axis at level 0
    per_level_scale: float = 2.0

    @property
    def table_size(self) -> int:
        return 1 << self.log2_table

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    def level_scales(self) -> np.ndarray:
        return np.array([self.base_resolution * self.per_level_scale ** l - 1.0 for l in range(self.levels)])

    def level_dense(self) -> np.ndarray:
        """Per level: grid side length when indexed densely, 0 when hashed."""
        out = []
        for s in self.level_scales():
            side = int(math.ceil(s)) + 2
            out.append(side if side ** 3 <= self.table_size else 0)
        return np.array(out, np.int64)


@dataclass(frozen=True)
class HashFunction:
    primes: tuple[int, int, int] = PRIMES
    offsets: tuple[int, int, int] = (0, 0, 0)
    dense: bool = True  # coarse levels that fit the table are indexed densely


@functools.lru_cache(maxsize=32)
def _level_tables(spec: HashGridSpec, dense: bool, n_levels: int, device: torch.device, dtype: torch.dtype
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``n_levels`` coarsest levels' scales (``dtype``) and dense sides (int64, 0: hashed) on
    ``device``, made once (constants: no copy up a call)."""
    scales = torch.tensor(spec.level_scales()[:n_levels], dtype=dtype, device=device)
    sides = torch.tensor((spec.level_dense() if dense else np.zeros(spec.levels, np.int64))[:n_levels], device=device)
    return scales, sides


def corner_indices_torch(xn: torch.Tensor, spec: HashGridSpec, fn: HashFunction = HashFunction(),
                         levels: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Row indices (N, L', 8) int64 into the (L*T, F) table and trilinear weights (N, L', 8) of the
    ``levels`` = L' coarsest levels (None: all L)."""
    T = spec.table_size
    dev = xn.device
    n_levels = spec.levels if levels is None else levels
    primes, d = fn.primes, fn.offsets
    scales, dense = _level_tables(spec, fn.dense, n_levels, dev, xn.dtype)
    p = xn[:, None, :] * scales[None, :, None] + 0.5  # (N, L, 3)
    g = torch.floor(p)
    f = p - g
    g = g.long()
    v = g[:, :, None, :] + corners_on(dev)[0][None, None]  # (N, L, 8, 3)
    w = corner_weights(f)  # (N, L, 8)
    side = dense[None, :, None]
    dense_idx = v[..., 0] + side * (v[..., 1] + side * v[..., 2])
    hashed = (v[..., 0] * primes[0] + d[0]) ^ (v[..., 1] * primes[1] + d[1]) ^ (v[..., 2] * primes[2] + d[2])
    in_dense = (side > 0) & ((v >= 0) & (v < side[..., None])).all(-1)
    idx = torch.where(in_dense, dense_idx, hashed) & (T - 1)
    idx = idx + torch.arange(n_levels, device=dev)[None, :, None] * T
    return idx, w


class _TorchEncode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, xn, table, grid, fn, levels):
        idx, w = corner_indices_torch(xn, grid.spec, grid.hash_functions[fn], levels)
        ctx.save_for_backward(idx, w)
        ctx.grid = grid
        feats = (table[idx] * w[..., None]).sum(2).reshape(len(xn), idx.shape[1] * grid.spec.features)  # (N, L' F)
        if feats.shape[1] < grid.spec.out_dim:  # the levels left out read as zeros
            feats = torch.nn.functional.pad(feats, (0, grid.spec.out_dim - feats.shape[1]))
        return feats

    @staticmethod
    def backward(ctx, grad_out):
        idx, w = ctx.saved_tensors
        grid = ctx.grid
        F = grid.spec.features
        n_levels = idx.shape[1]
        g_out = grad_out[:, : n_levels * F].reshape(len(idx), n_levels, 1, F)
        contrib = (g_out * w[..., None]).reshape(-1, F)
        rows, inv = torch.unique(idx.reshape(-1), return_inverse=True)
        g = torch.zeros(len(rows), F, dtype=grad_out.dtype, device=grad_out.device).index_add_(0, inv, contrib)
        grid._accumulate(rows, g)
        return None, None, None, None, None


def _numba_kernels():
    from h3edge.mapping import _hash_kernels as k

    return k.fwd, k.bwd, k.collect, k.adam_touched, k.SCAN_BLOCK


class _NumbaEncode(torch.autograd.Function):
    # The kernels loop over len(scales) levels: the first ``levels`` scales (and dense sides)
    # encode the coarsest levels only, into the first columns of a full-width output.
    @staticmethod
    def forward(ctx, xn, table, grid, fn, levels):
        fwd = grid._kernels()[0]
        x = xn.detach().numpy()
        n = grid.spec.levels if levels is None else levels
        out = (np.empty if n == grid.spec.levels else np.zeros)((len(x), grid.spec.out_dim), np.float32)
        dense, consts = grid._fn_np[fn]
        fwd(x, table.detach().numpy(), grid._scales_np[:n], dense[:n], grid.spec.table_size, *consts, out)
        ctx.grid, ctx.x, ctx.fn, ctx.n_levels = grid, x, fn, n
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_out):
        grid, x, n = ctx.grid, ctx.x, ctx.n_levels
        bwd = grid._kernels()[1]
        dense, consts = grid._fn_np[ctx.fn]
        bwd(x, np.ascontiguousarray(grad_out.detach().numpy(), dtype=np.float32), grid._scales_np[:n], dense[:n],
            grid.spec.table_size, *consts, grid._grad_buf.numpy(), grid._touched.numpy())
        grid._numba_pending = True  # gradients and flags accumulate across calls until taken
        return None, None, None, None, None


class HashGrid(torch.nn.Module):
    """Hash-encoded feature field over all of space, scaled to a reference cube ``bound``;
    ``forward(x_world) -> (N, L*F)``.

    ``hash_functions``: the ways the one table can be indexed (``forward(..., fn=i)``); the default
    is the single instant-NGP hash."""

    def __init__(
        self,
        spec: HashGridSpec,
        bound: np.ndarray,
        hash_functions: tuple[HashFunction, ...] = (HashFunction(),),
        backend: str = "auto",
        init_scale: float = 1e-4,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ):
        super().__init__()
        self.spec = spec
        self.hash_functions = tuple(hash_functions)
        bound = np.asarray(bound, np.float64)
        self.register_buffer("bound_min", torch.tensor(bound[0], dtype=torch.float32, device=device))
        self.register_buffer("bound_size", torch.tensor(bound[1] - bound[0], dtype=torch.float32, device=device))
        gen = torch.Generator().manual_seed(seed)
        table = (torch.rand(spec.levels * spec.table_size, spec.features, generator=gen) * 2 - 1) * init_scale
        # The table is optimised row-sparsely (sparse_adam_step), not by a torch optimiser: it
        # requires grad only so that autograd calls the encoders' backward, which never fills .grad.
        self.register_buffer("table", table.to(device).requires_grad_(True))
        self.register_buffer("adam_m", torch.zeros_like(self.table))
        self.register_buffer("adam_v", torch.zeros_like(self.table))
        self.adam_steps = 0
        dev = torch.device(device)
        if backend == "auto":
            backend = "numba" if dev.type == "cpu" and _numba_available() else "torch"
        if backend == "numba" and dev.type != "cpu":
            raise ValueError("the numba backend runs on CPU only")
        self.backend = backend
        self._scales_np = spec.level_scales().astype(np.float32)
        self._fn_np = [(spec.level_dense() if f.dense else np.zeros(spec.levels, np.int64),
                        tuple(np.int64(v) for v in (*f.primes, *f.offsets))) for f in self.hash_functions]
        if backend == "numba":
            self._grad_buf = torch.zeros_like(self.table)
            self._touched = torch.zeros(len(self.table), dtype=torch.bool)
            self._numba_pending = False  # flagged rows await the optimiser step or take_sparse_grad
        self._pending: list[tuple[torch.Tensor, torch.Tensor]] = []
        self._kern = None

    def inference_copy_memo(self) -> dict:
        """``copy.deepcopy`` memo entries that leave this grid's optimiser state and gradient
        scratch out of a copy (empty in the copy) and share its compiled kernels."""
        memo: dict = {}
        for name in ("adam_m", "adam_v", "_grad_buf", "_touched"):
            if hasattr(self, name):
                memo[id(getattr(self, name))] = torch.zeros(0)
        if self._kern is not None:
            memo[id(self._kern)] = self._kern
        return memo

    def sparse_state_dict(self) -> tuple[dict, dict[str, np.ndarray]]:
        """The table and its Adam state, sparsely: only the rows the optimiser ever moved (the others
        still hold the seeded initialisation a grid built with the same spec and seed recreates)."""
        with torch.no_grad():
            rows = torch.nonzero(((self.adam_v != 0) | (self.adam_m != 0)).any(1)).squeeze(1)
            arrays = {"rows": rows.cpu().numpy().copy()}
            for part in ("table", "adam_m", "adam_v"):
                arrays[part] = getattr(self, part)[rows].detach().cpu().numpy().copy()
        return {"adam_steps": self.adam_steps}, arrays

    def load_sparse_state_dict(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        """Inverse of :meth:`sparse_state_dict`, on a grid freshly built with the same spec and seed."""
        dev = self.table.device
        with torch.no_grad():
            rows = torch.from_numpy(np.asarray(arrays["rows"])).long().to(dev)
            for part in ("table", "adam_m", "adam_v"):
                getattr(self, part)[rows] = torch.from_numpy(np.asarray(arrays[part])).to(dev)
        self.adam_steps = int(meta["adam_steps"])

    def _kernels(self):
        if self._kern is None:
            self._kern = _numba_kernels()
        return self._kern

    def normalise(self, x: torch.Tensor) -> torch.Tensor:
        """Coordinates relative to the reference cube ([0, 1]^3 inside it; not clamped)."""
        return (x - self.bound_min) / self.bound_size

    def forward(self, x: torch.Tensor, fn: int = 0, normalised: bool = False, levels: int | None = None
                ) -> torch.Tensor:
        """Features (N, L*F) of world points ``x`` (anywhere), or of ``normalised`` coordinates
        taken as they are (warped spaces may leave [0, 1]^3; hashing does not care), through hash
        function ``fn``. ``levels``: only the coarsest ``levels`` levels are encoded; the others
        read 0, are never looked up and take no gradient (None: all)."""
        if levels is not None and not 1 <= levels <= self.spec.levels:
            raise ValueError(f"levels must be in [1, {self.spec.levels}], got {levels}")
        xn = x.to(torch.float32).contiguous() if normalised else self.normalise(x.to(torch.float32)).contiguous()
        if self.backend == "numba":
            return _NumbaEncode.apply(xn, self.table, self, fn, levels)
        return _TorchEncode.apply(xn, self.table, self, fn, levels)

    def _accumulate(self, rows: torch.Tensor, grads: torch.Tensor) -> None:
        self._pending.append((rows, grads))

    def take_sparse_grad(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Rows touched since the last call and their summed gradients (rows unique)."""
        if self.backend == "numba" and self._numba_pending:
            # the numba backward accumulates every call into one buffer: collect it once
            rows = np.flatnonzero(self._touched.numpy()).astype(np.int64)
            self._numba_pending = False
            grads = np.empty((len(rows), self.spec.features), np.float32)
            self._kernels()[2](self._grad_buf.numpy(), self._touched.numpy(), rows, grads)
            return torch.from_numpy(rows), torch.from_numpy(grads)
        if not self._pending:
            return torch.zeros(0, dtype=torch.long, device=self.table.device), \
                torch.zeros(0, self.spec.features, device=self.table.device)
        if len(self._pending) == 1:
            rows, g = self._pending[0]
        else:
            rows_all = torch.cat([r for r, _ in self._pending])
            g_all = torch.cat([g for _, g in self._pending])
            rows, inv = torch.unique(rows_all, return_inverse=True)
            g = torch.zeros(len(rows), g_all.shape[1], dtype=g_all.dtype, device=g_all.device).index_add_(0, inv, g_all)
        self._pending = []
        return rows, g

    @torch.no_grad()
    def sparse_adam_step(self, lr: float, betas=(0.9, 0.999), eps: float = 1e-15) -> int:
        """Lazy Adam on the touched rows only; returns how many rows were updated."""
        if self.backend == "numba":
            if not self._numba_pending:
                return 0
            self._numba_pending = False
            step = self.adam_steps + 1  # counted only when a row moves, as the torch path counts
            b1, b2 = betas
            c1, c2 = 1 - b1 ** step, 1 - b2 ** step
            kern, block = self._kernels()[3:5]
            counts = np.zeros(-(-len(self.table) // block), np.int64)
            kern(self.table.detach().numpy(), self.adam_m.numpy(), self.adam_v.numpy(), self._grad_buf.numpy(),
                 self._touched.numpy(), lr, b1, b2, eps, c1, c2, counts)
            updated = int(counts.sum())
            if updated:
                self.adam_steps = step
            return updated
        rows, g = self.take_sparse_grad()
        if len(rows) == 0:
            return 0
        self.adam_steps += 1
        lazy_adam_rows(self.table, self.adam_m, self.adam_v, rows, g, self.adam_steps, lr, betas, eps)
        return len(rows)


def _numba_available() -> bool:
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True
