"""Volume-rendering weights and each loss on hand-made rays."""

import math

import pytest
import torch

from h3edge.mapping.losses import depth_l1, free_space_and_sdf, rgb_l1, s3im
from h3edge.mapping.volume_rendering import color_samples, composite, render_weights

TR = 0.05


def ray_through_surface(surface=2.0, n=41, spacing=0.01, start=1.8):
    d = start + spacing * torch.arange(n, dtype=torch.float64)
    sdf = (surface - d) / TR  # exact SDF in truncation units
    return d[None], sdf[None]


def test_weights_peak_at_zero_crossing():
    s = torch.tensor([-2.0, -0.1, 0.0, 0.1, 2.0])
    w = render_weights(s, 0.05)
    assert w[2] == pytest.approx(0.25) and w.argmax() == 2
    assert w[0] == w[4] and w[1] == w[3]  # symmetric
    assert torch.equal(render_weights(s, 0.05, torch.tensor([1, 1, 0, 1, 1.0]))[2], torch.tensor(0.0))


def test_composite_recovers_surface_depth_and_colour():
    # 1 mm steps resolve the 2.5 mm kernel: the depth is exact to 0.1 mm ...
    d, sdf = ray_through_surface(2.003, n=401, spacing=0.001)
    assert composite(sdf, d, None, beta=0.05).depth.item() == pytest.approx(2.003, abs=1e-4)
    # ... while the authors' 1 cm steps pull it towards the nearest sample (here by 0.9 mm)
    d, sdf = ray_through_surface(2.003)
    col = torch.where((d < 2.003)[..., None], torch.tensor([1.0, 0, 0], dtype=torch.float64),
                      torch.tensor([0, 0, 1.0], dtype=torch.float64))
    out = composite(sdf, d, col, beta=0.05)
    assert out.hit.item()
    assert out.depth.item() == pytest.approx(2.003, abs=2e-3)
    assert out.color[0].sum().item() == pytest.approx(1.0)
    empty = composite(torch.full((1, 5), 50.0), torch.linspace(1, 2, 5)[None], None, beta=0.05)
    assert not empty.hit.item() and empty.depth.item() == 0


def test_colour_only_where_the_weight_is_not_negligible():
    """Colour evaluated at the few samples that weigh (normalised weight > floor) renders the same
    colour and colour gradient as at every sample, and is not darkened by the skipped ones."""
    g = torch.Generator().manual_seed(0)
    surf = 1.5 + torch.rand(64, 1, generator=g, dtype=torch.float64)
    d = surf + 0.01 * (torch.arange(11, dtype=torch.float64) - 5)  # the band: 11 samples 1 cm apart
    d = d + 0.004 * torch.rand(d.shape, generator=g, dtype=torch.float64)
    sdf = (surf - d) / TR
    mask = torch.ones_like(sdf, dtype=torch.bool)
    col = torch.rand(64, 11, 3, generator=g, dtype=torch.float64, requires_grad=True)
    need = color_samples(sdf, 0.05, mask, 1e-3)
    assert 0.1 < need.double().mean() < 0.5  # most band samples weigh ~0 with the paper's beta
    assert torch.equal(color_samples(sdf, 0.05, mask, 0.0), mask)
    full = composite(sdf, d, col, 0.05, mask)
    part = composite(sdf, d, torch.where(need[..., None], col, torch.zeros_like(col)), 0.05, mask, color_mask=need)
    assert torch.allclose(part.depth, full.depth) and torch.equal(part.hit, full.hit)
    assert (part.color - full.color).abs().max() < 0.01
    (gf,) = torch.autograd.grad(full.color.sum(), col)
    (gp,) = torch.autograd.grad(part.color.sum(), col)
    assert (gp - gf)[need].abs().max() < 0.01 and gf[~need].abs().max() < 0.011
    # without renormalising over the evaluated samples the skipped ones would darken the ray
    dark = composite(sdf, d, torch.where(need[..., None], col, torch.zeros_like(col)), 0.05, mask)
    assert (dark.color.sum(-1) <= part.color.sum(-1) + 1e-12).all()


def test_depth_and_rgb_l1():
    assert depth_l1(torch.tensor([1.0, 2.0, 5.0]), torch.tensor([1.5, 2.0, 0.0])).item() == pytest.approx(0.25)
    assert rgb_l1(torch.zeros(4, 3), torch.full((4, 3), 0.2)).item() == pytest.approx(0.2)


def test_s3im_zero_for_identical_and_grows_with_noise():
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(4096, 3, generator=g)
    assert s3im(gt, gt, generator=g).item() == pytest.approx(0.0, abs=1e-6)
    small = s3im((gt + 0.05 * torch.randn(4096, 3, generator=g)).clamp(0, 1), gt, generator=g).item()
    big = s3im((gt + 0.3 * torch.randn(4096, 3, generator=g)).clamp(0, 1), gt, generator=g).item()
    assert 0 < small < big
    pred = gt.clone().requires_grad_(True)
    s3im(pred * 0.9, gt, generator=g).backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0


