"""A few optimisation steps on the tiny simulated scene reduce every loss and the depth error."""

import dataclasses

import numpy as np
import pytest
import torch

from h3edge.io import open_sequence
from h3edge.mapping.field import Field, FieldConfig
from h3edge.mapping.trainer import LOSS_TERMS, TrainConfig, Trainer, free_depths_in_voxels, sample_depths
from h3edge.mapping.volume_rendering import composite
from h3edge.mapping.voxels import VoxelConfig, VoxelMap
from h3edge.sim.scene import ROOM_SIZE
from tests.helpers import rays_from_frame


def test_sample_depths_layout():
    cfg = TrainConfig()
    t, b0 = sample_depths(torch.tensor([2.0, 0.5]), cfg, 0.05, 0.05, torch.Generator().manual_seed(0))
    assert t.shape == (2, cfg.free_samples + cfg.band_samples) and b0 == cfg.free_samples
    assert (t.diff(dim=1) >= 0).all()  # sorted along each ray
    assert torch.allclose(t[0, b0:], 2.0 + 0.01 * torch.arange(-5, 6, dtype=torch.float32))
    assert (t[0, :b0] <= 1.95).all() and (t[:, :b0] >= 0.05).all()
    short, _ = sample_depths(torch.tensor([2.0]), dataclasses.replace(cfg, band_behind=0.02), 0.05, 0.05)
    assert torch.allclose(short[0, b0:], 2.0 + 0.01 * torch.arange(-5, 3, dtype=torch.float32))  # to 2 cm behind


def test_training_reduces_losses(tiny_scene):
    torch.manual_seed(0)
    seq = open_sequence(tiny_scene)
    frames = [seq[i] for i in (0, 2, 4)]
    voxels = VoxelMap(VoxelConfig(min_points=3))  # 160x120: a far 10 cm voxel covers < 10 pixels
    for f in frames:
        voxels.allocate(f.depth, f.intrinsics, f.pose)
    bound = np.stack([np.zeros(3) - 0.5, ROOM_SIZE + 0.5])
    fld = Field(FieldConfig(geo_log2_table=14, tex_log2_table=14, sdf_layers=2), bound, 0.1)
    opt = torch.optim.Adam(list(fld.sdf_mlp.parameters()) + list(fld.color_mlp.parameters()) + [voxels.priors], lr=1e-2)
    cfg = TrainConfig()
    g = torch.Generator().manual_seed(0)
    n_pix = frames[0].depth.size
    eval_rays = rays_from_frame(frames[1], torch.randint(0, n_pix, (1024,), generator=g))

    def eval_error():
        with torch.no_grad():
            t, b0 = sample_depths(eval_rays.depth, cfg, 0.05, 0.05, g)
            pts = eval_rays.origins[:, None] + eval_rays.dirs[:, None] * t[..., None]
            sdf, inside = fld.sdf(pts.reshape(-1, 3), voxels)
            out = composite(sdf.reshape(t.shape)[:, b0:], t[:, b0:], None, fld.cfg.beta,
                            inside.reshape(t.shape)[:, b0:])
            ok = out.hit & (eval_rays.depth > 0)
            return float((out.depth[ok] - eval_rays.depth[ok]).abs().mean()), float(ok.float().mean())

    err0, _ = eval_error()
    trainer = Trainer(cfg, 0.05, fld, voxels, opt, generator=g)
    hist, ended = [], np.zeros(len(voxels))
    for it in range(30):
        f = frames[it % 3]
        rays = rays_from_frame(f, torch.randint(0, n_pix, (1024,), generator=g))
        ok = rays.depth > 0
        vox = voxels.locate((rays.origins[ok] + rays.dirs[ok] * rays.depth[ok, None]).numpy())[0]
        ended += np.bincount(vox[vox >= 0], minlength=len(voxels))
        hist.append(trainer.step(rays))
    # each step counts its rays in the voxels their measured surfaces fell in (VoxelMap.trained)
    assert ended.sum() > 0 and np.array_equal(voxels.trained, ended)
    err1, hit = eval_error()
    first, last = hist[0], np.mean([h["loss"] for h in hist[-5:]])
    assert last < 0.5 * first["loss"]
    assert np.mean([h["rgb"] for h in hist[-5:]]) < first["rgb"]
    assert err1 < err0 and err1 < 0.02 and hit > 0.9


