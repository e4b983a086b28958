"""The hierarchical hybrid field: SDF = octree prior + residual MLP(geometry hash features);
colour = MLP(texture features).

The texture features come from a :class:`TextureEncoder` (``h3edge.mapping.texture_grid``):
H3-Mapping's quasi-heterogeneous grids (space warps, one table with a hash function per warp,
zero-padded concatenation) or, with ``[texture] quasi_heterogeneous = false``, H2-Mapping's uniform
hash grid; both take ``forward(points, voxel_index) -> (N, out_dim)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from torch import nn

from h3edge.mapping.color_base import ColorBase, compose
from h3edge.mapping.hashgrid import HashGrid, HashGridSpec
from h3edge.mapping.texture_grid import QuasiHeteroTexture, UniformTexture
from h3edge.mapping.texture_patterns import TextureConfig
from h3edge.mapping.voxels import VoxelMap


@dataclass(frozen=True)
class FieldConfig:
    geo_levels: int = 4
    """L (geometry)"""
    geo_features: int = 2
    """F"""
    geo_log2_table: int = 19
    """T = 2^19"""
    geo_level_scale: float = 2.0
    """finest cell = voxel / 8"""
    tex_levels: int = 4
    """L (texture): levels of the texture hash grid (paper: 4)"""
    tex_features: int = 2
    """F (texture): features per level (paper: 2)"""
    tex_log2_table: int = 19
    """T = 2^19 rows per texture level (paper)"""
    tex_level_scale: float = 3.0
    """the paper's "scale difference 3": finest cell = voxel / 27"""
    sdf_hidden: int = 64
    """hidden width of the SDF residual MLP (paper: 64)"""
    sdf_layers: int = 5
    """hidden layers of the SDF MLP (the authors' effective default)"""
    color_hidden: int = 64
    """hidden width of the colour MLP (paper: 64)"""
    color_layers: int = 2
    """hidden layers of the colour MLP (paper: 2)"""
    backend: str = "auto"
    """hash-grid backend: auto | torch | numba"""
    beta: float = 0.05
    """beta: width of the volume-rendering kernel sigma(s/beta) sigma(-s/beta) on this field's SDF (truncation units,
    authors: 0.05), used by training and by rendering alike"""
    grid_cell: float = 0.0
    """m: the hash grids' level-0 cell. 0 = one cell per octree leaf voxel (the paper's); a value keeps the grids'
    resolution fixed while the leaf voxel (the priors' lattice) changes"""

    def __post_init__(self):
        if not self.grid_cell >= 0:  # refused when the profile loads, not at the first frame
            raise ValueError(f"field.grid_cell must be >= 0 m (0: the leaf voxel), got {self.grid_cell}")
        if not self.beta > 0:  # the rendering kernel divides by it
            raise ValueError(f"field.beta must be > 0 truncation units, got {self.beta}")


def mlp(n_in: int, hidden: int, layers: int, n_out: int) -> nn.Sequential:
    mods: list[nn.Module] = []
    d = n_in
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), nn.ReLU(inplace=True)]
        d = hidden
    mods.append(nn.Linear(d, n_out))
    return nn.Sequential(*mods)


class TextureEncoder(Protocol):
    out_dim: int

    def __call__(self, points: torch.Tensor, voxel_index: torch.Tensor) -> torch.Tensor: ...


