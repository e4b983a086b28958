"""Texture feature encoders behind one interface: ``out_dim`` and ``forward(points, voxel_index)``.

- :class:`UniformTexture`: H2-Mapping's single multiresolution hash grid.
- :class:`QuasiHeteroTexture`: H3-Mapping's quasi-heterogeneous grids (Sec. III): each sample is
  encoded in the identity space (always), in the scaling-warped space S(x) = C x when its voxel is
  weak texture (every classified voxel with ``scaling_everywhere``, research/textures.md), and in
  the affine-warped space of each of its voxel's low-frequency directions m
  (x -> a(c) + A_m (x - c), A_m = diag(1, 1, C) R(DIR_m)^T about the voxel centre c). All spaces
  read ONE hash table, each through its own hash function (fixed primes and offsets); the
  features are concatenated [identity | weak | dir_0 .. dir_{M-1}] into (M + 2) L F values with
  zeros where a warp does not apply. Warps are computed in the grid's normalised coordinates.

The per-voxel warp state (class, affine matrices, centres) comes from
:class:`~h3edge.mapping.texture_patterns.TexturePatterns` via :meth:`QuasiHeteroTexture.set_warps`.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from h3edge.mapping.hashgrid import PRIMES, HashFunction, HashGrid, HashGridSpec
from h3edge.mapping.texture_patterns import RICH, WEAK, TextureConfig, affine_matrix

# Per warp type: primes (first 1, as instant-NGP) from the authors' configuration, and offsets
# Delta of the paper's hash (the 1..9 millionth primes; the authors' code has no offset).
WARP_HASHES = (
    HashFunction(PRIMES, (0, 0, 0), dense=True),  # identity
    HashFunction((1, 2741578211, 1179736007), (15485863, 32452843, 49979687), dense=False),  # scaling (weak)
    HashFunction((1, 3554383747, 1552879877), (67867967, 86028121, 104395301), dense=False),  # affine, m = 0
    HashFunction((1, 2165219737, 1434869437), (122949823, 141650939, 160481183), dense=False),  # affine, m = 1
)


class UniformTexture(nn.Module):
    """H2-Mapping's texture grid: one multiresolution hash grid, no warps."""

    def __init__(self, grid: HashGrid):
        super().__init__()
        self.grid = grid
        self.out_dim = grid.spec.out_dim

    def forward(self, points: torch.Tensor, voxel_index: torch.Tensor) -> torch.Tensor:  # noqa: ARG002
        return self.grid(points)


class QuasiHeteroTexture(nn.Module):
    """H3-Mapping's quasi-heterogeneous texture grids (module doc)."""

    def __init__(self, spec: HashGridSpec, bound: np.ndarray, cfg: TextureConfig, backend: str = "auto",
                 seed: int = 2, device: str | torch.device = "cpu"):
        super().__init__()
        M = cfg.max_directions
        if M + 2 > len(WARP_HASHES):
            raise ValueError(f"max_directions {M} > {len(WARP_HASHES) - 2}: add hash functions to WARP_HASHES")
        if not 0 <= cfg.identity_levels <= spec.levels:
            raise ValueError(f"identity_levels must be in [0, {spec.levels}] (0: all), got {cfg.identity_levels}")
        self.cfg = cfg
        self.grid = HashGrid(spec, bound, hash_functions=WARP_HASHES[: M + 2], backend=backend, seed=seed,
                             device=device)
        self.block = spec.out_dim
        self.out_dim = (M + 2) * spec.out_dim
        dev = torch.device(device)
        self.register_buffer("centres", torch.zeros(0, 3, device=dev))  # normalised voxel centres
        self.register_buffer("weak", torch.zeros(0, dtype=torch.bool, device=dev))
        self.register_buffer("n_dirs", torch.zeros(0, dtype=torch.long, device=dev))
        self.register_buffer("affine", torch.zeros(0, M, 3, 3, device=dev))

    PER_VOXEL = ("centres", "weak", "n_dirs", "affine")  # buffers sized by the map, not the config

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        for name in self.PER_VOXEL:  # take the saved map's voxel count before torch checks shapes
            saved = state_dict.get(prefix + name)
            if saved is not None:
                setattr(self, name, torch.empty_like(saved, device=getattr(self, name).device))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @torch.no_grad()
    def set_warps(self, voxel_ijk: np.ndarray, voxel_size: float, classes: np.ndarray, dirs: np.ndarray,
                  n_dirs: np.ndarray) -> None:
        """Install the per-voxel warp state for voxels with integer coordinates ``voxel_ijk`` (V, 3):
        classes (V,), directions (V, M, 3), direction counts (V,).
        ``warp_rich`` / ``warp_weak`` off leave those voxels on identity features only."""
        dev = self.centres.device
        lo, size = self.grid.bound_min.cpu().numpy(), self.grid.bound_size.cpu().numpy()
        centres = ((voxel_ijk + 0.5) * voxel_size - lo) / size
        V = len(voxel_ijk)
        weak = (classes[:V] == WEAK) if self.cfg.warp_weak else np.zeros(V, bool)
        if self.cfg.warp_weak and self.cfg.scaling_everywhere:
            weak = np.ones(V, bool)
        nd = np.where(classes[:V] == RICH, n_dirs[:V], 0) if self.cfg.warp_rich else np.zeros(V, np.int64)
        M = self.cfg.max_directions
        A = np.tile(np.eye(3), (V, M, 1, 1))
        has = np.arange(M)[None, :] < nd[:, None]
        if has.any():
            A[has] = affine_matrix(dirs[:V][has], self.cfg.compression)
        self.centres = torch.from_numpy(centres.astype(np.float32)).to(dev)
        self.weak = torch.from_numpy(weak).to(dev)
        self.n_dirs = torch.from_numpy(nd.astype(np.int64)).to(dev)
        self.affine = torch.from_numpy(A.astype(np.float32)).to(dev)

    def warp_affine(self, xn: torch.Tensor, vox: torch.Tensor, m: int) -> torch.Tensor:
        """Affine-warped normalised coordinates of points ``xn`` in voxels ``vox`` for direction m."""
        c = self.centres[vox]
        return self.cfg.anchor_scale * c + torch.einsum("nij,nj->ni", self.affine[vox, m], xn - c)

    def forward(self, points: torch.Tensor, voxel_index: torch.Tensor) -> torch.Tensor:
        xn = self.grid.normalise(points.to(torch.float32))
        n = len(xn)
        blocks = [self.grid(xn, fn=0, normalised=True, levels=self.cfg.identity_levels or None)]
        known = (voxel_index >= 0) & (voxel_index < len(self.weak))
        vox = torch.where(known, voxel_index, torch.zeros_like(voxel_index))
        zeros = lambda: torch.zeros(n, self.block, device=xn.device, dtype=blocks[0].dtype)  # noqa: E731
        idx = torch.nonzero(known & self.weak[vox]).squeeze(1) if len(self.weak) else xn.new_zeros(0).long()
        blocks.append(zeros().index_copy(0, idx, self.grid(self.cfg.compression * xn[idx], fn=1, normalised=True))
                      if len(idx) else zeros())
        for m in range(self.cfg.max_directions):
            idx = (
                torch.nonzero(known & (self.n_dirs[vox] > m)).squeeze(1) if len(self.n_dirs) else xn.new_zeros(0).long()
            )
            if len(idx):
                w = self.warp_affine(xn[idx], vox[idx], m)
                blocks.append(zeros().index_copy(0, idx, self.grid(w, fn=2 + m, normalised=True)))
            else:
                blocks.append(zeros())
        return torch.cat(blocks, 1)
