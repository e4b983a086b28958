"""H3 texture patterns and quasi-heterogeneous grids: R(DIR), warps, hash separation, direction
and gradient fusion, line validation, the encoder's zero-padded blocks, gradient-aided scores."""

import math

import numpy as np
import pytest
import torch

from h3edge.geometry.camera import Intrinsics
from h3edge.mapping.gradient import color_gradient
from h3edge.mapping.hashgrid import HashGridSpec, corner_indices_torch
from h3edge.mapping.keyframes import KeyframeConfig, KeyframeSet
from h3edge.mapping.texture_grid import WARP_HASHES, QuasiHeteroTexture
from h3edge.mapping.texture_patterns import (
    PLAIN,
    RICH,
    WEAK,
    TextureConfig,
    TexturePatterns,
    affine_matrix,
    fuse_frame_directions,
    lift_segments,
    line_rotation,
    voxel_gradient_stats,
)

EZ = np.array([0.0, 0.0, 1.0])


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def is_prime(n: int) -> bool:
    return n > 1 and all(n % p for p in range(2, math.isqrt(n) + 1))


# ---------------------------------------------------------------- R(DIR), warps
def test_rotation_maps_dir_to_z_and_is_orthonormal():
    d = unit(np.random.default_rng(0).normal(size=(500, 3)))
    R = line_rotation(d)
    eye = np.broadcast_to(np.eye(3), R.shape)
    assert np.allclose(R @ np.swapaxes(R, 1, 2), eye, atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    mapped = np.einsum("nji,nj->ni", R, d)  # R^T d
    assert np.allclose(np.abs(mapped), EZ, atol=1e-12)  # +z, or -z for the flipped (same line) direction
    up = d[:, 2] >= 0
    assert np.allclose(mapped[up], EZ, atol=1e-12)


def test_rotation_is_the_papers_formula():
    bx, by, bz = unit([0.3, -0.5, 0.8])
    k = 1 / (1 + bz)
    paper = np.array([[bz + by * by * k, -bx * by * k, bx], [-bx * by * k, 1 - by * by * k, by], [-bx, -by, bz]])
    assert np.allclose(line_rotation(np.array([bx, by, bz])), paper)


@pytest.mark.parametrize("d", [[0, 0, -1.0], [0, 0, 1.0], [1e-9, 0, -1.0], [1.0, 0, 0], [0, 1.0, 0]])
def test_rotation_edge_cases(d):
    R = line_rotation(np.array(d))
    assert np.all(np.isfinite(R))
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.allclose(np.abs(R.T @ unit(d)), EZ, atol=1e-9)
    if d[2] == -1.0 and d[0] == 0:
        assert np.allclose(R, np.eye(3))  # -z is the z line


def test_affine_warp_compresses_along_dir_only():
    d = unit([1.0, 2.0, -0.5])
    A = affine_matrix(d, 0.1)
    perp = unit(np.cross(d, [0.0, 0.0, 1.0]))
    assert np.isclose(np.linalg.norm(A @ d), 0.1)
    assert np.isclose(np.linalg.norm(A @ perp), 1.0)
    assert np.isclose(abs(np.dot(A @ d, A @ perp)), 0.0, atol=1e-12)


def _encoder(cfg=TextureConfig(), log2=14, voxel=0.1):
    bound = np.array([[0.0] * 3, [1.6] * 3])
    spec = HashGridSpec(4, 2, log2, int(1.6 / voxel), 3.0)
    return QuasiHeteroTexture(spec, bound, cfg, backend="torch", seed=0), bound


def _warps(anchor_scale: float, dirs: np.ndarray, n=2000):
    """A 3x3x3 block of voxels, each with its own direction for m = 0: the encoder, the voxels'
    normalised samples and their warped images."""
    enc, bound = _encoder(TextureConfig(anchor_scale=anchor_scale))
    ijk = np.stack(np.meshgrid(*[np.arange(5, 8)] * 3, indexing="ij"), -1).reshape(-1, 3)
    V = len(ijk)
    enc.set_warps(ijk, 0.1, np.full(V, RICH, np.int8), np.stack([dirs, dirs], 1), np.ones(V, np.int64))
    rng = np.random.default_rng(1)
    warped = []
    for v in range(V):
        x = (ijk[v] + rng.uniform(0, 1, (n, 3))) * 0.1
        xn = enc.grid.normalise(torch.tensor(x, dtype=torch.float32))
        warped.append(enc.warp_affine(xn, torch.full((n,), v), 0))
    return enc, ijk, warped


def _lands_in(enc, ijk, w: torch.Tensor, i: int) -> np.ndarray:
    """Which warped points ``w`` are also images of points of voxel i (its warp inverted)."""
    c = enc.centres[i]
    x = c + torch.linalg.solve(enc.affine[i, 0], (w - enc.cfg.anchor_scale * c).T).T
    vox = np.floor(x.numpy() * 1.6 / 0.1 + 1e-9).astype(int)
    return np.all(vox == ijk[i], axis=1)


def test_affine_warps_of_different_voxels_never_collide():
    dirs = unit(np.random.default_rng(2).normal(size=(27, 3)))
    dirs[:9] = unit([1.0, 1.0, 1.0])  # the worst case: neighbours sharing an oblique direction
    enc, ijk, warped = _warps(2.0, dirs)
    for i in range(len(ijk)):
        for j in range(len(ijk)):
            if i != j:
                assert not _lands_in(enc, ijk, warped[j], i).any(), (i, j)


def test_paper_anchor_lets_oblique_neighbours_overlap():
    """Why the device profiles set anchor_scale 2 (D0-7): about the centre itself (1, the paper's), an
    oblique direction reaches into the warped region of the neighbour with the same direction."""
    enc, ijk, warped = _warps(1.0, np.tile(unit([1.0, 1.0, 1.0]), (27, 1)))
    assert _lands_in(enc, ijk, warped[22], 13).mean() > 0.01  # the central voxel and its +x neighbour


def test_hash_functions_are_distinct_and_separate_warps():
    primes = {p for h in WARP_HASHES for p in (*h.primes, *h.offsets) if p > 1}
    assert all(is_prime(p) for p in primes)
    assert len({(h.primes, h.offsets) for h in WARP_HASHES}) == len(WARP_HASHES)
    spec = HashGridSpec(4, 2, 16, 20, 3.0)
    xn = torch.rand(20_000, 3, generator=torch.Generator().manual_seed(0)) * 1.5 - 0.25
    rows = [corner_indices_torch(xn, spec, h)[0] for h in WARP_HASHES]
    for i in range(len(rows)):
        for j in range(i + 1, len(rows)):
            same = (rows[i] == rows[j]).float().mean().item()
            assert same < 0.01  # the same vertex lands on the same row only by chance (~1/T)


# ------------------------------------------------------------------- fusion
def test_frame_fusion_groups_near_directions_sign_free():
    d0 = unit([1.0, 0.0, 0.0])
    near = unit([1.0, 0.05, 0.0])
    perp = unit([0.0, 1.0, 0.0])
    vox = np.array([7, 7, 7, 7, 3])
    dirs = np.stack([d0, -near, near, perp, perp])
    w = np.array([5.0, 2.0, 1.0, 4.0, 1.0])
    rounds = fuse_frame_directions(vox, dirs, w, max_dirs=2, tr_near=0.95)
    ids0, dir0, w0 = rounds[0]
    assert list(ids0) == [3, 7]
    k = list(ids0).index(7)
    expect = unit(5 * d0 + 2 * near + 1 * near)  # -near flipped onto d_max's sign
    assert np.allclose(dir0[k], expect) and np.isclose(w0[k], 8.0)
    ids1, dir1, w1 = rounds[1]
    assert list(ids1) == [7] and np.allclose(np.abs(dir1[0]), perp) and np.isclose(w1[0], 4.0)


def test_across_frame_update_and_adoption():
    tp = TexturePatterns(TextureConfig(max_directions=2))
    a, b, c = unit([1, 0, 0]), unit([0, 1, 0]), unit([0, 0, 1])
    tp.fuse_directions(np.array([0]), a[None], np.array([2.0]))
    tp.fuse_directions(np.array([0]), -unit([1, 0.1, 0])[None], np.array([2.0]))  # same line: weighted update
    assert tp.n_dirs[0] == 1 and np.isclose(tp.dir_weights[0, 0], 4.0)
    assert np.allclose(tp.dirs[0, 0], unit(a + unit([1, 0.1, 0])))
    tp.fuse_directions(np.array([0]), b[None], np.array([1.0]))  # new direction adopted (m < M)
    tp.fuse_directions(np.array([0]), c[None], np.array([9.0]))  # M reached: not adopted
    assert tp.n_dirs[0] == 2 and np.allclose(tp.dirs[0, 1], b) and np.isclose(tp.dir_weights[0].sum(), 5.0)


def test_gradient_fusion_and_class_priority():
    tp = TexturePatterns(TextureConfig(tr_weak=0.2))
    tp.fuse_gradient(np.array([0, 1, 2]), np.array([100.0, 100.0, 100.0]), np.array([0.1, 0.5, 0.1]))
    tp.fuse_gradient(np.array([0, 1]), np.array([300.0, 100.0]), np.array([0.3, 0.5]))
    assert np.allclose(tp.G[:3], [0.25, 0.5, 0.1]) and np.allclose(tp.CNT[:3], [400, 200, 100])
    tp.fuse_directions(np.array([2]), unit([1, 0, 0])[None], np.array([1.0]))
    cls = tp.classes(4)
    assert list(cls) == [PLAIN, PLAIN, RICH, PLAIN]  # 2 is weak by G but has a direction: rich wins; 3 unseen


def test_voxel_gradient_stats_and_keyframe_score():
    vox = np.array([4, 4, 4, 9, -1])
    g = np.array([0.3, 0.3, 0.6, 0.1, 5.0])
    ids, cnt, gm = voxel_gradient_stats(vox, g, scale=4.0)
    assert list(ids) == [4, 9] and np.allclose(cnt, [12, 4]) and np.allclose(gm, [0.4, 0.1])
    # the gradient-aided score prefers a frame seeing a rich voxel close up over many weak ones
    ks = KeyframeSet(KeyframeConfig(per_iteration=1))
    ks.insert(0, np.arange(30), np.maximum(np.full(30, 20.0) ** 2 * 0.01, 1))  # 30 weak voxels: 4 each
    ks.insert(1, np.arange(30, 33), np.maximum(np.full(3, 200.0) ** 2 * 0.5, 1))  # 3 rich voxels, close
    assert ks.select()[0].frame_id == 1


# --------------------------------------------------------- line validation
def _plane_and_corner_depth(h=120, w=160, f=100.0):
    intr = Intrinsics(w, h, f, f, w / 2, h / 2)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x = (u - intr.cx) / f
    # left half: a wall at z = 2; right half: a wedge folding towards the camera (a corner at u = w/2)
    z = np.where(u < w / 2, 2.0, 2.0 / (1 + 1.0 * x))
    z[:, 120:] = 1.0  # a box in front: a depth step at u = 120
    return intr, z.astype(np.float32)


def test_plane_check_and_depth_steps():
    intr, depth = _plane_and_corner_depth()
    segs = np.array([[10, 20, 70, 90],  # on the wall: kept
                     [40, 60, 110, 60],  # across the fold: its midpoint leaves the surface -> plane check
                     [100, 30, 140, 30],  # across the depth step at u = 120
                     [10, 100, 14, 100]],  # too short
                    np.float32)
    ends, w, keep = lift_segments(segs, np.ones(4, np.float32), depth, intr, np.eye(4), TextureConfig())
    assert list(keep) == [True, False, False, False]
    assert np.allclose(ends[0, :, 2], 2.0)


def _kinect_depth(z: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A Kinect v1's depth of true depth ``z``: disparity (focal x baseline 43.5 px m) with noise of
    1/16 px, quantised to 1/8 px, as the sensor reports it (steps of ~1.8 cm at 2.5 m)."""
    disparity = 43.5 / z + rng.normal(0.0, 1 / 16, z.shape)
    return (43.5 / (np.round(disparity * 8) / 8)).astype(np.float32)


def test_kinect_depth_steps_are_not_occlusion_edges():
    """The colour gradient leaves out occlusion edges, not depth noise. On a textured wall seen at
    2-3 m through a Kinect's quantised depth the authors' test (depth Laplacian > 1 cm) zeroed
    most pixels (45-65 % of a real 7-Scenes frame's), and the wall read as weak texture; a
    relative jump keeps the wall's texture and still finds both sides of a box's outline 1 m in
    front of it."""
    rng = np.random.default_rng(0)
    h, w = 120, 160
    u = np.arange(w, dtype=np.float32)[None, :].repeat(h, 0)
    z = 2.0 + u / w  # a wall receding from 2 to 3 m across the view
    box = (slice(40, 80), slice(60, 100))
    z[box] -= 1.0
    depth = _kinect_depth(z, rng)
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)  # texture everywhere
    g = color_gradient(rgb, depth, 0.05)
    textured = color_gradient(rgb) > 0.2
    wall = np.ones((h, w), bool)
    wall[35:85, 55:105] = False  # the box and 5 px around it
    assert textured[wall].mean() > 0.95
    assert (g[wall] > 0.2).mean() > 0.9  # the authors' test: 0.08
    outline = np.zeros((h, w), bool)
    outline[40:80, 59:61] = outline[40:80, 99:101] = True  # both sides of the box's vertical edges
    assert (g[outline] == 0).all()
    assert (g[box][1:-1, 1:-1] > 0.2).mean() > 0.9  # the box's own face keeps its texture


def test_update_finds_stripe_directions_on_a_synthetic_wall():
    """Stripes along y on a fronto-parallel wall: the voxels get the y direction; the flat part is weak."""
    from h3edge.mapping.voxels import VoxelConfig, VoxelMap

    h, w, f = 240, 320, 200.0
    intr = Intrinsics(w, h, f, f, w / 2, h / 2)
    depth = np.full((h, w), 1.0, np.float32)
    rgb = np.full((h, w, 3), 128, np.uint8)
    for u0 in range(20, 150, 16):
        rgb[:, u0:u0 + 8] = 30  # vertical stripes on the left half
    vm = VoxelMap(VoxelConfig(min_points=3))
    vm.allocate(depth, intr, np.eye(4))
    v, u = np.mgrid[0:h, 0:w]
    pts = np.stack([(u - intr.cx) / f, (v - intr.cy) / f, np.ones_like(u, float)], -1)
    tp = TexturePatterns(TextureConfig())
    info = tp.update(rgb, depth, intr, np.eye(4), pts, vm.locate, 0.1, color_gradient(rgb, depth, 0.05))
    assert info["lines"] > 5
    cls = tp.classes(len(vm))
    rich = np.flatnonzero(cls == RICH)
    assert len(rich) > 0
    assert np.all(np.abs(tp.dirs[rich, 0, 1]) > 0.99)  # the stripes run along y
    right = vm.locate(np.array([[0.5, 0.0, 1.05]]))[0][0]  # a voxel on the flat right half
    assert cls[right] == WEAK


# ----------------------------------------------------------------- encoder
def test_encoder_blocks_are_zero_padded_and_train_one_table():
    enc, _ = _encoder(TextureConfig(scaling_everywhere=False))  # the paper's layout
    ijk = np.array([[1, 1, 1], [2, 1, 1], [3, 1, 1]])
    cls = np.array([PLAIN, WEAK, RICH], np.int8)
    dirs = np.zeros((3, 2, 3))
    dirs[2] = [unit([1, 1, 0]), unit([0, 0, 1])]
    enc.set_warps(ijk, 0.1, cls, dirs, np.array([0, 0, 2]))
    x = torch.tensor((ijk + 0.3) * 0.1, dtype=torch.float32)
    vox = torch.arange(3)
    enc.grid.table.data.uniform_(-1, 1)
    feats = enc(x, vox)
    B = enc.block
    assert feats.shape == (3, 4 * B) and enc.out_dim == 4 * B
    nz = (feats.abs().reshape(3, 4, B).sum(-1) > 0).numpy()
    assert nz.tolist() == [[True, False, False, False], [True, True, False, False], [True, False, True, True]]
    assert torch.allclose(feats[:, :B], enc.grid(x))  # identity block = the plain hash grid
    # unknown voxels (-1 or allocated after the last determination) get identity features only
    f2 = enc(x, torch.tensor([-1, 7, 2]))
    assert (f2[:2, B:] == 0).all() and (f2[2, B:] != 0).any()
    feats.sum().backward()
    rows, g = enc.grid.take_sparse_grad()
    assert len(rows) > 0 and torch.isfinite(g).all()


@pytest.mark.parametrize("flag", ["warp_rich", "warp_weak"])
def test_warp_switches(flag):
    enc, _ = _encoder(TextureConfig(scaling_everywhere=False, **{flag: False}))
    ijk = np.array([[1, 1, 1], [2, 1, 1]])
    dirs = np.zeros((2, 2, 3))
    dirs[1, 0] = unit([1, 0, 0])
    enc.set_warps(ijk, 0.1, np.array([WEAK, RICH], np.int8), dirs, np.array([0, 1]))
    assert enc.weak.tolist() == [flag == "warp_rich", False]
    assert enc.n_dirs.tolist() == [0, 0 if flag == "warp_rich" else 1]


def test_scaling_warp_everywhere_gives_every_voxel_the_low_frequency_block():
    """``scaling_everywhere``: the scaling-warped features for every classified voxel (no block
    switching between neighbours of different class); directional warps stay per class; with the
    scaling warp off it has no effect."""
    ijk = np.array([[1, 1, 1], [2, 1, 1], [3, 1, 1]])
    cls = np.array([PLAIN, WEAK, RICH], np.int8)
    dirs = np.zeros((3, 2, 3))
    dirs[2, 0] = unit([1, 0, 0])
    enc, _ = _encoder(TextureConfig(scaling_everywhere=True))
    enc.set_warps(ijk, 0.1, cls, dirs, np.array([0, 0, 1]))
    assert enc.weak.tolist() == [True, True, True] and enc.n_dirs.tolist() == [0, 0, 1]
    enc.grid.table.data.uniform_(-1, 1)
    feats = enc(torch.tensor((ijk + 0.3) * 0.1, dtype=torch.float32), torch.arange(3))
    nz = (feats.abs().reshape(3, 4, enc.block).sum(-1) > 0).numpy()
    assert nz.tolist() == [[True, True, False, False], [True, True, False, False], [True, True, True, False]]
    off, _ = _encoder(TextureConfig(scaling_everywhere=True, warp_weak=False))
    off.set_warps(ijk, 0.1, cls, dirs, np.array([0, 0, 1]))
    assert off.weak.tolist() == [False, False, False]


def test_identity_block_can_leave_out_its_finest_levels():
    """``identity_levels``: the identity block encodes only its coarsest levels (zeros after, no
    gradient into the finer levels' rows through it); the warped blocks keep every level."""
    ijk = np.array([[1, 1, 1], [3, 1, 1]])
    dirs = np.zeros((2, 2, 3))
    dirs[1, 0] = unit([1, 0, 0])
    x = torch.tensor((ijk + 0.3) * 0.1, dtype=torch.float32)
    feats = {}
    for n in (0, 3):
        enc, _ = _encoder(TextureConfig(scaling_everywhere=True, identity_levels=n))
        enc.set_warps(ijk, 0.1, np.array([WEAK, RICH], np.int8), dirs, np.array([0, 1]))
        enc.grid.table.data.uniform_(-1, 1, generator=torch.Generator().manual_seed(0))
        feats[n] = enc(x, torch.arange(2))
    B, F = enc.block, enc.grid.spec.features
    assert torch.allclose(feats[3][:, : 3 * F], feats[0][:, : 3 * F])
    assert (feats[3][:, 3 * F: B] == 0).all() and (feats[0][:, 3 * F: B] != 0).all()
    assert torch.allclose(feats[3][:, B:], feats[0][:, B:])  # warped blocks: every level
    with pytest.raises(ValueError):
        _encoder(TextureConfig(identity_levels=5))


def test_level_mask_zeroes_one_level_of_one_block_and_restores():
    """The texture-levels diagnostic (``benchmarks.texture_levels``) reads exactly one block's
    level as zero inside its context and the encoder as trained after it."""
    from benchmarks.texture_levels import LevelMask, level_columns

    enc, _ = _encoder(TextureConfig(scaling_everywhere=True))
    ijk = np.array([[1, 1, 1], [2, 1, 1]])
    enc.set_warps(ijk, 0.1, np.array([WEAK, WEAK], np.int8), np.zeros((2, 2, 3)), np.array([0, 0]))
    enc.grid.table.data.uniform_(-1, 1, generator=torch.Generator().manual_seed(0))
    x, vox = torch.tensor((ijk + 0.3) * 0.1, dtype=torch.float32), torch.arange(2)
    full = enc(x, vox)
    L, F = enc.grid.spec.levels, enc.grid.spec.features
    cols = level_columns(1, 2, L, F)
    assert cols == [1 * L * F + 2 * F + f for f in range(F)]
    with LevelMask(enc, cols):
        masked = enc(x, vox)
    keep = [c for c in range(enc.out_dim) if c not in cols]
    assert (masked[:, cols] == 0).all() and (full[:, cols] != 0).all()
    assert torch.equal(masked[:, keep], full[:, keep])
    assert torch.equal(enc(x, vox), full)