class Field(nn.Module):
    def __init__(self, cfg: FieldConfig, bound: np.ndarray, voxel_size: float, device="cpu",
                 texture: TextureConfig = TextureConfig()):
        super().__init__()
        self.cfg = cfg
        cell = cfg.grid_cell or voxel_size  # paper: one level-0 cell per leaf voxel
        base = int(np.ceil((bound[1] - bound[0]).max() / cell))
        geo = HashGridSpec(cfg.geo_levels, cfg.geo_features, cfg.geo_log2_table, base, cfg.geo_level_scale)
        tex = HashGridSpec(cfg.tex_levels, cfg.tex_features, cfg.tex_log2_table, base, cfg.tex_level_scale)
        self.geo_grid = HashGrid(geo, bound, backend=cfg.backend, seed=1, device=device)
        if texture.quasi_heterogeneous:
            self.texture: nn.Module = QuasiHeteroTexture(tex, bound, texture, cfg.backend, seed=2, device=device)
        else:
            self.texture = UniformTexture(HashGrid(tex, bound, backend=cfg.backend, seed=2, device=device))
        self.sdf_mlp = mlp(geo.out_dim, cfg.sdf_hidden, cfg.sdf_layers, 1).to(device)
        self.color_mlp = nn.Sequential(mlp(self.texture.out_dim, cfg.color_hidden, cfg.color_layers, 3),
                                       nn.Sigmoid()).to(device)
        # the fused colour base the MLP's colour is composed with (:mod:`h3edge.mapping.color_base`);
        # the mapper's, set by it; not a parameter (fused at integration, never trained)
        self.color_base: ColorBase | None = None
        # the gain on the colour MLP's residual over the base that renders apply: what fresh frames
        # confirmed (:mod:`h3edge.mapping.residual_check`; set by the mapper, 1 until they have)
        self.residual_gain = 1.0

    def place(self, lo: np.ndarray) -> None:
        """Move the grids' reference cube to start at world point ``lo`` (3,) metres, its size kept:
        the field reads at p what it read at p - (lo - the old start). Before any training only."""
        with torch.no_grad():
            for grid in self.hash_grids():
                grid.bound_min.copy_(torch.as_tensor(np.asarray(lo, np.float32), device=grid.bound_min.device))

    def hash_grids(self) -> list[HashGrid]:
        return [self.geo_grid, self.texture.grid]

    def sdf(self, points: torch.Tensor, voxels: VoxelMap, located: tuple[np.ndarray, np.ndarray] | None = None,
            prior: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """SDF (truncation units) = trilinear prior + residual, and the in-voxel mask. Points outside
        the allocated voxels get 0 and must be masked by the caller (the residual is not evaluated).
        ``located`` / ``prior``: the voxel lookup or the (prior SDF, inside) pair, when already known."""
        prior, inside = voxels.coarse_sdf(points, located) if prior is None else prior
        idx = torch.nonzero(inside).squeeze(1)
        if len(idx) == len(points):
            return prior + self.sdf_mlp(self.geo_grid(points))[:, 0], inside
        # outside the allocated voxels the SDF is undefined (masked everywhere): no residual there
        res = self.sdf_mlp(self.geo_grid(points[idx]))[:, 0]
        return prior.index_add(0, idx, res), inside

    def color(self, points: torch.Tensor, voxel_index: torch.Tensor | None = None,
              residual: float | None = None) -> torch.Tensor:
        """RGB (N, 3) in [0, 1] at world points (N, 3) metres: the colour MLP on the texture
        features, composed with the fused colour base where it knows the colour
        (:func:`~h3edge.mapping.color_base.compose`, relative to the MLP's colour at zero features).
        ``voxel_index``: each point's leaf voxel (-1 or None: unknown, no warps apply).
        ``residual``: the gain on the MLP's residual over the base (training: 1.0; None: the
        ``residual_gain`` fresh frames confirmed, :mod:`h3edge.mapping.residual_check`)."""
        if self.color_base is None or len(self.color_base) == 0 or len(points) == 0:
            return self.color_mlp(self._texture(points, voxel_index))
        rgb, neutral = self.color_field(points, voxel_index)
        base, known = self.color_base.sample(points)
        gain = self.residual_gain if residual is None else residual
        return compose(rgb, base.to(rgb.dtype), known, neutral.to(rgb.dtype), gain)

    def color_field(self, points: torch.Tensor, voxel_index: torch.Tensor | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The colour MLP's own output at world points (N, 3) metres, (N, 3) in [0, 1], and at zero
        texture features (1, 3): what an unlearned texture cell reads (the neutral colour of
        :func:`~h3edge.mapping.color_base.compose`)."""
        features = self._texture(points, voxel_index)
        return self.color_mlp(features), self.color_mlp(features.new_zeros((1, features.shape[1])))

    def _texture(self, points: torch.Tensor, voxel_index: torch.Tensor | None) -> torch.Tensor:
        if voxel_index is None:  # unknown voxels: no warps apply (identity features only)
            voxel_index = torch.full((len(points),), -1, dtype=torch.long, device=points.device)
        return self.texture(points, voxel_index)

    def sparse_step(self, lr: float) -> None:
        for g in self.hash_grids():
            g.sparse_adam_step(lr)
