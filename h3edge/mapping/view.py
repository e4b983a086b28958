"""Read-only views of the map for queries: mesh and render from a field + voxel map.

:class:`MapView` answers mesh and render requests from a field and its voxels. The mapper uses one
over its live state; a service takes :meth:`MapView.frozen` copies (the tables, MLPs, priors and
voxel index, without optimiser state: ~2x the tables' bytes, tens of ms) so that a long mesh or
render runs beside training without seeing half-updated parameters or holding the mapper up;
a copy can carry ONNX-exported decoders run by onnxruntime (:mod:`h3edge.mapping.onnx_decoders`).
"""

from __future__ import annotations

import copy

import numpy as np
import torch
import trimesh

from h3edge.errors import InputError
from h3edge.geometry.camera import Intrinsics, rigid_error
from h3edge.mapping.cell_votes import CellVotes
from h3edge.mapping.color_base import FusedDistances
from h3edge.mapping.field import Field
from h3edge.mapping.free_space import FreeSpace
from h3edge.mapping.mesh import FILL_BATCH, extract_mesh, left_out_surface, paint
from h3edge.mapping.onnx_decoders import DecoderRuntime
from h3edge.mapping.raymarch import MapRenderer, PriorLookup, RenderConfig, free_floor_fn, residual_gain
from h3edge.mapping.voxels import VoxelMap


def _inference_copy(field: Field) -> Field:
    """Deep copy of ``field`` without optimiser state or gradient scratch (not trainable). The
    colour base is shared, not copied: at its cap it is as large as the rest of the map, and a copy
    per query would not fit the memory plan. A query reads it while frames fuse into it: it may see
    colours and cells fused since, never a torn table (rows are written before the slots that point
    at them; a grown table is new arrays, the old ones stay whole for a reader that holds them)."""
    memo: dict = {}
    for g in field.hash_grids():
        memo.update(g.inference_copy_memo())
    if field.color_base is not None:
        memo[id(field.color_base)] = field.color_base
    with torch.no_grad():
        out = copy.deepcopy(field, memo)
    for p in out.parameters():
        p.requires_grad_(False)
    return out


def _voxels_copy(voxels: VoxelMap) -> VoxelMap:
    return voxels.frozen_copy()