def test_step_reports_each_term_and_their_weighted_sum(tiny_scene):
    """A step's ``loss`` is the sum of ``LOSS_TERMS`` weighted by their ``LossWeights`` fields, each
    term reported under its name (those with nothing to fit this step: 0); a weight set to 0 drops
    its term from the sum but not from the report."""
    seq = open_sequence(tiny_scene)
    f = seq[0]
    voxels = VoxelMap(VoxelConfig(min_points=3))
    voxels.allocate(f.depth, f.intrinsics, f.pose)
    fld = Field(FieldConfig(geo_log2_table=12, tex_log2_table=12, sdf_layers=2),
                np.stack([np.zeros(3) - 0.5, ROOM_SIZE + 0.5]), 0.1)
    opt = torch.optim.Adam(list(fld.sdf_mlp.parameters()) + list(fld.color_mlp.parameters()), lr=1e-2)
    cfg = TrainConfig()
    g = torch.Generator().manual_seed(0)
    rays = rays_from_frame(f, torch.randint(0, f.depth.size, (512,), generator=g))
    out = Trainer(cfg, 0.05, fld, voxels, opt, generator=g).step(rays)
    names = [n for n, _ in LOSS_TERMS]
    assert set(names) | {"loss", "hit_ratio", "carved"} == set(out)
    assert out["loss"] == pytest.approx(sum(getattr(cfg.weights, n) * out[n] for n in names), rel=1e-5)
    assert out["rgb"] > 0 and out["sdf"] > 0 and out["seen_free"] == 0  # no votes: nothing to fit there
    no_rgb = dataclasses.replace(cfg, weights=dataclasses.replace(cfg.weights, rgb=0.0))
    again = Trainer(no_rgb, 0.05, fld, voxels, opt, generator=g).step(rays)
    assert again["rgb"] > 0
    assert again["loss"] == pytest.approx(sum(getattr(no_rgb.weights, n) * again[n] for n in names), rel=1e-5)


def test_free_space_samples_land_in_voxels(tiny_scene):
    """Free-space samples drawn inside the allocated voxels a ray crosses (where a phantom surface
    could be) instead of over the whole range, where most miss every voxel and carve nothing."""
    seq = open_sequence(tiny_scene)
    voxels = VoxelMap(VoxelConfig(min_points=3))
    for i in (0, 3, 6, 9):
        f = seq[i]
        voxels.allocate(f.depth, f.intrinsics, f.pose)
    f = seq[5]
    g = torch.Generator().manual_seed(0)
    rays = rays_from_frame(f, torch.randint(0, f.depth.size, (2000,), generator=g))
    cfg = TrainConfig()

    def share_inside(t):
        pts = rays.origins[:, None, :] + rays.dirs[:, None, :] * t[..., None]
        vox, _ = voxels.locate(pts.reshape(-1, 3).numpy())
        ok = (rays.depth > 0)[:, None].expand_as(t).reshape(-1).numpy()
        return float((vox >= 0)[ok].mean())

    t_all, b0 = sample_depths(rays.depth, cfg, 0.05, 0.05, g)
    t_vox = free_depths_in_voxels(rays, voxels, cfg, 0.05, 0.05, g)
    assert t_vox.shape == (2000, cfg.free_samples) and (t_vox.diff(dim=1) >= 0).all()
    valid = rays.depth > 0
    assert (t_vox[valid] <= (rays.depth[valid] - 0.05)[:, None] + 1e-6).all() and (t_vox >= 0.05).all()
    stratified, in_voxels = share_inside(t_all[:, :b0]), share_inside(t_vox)
    assert in_voxels > stratified + 0.2, (stratified, in_voxels)
