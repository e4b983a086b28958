"""Metrics on known answers."""

import numpy as np
import pytest
import trimesh

from h3edge.eval.cull import cull_mesh
from h3edge.eval.evaluate import MeshRenderer, evaluate_views
from h3edge.eval.metrics import (
    accuracy_completion,
    depth_error_map,
    depth_error_shares,
    depth_l1,
    far_share_from,
    mesh_to_mesh,
    psnr,
    sample_surface,
    ssim,
)
from h3edge.geometry.camera import Intrinsics, look_at


def test_psnr_known_answers():
    rng = np.random.default_rng(0)
    img = rng.uniform(0.2, 0.8, (64, 64, 3))
    assert psnr(img, img) == float("inf")
    assert psnr(img + 0.1, img) == pytest.approx(20.0, abs=1e-9)  # MSE = 0.01
    sigma = 0.05
    noisy = img + rng.normal(0, sigma, img.shape)
    assert psnr(noisy, img) == pytest.approx(-20 * np.log10(sigma), abs=0.1)
    u8 = (img * 255).astype(np.uint8)
    assert psnr(np.clip(u8.astype(int) + 5, 0, 255).astype(np.uint8), u8) == pytest.approx(
        20 * np.log10(255 / 5), abs=1e-6
    )
    mask = np.zeros((64, 64), bool)
    mask[:10] = True
    off = img.copy()
    off[10:] += 0.5
    assert psnr(off, img, mask) == float("inf")


def test_ssim_known_answers():
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 1, (64, 64, 3))
    assert ssim(img, img) == pytest.approx(1.0)
    # constant images: only the luminance term remains, (2ab + C1) / (a^2 + b^2 + C1), C1 = (0.01 L)^2
    a, b, c1 = 0.5, 0.7, 0.01 ** 2
    flat_a, flat_b = np.full((32, 32, 3), a), np.full((32, 32, 3), b)
    assert ssim(flat_a, flat_b) == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), rel=1e-6)
    noisier = [ssim(np.clip(img + rng.normal(0, s, img.shape), 0, 1), img) for s in (0.02, 0.1, 0.3)]
    assert noisier[0] > noisier[1] > noisier[2]


def test_depth_l1_counts_holes():
    gt = np.full((4, 4), 2.0, np.float32)
    gt[0, 0] = 0  # invalid GT pixel ignored
    pred = gt + 0.01
    pred[0, 0] = 100
    assert depth_l1(pred, gt) == (pytest.approx(0.01, abs=1e-6), 1.0)
    pred[1, 1] = 0  # hole: full depth as error
    e, cov = depth_l1(pred, gt)
    assert e == pytest.approx((14 * 0.01 + 2.0) / 15, abs=1e-6) and cov == pytest.approx(14 / 15)


def _plane(z=0.0):
    return trimesh.Trimesh([[0, 0, z], [1, 0, z], [1, 1, z], [0, 1, z]], [[0, 1, 2], [0, 2, 3]], process=False)


def test_identical_meshes_zero():
    pts = sample_surface(_plane(), 50_000, seed=0)
    m = accuracy_completion(pts, pts)
    assert m["accuracy"] == 0 and m["completion"] == 0 and m["completion_ratio"] == 1


def test_shifted_mesh_about_one_cm():
    gt = sample_surface(_plane(0.0), 200_000, seed=0)
    rc = sample_surface(_plane(0.01), 200_000, seed=1)
    m = accuracy_completion(rc, gt)
    assert m["accuracy"] == pytest.approx(0.01, abs=0.001)
    assert m["completion"] == pytest.approx(0.01, abs=0.001)
    far = accuracy_completion(sample_surface(_plane(0.1), 20_000, seed=1), gt)
    assert far["completion_ratio"] == 0