class MapView:
    def __init__(self, field: Field, voxels: VoxelMap, voxel_size: float, render_cfg: RenderConfig,
                 mesh_resolution: int, frames_mapped: int = 0, mesh_min_support: float = 0.0,
                 free_space: FreeSpace | None = None, votes: CellVotes | None = None,
                 max_position: float = float("inf")):
        self.field, self.voxels, self.free_space = field, voxels, free_space
        # m: the farthest point from the world origin a query reads the map at (mapper.max_position):
        # a render camera beyond is refused, a distance query there reads unknown
        self.max_position = max_position
        # the fine free-space votes a render's and mesh's SDF floor reads (render.free_floor); a frozen
        # copy shares the live ones (1 KB a voxel: a copy per query would not fit the memory plan), so a
        # query may see the cells a frame integrated since voted free, never a torn array (rows only grow)
        self.votes = votes
        self.voxel_size, self.render_cfg = voxel_size, render_cfg
        self.mesh_resolution, self.mesh_min_support = mesh_resolution, mesh_min_support
        self.frames_mapped = frames_mapped

    def frozen(self, decoders: DecoderRuntime | None = None) -> MapView:
        """A copy of the field, voxels and free space (call where the field is not being updated);
        the colour base and the votes are shared with this view, not copied (their rows only grow,
        so a query beside integration reads a whole table). With ``decoders`` its SDF and colour
        decoders run on that runtime's shared onnxruntime sessions."""
        field = _inference_copy(self.field)
        if decoders is not None:
            field.sdf_mlp = decoders.mlp(field.sdf_mlp)
            field.color_mlp = decoders.mlp(field.color_mlp)
        return MapView(field, _voxels_copy(self.voxels), self.voxel_size, self.render_cfg, self.mesh_resolution,
                       self.frames_mapped, self.mesh_min_support,
                       copy.deepcopy(self.free_space) if self.free_space is not None else None,
                       self.votes, self.max_position)

    @property
    def device(self) -> torch.device:
        return self.voxels.device

    @torch.no_grad()
    def sdf_np(self, pts: np.ndarray, lookup: PriorLookup | None = None) -> np.ndarray:
        """SDF (truncation units) at points (N, 3) metres; 0 outside the allocated voxels."""
        return self.banded_sdf_np(pts, np.inf, lookup)

    @torch.no_grad()
    def color_np(self, pts: np.ndarray, lookup: PriorLookup | None = None) -> np.ndarray:
        vox = (lookup or PriorLookup(self.voxels))(pts)[1]
        p = torch.from_numpy(pts.astype(np.float32)).to(self.device)
        return self.field.color(p, torch.from_numpy(vox).to(self.device), residual_gain(self.render_cfg)).cpu().numpy()

    def renderer(self) -> MapRenderer:
        return MapRenderer(self.field, self.voxels, self.render_cfg, self.votes)

    def render(self, intr: Intrinsics, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(uint8 RGB (H, W, 3), float32 z-depth metres (H, W), 0 where nothing was hit). InputError for
        a camera pose that is not a finite rigid transform or lies beyond ``max_position`` (the ray
        marches step centimetres along rays: from farther than float64 resolves they would not end)."""
        err = rigid_error(np.asarray(c2w, np.float64))
        if err:
            raise InputError(f"render pose: {err}")
        dist = float(np.linalg.norm(np.asarray(c2w, np.float64)[:3, 3]))
        if dist > self.max_position:
            raise InputError(f"render camera {dist:.4g} m from the world origin, beyond mapper.max_position "
                             f"({self.max_position:g} m)")
        return self.renderer().render(intr, c2w)

    @torch.no_grad()
    def banded_sdf_np(self, pts: np.ndarray, margin: float, lookup: PriorLookup | None = None) -> np.ndarray:
        """SDF with the residual evaluated only where |prior| < ``margin`` (truncation units); the
        prior alone elsewhere (same sign there while the residual stays under ``margin``). Points
        are located and their priors read in one pass over a dense voxel-id grid (``lookup``:
        a :class:`PriorLookup` of this view's voxels, built here when not given)."""
        prior, vox = (lookup or PriorLookup(self.voxels))(pts)
        out = prior.astype(np.float32)
        near = np.flatnonzero((vox >= 0) & (np.abs(prior) < margin))
        if len(near):
            p = torch.from_numpy(pts[near].astype(np.float32)).to(self.device)
            known = (
                torch.from_numpy(out[near]).to(self.device),
                torch.ones(len(near), dtype=torch.bool, device=self.device),
            )
            out[near] = self.field.sdf(p, self.voxels, prior=known)[0].cpu().numpy()
        floor = free_floor_fn(self.votes, self.voxels, self.render_cfg.free_floor)
        if floor is not None:
            out = np.maximum(out, floor(pts, vox)).astype(np.float32)
        return out

    def block_meshes(self, blocks: np.ndarray, block_voxels: int, resolution: int | None = None
                     ) -> list[trimesh.Trimesh]:
        """The meshes of map blocks ``blocks`` (B, 3) (cubes of ``block_voxels`` leaf voxels: block b
        holds the voxels with ``floor(ijk / block_voxels) == b``), one lookup table for all of them."""
        from h3edge.mapping.voxels import unpack

        keys = self.voxels.voxel_keys
        blocks = np.asarray(blocks, np.int64).reshape(-1, 3)
        of_block = np.floor_divide(unpack(keys), block_voxels)
        lookup = PriorLookup(self.voxels)
        near_block = self._base_cells_near(blocks, block_voxels)
        out = []
        for b, near in zip(blocks, near_block):
            mine = keys[np.all(of_block == b, axis=1)]
            out.append(self.mesh(resolution, voxel_keys=mine, lookup=lookup, base_cells=near)
                       if len(mine) else trimesh.Trimesh())
        return out

    def _fill_source(self) -> FusedDistances | None:
        """The fused base's distances a mesh fills the cubes it leaves out from (D53-9); None where
        it does not (no base, or no support rule)."""
        base = self.field.color_base
        if base is None or len(base) == 0 or self.mesh_min_support <= 0:
            return None
        return base.distances()

    def _base_cells_near(self, blocks: np.ndarray, block_voxels: int) -> list[tuple[np.ndarray, np.ndarray] | None]:
        """Per block of ``blocks`` (B, 3) (``block_voxels`` voxels a side): the base's cells in it and
        its 26 neighbours (the cubes at its faces read cells across them), as (coordinates (n, 3),
        distances (n,)), from one pass over the base a batch at a time; None without a fill."""
        source = self._fill_source()
        if source is None:
            return [None] * len(blocks)
        scale = source.cell / (self.voxel_size * block_voxels)
        parts: list[list] = [[] for _ in blocks]
        for ijk, dist in source.batches(FILL_BATCH):
            of_block = np.floor((ijk + 0.5) * scale).astype(np.int64)
            for part, b in zip(parts, blocks):
                near = np.flatnonzero(np.all(np.abs(of_block - b) <= 1, axis=1))
                if len(near):
                    part.append((ijk[near], dist[near]))
        return [(np.concatenate([p[0] for p in part]), np.concatenate([p[1] for p in part])) if part
                else (np.zeros((0, 3), np.int64), np.zeros(0, np.float32)) for part in parts]

    def mesh(self, resolution: int | None = None, aabb: np.ndarray | None = None, color: bool = True,
             prior_margin: float | None = 1.0, voxel_keys: np.ndarray | None = None,
             lookup: PriorLookup | None = None, base_cells: tuple[np.ndarray, np.ndarray] | None = None,
             fill: bool = True) -> trimesh.Trimesh:
        """Marching-cubes mesh of the map, vertex colours from the colour field. The residual MLP is
        evaluated at lattice points whose prior is within ``prior_margin`` truncation units of the
        surface (None: everywhere), where the zero crossing can be. Cubes whose lattice points lack
        observed priors (support under ``mesh_min_support``) are left out of the field's surface
        and take the fused base's there (:func:`~h3edge.mapping.mesh.left_out_surface`, D53-9).
        ``voxel_keys``: mesh only these voxels; ``lookup``: this view's :class:`PriorLookup`, when
        the caller has one; ``base_cells``: the base's cells that may lie in a left-out cube, as
        (coordinates (n, 3), distances (n,)) (default: all of them; the surface is read from the whole base);
        ``fill`` False: the field's surface alone."""
        if len(self.voxels) == 0:
            return trimesh.Trimesh()
        lookup = lookup or PriorLookup(self.voxels)
        margin = np.inf if prior_margin is None else prior_margin
        keys = self.voxels.voxel_keys if voxel_keys is None else voxel_keys
        res = resolution or self.mesh_resolution
        mesh = extract_mesh(keys, self.voxel_size, lambda x: self.banded_sdf_np(x, margin, lookup), res, None,
                            aabb=aabb, support_fn=lookup.support, min_support=self.mesh_min_support)
        source = self._fill_source() if fill else None
        if source is not None:
            # where the priors carry no evidence yet the mesh shows the fused base's surface (D53-9)
            cells = source.batches(FILL_BATCH) if base_cells is None else [base_cells]
            verts, faces = left_out_surface(cells, source.volume, source.cell, keys, self.voxel_size, res,
                                            lookup.support, self.mesh_min_support, aabb)
            if len(faces):
                v, f = np.asarray(mesh.vertices).reshape(-1, 3), np.asarray(mesh.faces).reshape(-1, 3)
                mesh = trimesh.Trimesh(np.concatenate([v, verts]), np.concatenate([f, faces + len(v)]), process=False)
        if color:
            paint(mesh, lambda x: self.color_np(x, lookup))
        return mesh