def test_exact_sdf_has_zero_losses():
    d, sdf = ray_through_surface(2.0, start=1.0, n=141)
    mask = torch.ones_like(d, dtype=torch.bool)
    fs, sd = free_space_and_sdf(sdf, d, torch.tensor([2.0], dtype=torch.float64), mask, TR)
    # in front of the band the exact SDF exceeds the truncation (1), so the fs loss is not 0 there;
    # the truncated target it is pulled to is 1
    assert sd.item() == pytest.approx(0.0, abs=1e-12)
    clipped = sdf.clamp(max=1.0)
    fs0, _ = free_space_and_sdf(clipped, d, torch.tensor([2.0], dtype=torch.float64), mask, TR)
    assert fs0.item() == pytest.approx(0.0, abs=1e-12) and fs.item() > 0


def test_free_space_and_sdf_values():
    d = torch.tensor([[1.0, 1.5, 1.98, 2.0, 2.02, 2.2]])
    pred = torch.tensor([[0.0, 1.0, 0.0, 0.0, 0.0, 0.0]])
    fs, sd = free_space_and_sdf(pred, d, torch.tensor([2.0]), torch.ones_like(d, dtype=torch.bool), TR)
    assert fs.item() == pytest.approx((1.0 + 0.0) / 2)  # samples at 1.0 and 1.5 are free space
    targets = torch.tensor([0.4, 0.0, -0.4])  # samples 1.98, 2.0, 2.02 are in the band
    assert sd.item() == pytest.approx(float(((TR * targets) ** 2).mean()), rel=1e-5)  # metres^2 (authors' units)
    # rays without valid depth and masked samples do not count
    fs, sd = free_space_and_sdf(pred, d, torch.tensor([0.0]), torch.ones_like(d, dtype=torch.bool), TR)
    assert fs.item() == 0 and sd.item() == 0


def test_surface_aware_rule_drops_negative_targets_past_second_sign_change():
    # a thin object: predicted SDF goes + - + before the measured surface at 2.0 m; samples past the
    # second sign change with negative targets (behind the measurement) must not be supervised
    d = torch.tensor([[1.97, 1.98, 1.99, 2.00, 2.01, 2.02, 2.03]])
    gt = torch.tensor([2.0])
    pred = torch.tensor([[0.5, -0.5, 0.5, 0.5, 0.5, 0.5, 0.5]])  # sign changes at samples 1 and 2
    mask = torch.ones_like(d, dtype=torch.bool)
    _, aware = free_space_and_sdf(pred, d, gt, mask, TR, surface_aware=True)
    _, vanilla = free_space_and_sdf(pred, d, gt, mask, TR, surface_aware=False)
    t = (gt - d[0]) / TR
    e = (TR * (pred[0] - t)) ** 2
    assert vanilla.item() == pytest.approx(float(e.mean()), rel=1e-5)
    assert aware.item() == pytest.approx(float(e[:4].mean()), rel=1e-5)  # samples 4..6 (t < 0) dropped
    assert math.isfinite(aware.item())


def test_sdf_targets_end_where_the_band_behind_ends():
    """Band samples deeper behind the measured depth than ``behind`` take no SDF target."""
    d = torch.tensor([[1.98, 2.0, 2.01, 2.03, 2.05]])
    gt = torch.tensor([2.0])
    pred = torch.tensor([[0.4, 0.0, -0.2, 0.0, 0.0]])  # exact at the first three, wrong at 3 and 5 cm behind
    mask = torch.ones_like(d, dtype=torch.bool)
    _, deep = free_space_and_sdf(pred, d, gt, mask, TR, surface_aware=False)
    _, short = free_space_and_sdf(pred, d, gt, mask, TR, surface_aware=False, behind=0.02 / TR)
    assert deep.item() > 0
    assert short.item() == pytest.approx(0.0, abs=1e-12)


def test_window_crossing_is_the_first_sign_change_between_valid_samples():
    """The first + to - change between neighbouring valid samples, linearly interpolated; none on a
    ray without one, and none across a masked-out sample."""
    from h3edge.mapping.raymarch import window_crossing

    t = torch.linspace(1.0, 1.08, 9)[None].repeat(4, 1)
    sdf = torch.tensor([[0.9, 0.5, 0.3, -0.3, -0.9, 0.4, -0.2, -0.5, -0.6],   # first crossing at 1.025
                        [0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2, 0.1],       # none
                        [-0.5, -0.4, 0.2, 0.1, -0.1, -0.2, -0.3, -0.4, -0.5],  # - to + is no surface: 1.035
                        [0.9, 0.5, 0.3, -0.3, -0.9, 0.4, -0.2, -0.5, -0.6]])
    mask = torch.ones_like(sdf, dtype=torch.bool)
    mask[3, 3] = False  # the first change straddles a sample outside the voxels: the next one counts
    tz, found = window_crossing(sdf, t, mask)
    assert found.tolist() == [True, False, True, True]
    assert tz[0].item() == pytest.approx(1.025, abs=1e-6)
    assert tz[2].item() == pytest.approx(1.035, abs=1e-6)
    assert tz[3].item() == pytest.approx(1.05 + 0.01 * 0.4 / 0.6, abs=1e-6)