def test_cull_removes_unseen_and_occluded():
    # camera at z = 2 looking down at a small near plane (z = 1) that hides the centre of a big
    # floor (z = 0); floor parts outside the frustum and under the near plane are culled
    floor = trimesh.creation.box((4, 4, 0.01))
    floor = floor.subdivide_to_size(0.05)
    floor.apply_translation([0, 0, -0.005])
    cover = trimesh.creation.box((0.6, 0.6, 0.01)).subdivide_to_size(0.05)
    cover.apply_translation([0, 0, 1.0])
    scene = trimesh.util.concatenate([floor, cover])
    intr = Intrinsics(64, 64, 40, 40, 32, 32)  # ~77 deg: sees about |x|, |y| < 1.6 of the floor at 2 m
    T = look_at(np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.01, 0.0]))
    culled = cull_mesh(scene, T[None], intr)
    c = culled.triangles_center
    top_floor = c[np.isclose(c[:, 2], 0.0, atol=1e-3)]
    assert len(top_floor) > 0
    assert np.abs(top_floor[:, :2]).max() < 1.7  # outside the frustum: gone
    under = (np.abs(top_floor[:, 0]) < 0.2) & (np.abs(top_floor[:, 1]) < 0.2)
    assert not under.any()  # occluded by the cover: gone
    assert (c[:, 2] > 1.0).any()  # the cover's top is seen


def test_view_metrics_on_self(tiny_scene):
    from h3edge.io import open_sequence
    seq = open_sequence(tiny_scene)
    res = evaluate_views(MeshRenderer(trimesh.load(seq.gt_mesh_path, process=False)), seq, stride=10)
    assert res["views"] == 4
    assert res["depth_l1_cm"] < 0.01 and res["depth_coverage"] > 0.99
    assert res["psnr_db"] > 25


def test_depth_error_shares_and_map_known_answers():
    gt = np.full((10, 10), 2.0, np.float32)
    gt[0] = 0  # no sensor depth: not counted
    pred = gt.copy()
    pred[1] = 1.9  # 10 cm in front: 10 of 90 valid pixels
    pred[2, :5] = 2.2  # 20 cm behind: 5
    pred[3, :3] = 0  # not rendered: 3
    pred[4] = 2.03  # within 5 cm
    sh = depth_error_shares(pred, gt, 0.05)
    assert sh["front_share"] == pytest.approx(10 / 90) and sh["behind_share"] == pytest.approx(5 / 90)
    assert sh["missing_share"] == pytest.approx(3 / 90) and sh["median_abs_m"] == pytest.approx(0.0)
    img = depth_error_map(pred, gt, 0.05)
    assert (img[0] == 0).all() and tuple(img[1, 0]) == (220, 30, 30) and tuple(img[2, 0]) == (30, 60, 230)
    assert tuple(img[3, 0]) == (255, 255, 255) and tuple(img[4, 0]) == (190, 190, 190)


def test_mesh_to_mesh_both_directions():
    a = trimesh.creation.box((1.0, 1.0, 1.0))
    b = a.copy()
    b.apply_translation((0.0, 0.0, 0.1))  # 10 cm up: top and bottom far, sides slide
    extra = trimesh.creation.box((0.2, 0.2, 0.2))
    extra.apply_translation((3.0, 0.0, 0.0))
    d = mesh_to_mesh(trimesh.util.concatenate([a, extra]), a, n=20000, threshold=0.05)
    assert d["b_to_a_far_share"] < 0.01  # a is covered by itself + extra
    assert d["a_to_b_far_share"] == pytest.approx(extra.area / (a.area + extra.area), abs=0.02)
    same = mesh_to_mesh(a, a, n=20000)
    assert same["a_to_b_mean"] < 0.01 and same["a_to_b_far_share"] == 0.0
    shifted = mesh_to_mesh(b, a, n=20000)
    assert 0.2 < shifted["a_to_b_far_share"] < 0.45  # most of top and bottom are 10 cm off
    from_a = far_share_from(a, n=20000, threshold=0.05)  # one tree for every mesh: the same answers
    assert from_a(b) == shifted["a_to_b_far_share"] and from_a(a) == 0.0
    assert from_a(trimesh.Trimesh()) == 1.0


def test_a_large_covered_surface_reads_covered_whatever_the_sample_count():
    """Distances go to a sampling dense for the threshold, not to ``n`` samples: 50,000 samples of
    a 12 x 10 m wall lie ~5 cm apart, and measured to those a wall covered by itself would read
    a few % farther than 5 cm."""
    wall = trimesh.Trimesh(vertices=[[0, 0, 0], [12, 0, 0], [12, 0, 10], [0, 0, 10]], faces=[[0, 1, 2], [0, 2, 3]])
    d = mesh_to_mesh(wall, wall.copy(), n=50_000, threshold=0.05)
    assert d["a_to_b_far_share"] == 0.0 and d["b_to_a_far_share"] == 0.0
    near = wall.copy()
    near.apply_translation((0.0, 0.04, 0.0))  # 4 cm in front: covered
    assert mesh_to_mesh(near, wall, n=50_000, threshold=0.05)["a_to_b_far_share"] == 0.0


def test_colour_regions_split_the_valid_pixels():
    """The colour-error regions are disjoint and cover the valid pixels: the band follows the depth
    step, a wrong render off the band is ``depth_off``, texture is where the colour changes."""
    from benchmarks.color_regions import regions

    depth = np.full((48, 64), 2.0, np.float32)
    depth[:, :32] = 1.0  # a step at column 32
    depth[0, :] = 0.0  # invalid row
    color = np.full((48, 64, 3), 128, np.uint8)
    color[30:, 50:] = np.indices((18, 14)).sum(0)[..., None] % 2 * 255  # a checkerboard off the step
    rendered = depth.copy()
    rendered[10, 5] += 0.05
    m = regions(color, depth, rendered)
    stack = np.stack(list(m.values()))
    assert (stack.sum(0) == (depth > 0)).all()  # disjoint, and exactly the valid pixels
    cols = np.flatnonzero(m["edge"].any(0))
    assert cols.min() >= 25 and cols.max() <= 37 and m["edge"][1:, 31].all() and m["edge"][1:, 32].all()
    assert m["depth_off"][10, 5] and m["depth_off"].sum() == 1
    assert m["texture"][30:, 50:].mean() > 0.5 and not m["texture"][1:20, :20].any()


def test_colour_regions_report_each_view_beside_the_pooled_figures():
    """Per view, the PSNR of the whole image and of each region (``per_view``), whereas the regions'
    PSNR pools the pixels of all views: one bad view dominates the pooled figure, not every view's."""
    from benchmarks.color_regions import summarise

    def view(sse_h: float, sse_t: float) -> dict:
        count = {"edge": 10, "depth_off": 0, "texture": 20, "rest": 70}
        return {"pixels": 100, "count": count,
                "sse_all": {"h3edge": sse_h, "tsdf": sse_t, "oracle": 0.01},
                "sse": {r: {"h3edge": sse_h * n / 100, "tsdf": sse_t * n / 100, "oracle": 0.01 * n / 100}
                        for r, n in count.items()},
                **{f"edge_{k}": {"right": 10, "front": 0, "behind": 0} for k in ("h3edge", "tsdf")}}

    res = summarise([view(0.01, 0.001), view(0.01, 1.0)])  # TSDF better on one view, far worse on the other
    per_view = res["per_view"]
    assert len(per_view) == 2
    assert per_view[0]["psnr_db"]["tsdf"] == pytest.approx(50.0)
    assert per_view[0]["psnr_db"]["h3edge"] == pytest.approx(40.0)
    assert per_view[1]["psnr_db"]["tsdf"] == pytest.approx(20.0)
    assert per_view[0]["rest"]["pixel_share"] == pytest.approx(0.7)
    assert per_view[0]["rest"]["psnr_tsdf"] == pytest.approx(50.0) and per_view[0]["depth_off"]["psnr_tsdf"] is None
    assert res["rest"]["psnr_tsdf"] < res["rest"]["psnr_h3edge"]  # pooled: TSDF's bad view wins
