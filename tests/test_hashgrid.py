"""Hash encoding: against a slow reference, torch vs fused numba, gradients, sparse Adam."""

import math

import numpy as np
import pytest
import torch

from h3edge.mapping.hashgrid import PRIMES, HashFunction, HashGrid, HashGridSpec

BOUND = np.array([[-1.0, -2.0, 0.0], [3.0, 2.0, 1.5]])
SPEC = HashGridSpec(
    levels=4, features=2, log2_table=12, base_resolution=6, per_level_scale=2.0
)  # dense + hashed levels
BACKENDS = ["torch", "numba"]


def reference_encode(grid: HashGrid, x: np.ndarray, fn: HashFunction | None = None, normalised=False) -> np.ndarray:
    """Point-by-point loops over the instant-NGP definition (``fn``: primes, offsets, dense)."""
    spec, T = grid.spec, grid.spec.table_size
    P, D = (PRIMES, (0, 0, 0)) if fn is None else (fn.primes, fn.offsets)
    table = grid.table.detach().numpy()
    lo, size = BOUND[0], BOUND[1] - BOUND[0]
    out = np.zeros((len(x), spec.out_dim))
    for i, p in enumerate(x):
        xn = p if normalised else np.clip((p - lo) / size, 0, 1)
        for l in range(spec.levels):
            scale = spec.base_resolution * spec.per_level_scale ** l - 1
            side = math.ceil(scale) + 2
            dense = side ** 3 <= T and (fn is None or fn.dense)
            pos = xn * scale + 0.5
            g = np.floor(pos).astype(int)
            f = pos - g
            for c in range(8):
                o = np.array([c & 1, (c >> 1) & 1, (c >> 2) & 1])
                v = g + o
                w = np.prod(np.where(o == 1, f, 1 - f))
                if dense:
                    h = v[0] + side * (v[1] + side * v[2])
                else:
                    h = (int(v[0]) * P[0] + D[0]) ^ (int(v[1]) * P[1] + D[1]) ^ (int(v[2]) * P[2] + D[2])
                out[i, l * 2:(l + 1) * 2] += w * table[l * T + (h % T)]
    return out


@pytest.fixture
def points():
    rng = np.random.default_rng(0)
    return rng.uniform(BOUND[0], BOUND[1], (200, 3))


def make_grid(backend, init=0.5):
    return HashGrid(SPEC, BOUND, backend=backend, init_scale=init, seed=3)


def test_spec_has_dense_and_hashed_levels():
    dense = SPEC.level_dense()
    assert dense[0] > 0 and dense[-1] == 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_matches_reference(backend, points):
    grid = make_grid(backend)
    out = grid(torch.tensor(points, dtype=torch.float32)).detach().numpy()
    assert np.allclose(out, reference_encode(grid, points), atol=1e-5)


WARP_FN = HashFunction((1, 2741578211, 1179736007), (15485863, 32452843, 49979687), dense=False)


@pytest.mark.parametrize("features", [2, 3])
def test_backends_agree_across_the_dense_cube_boundary(features):
    """Cells straddling the dense levels' cube mix dense and hashed corners; the numba kernels (F = 2
    and the generic width) index them as the torch path does, forward and backward."""
    spec = HashGridSpec(levels=4, features=features, log2_table=12, base_resolution=6, per_level_scale=2.0)
    xn = torch.tensor(np.random.default_rng(7).uniform(-0.3, 1.3, (300, 3)), dtype=torch.float32)
    assert_backends_agree(lambda b: HashGrid(spec, BOUND, backend=b, init_scale=0.5, seed=3), xn, normalised=True)


@pytest.mark.parametrize("backend", BACKENDS)
def test_second_hash_function_matches_reference(backend):
    """A table read through a second hash function (primes + offsets, always hashed) at normalised
    coordinates outside [0, 1] (warped spaces)."""
    grid = HashGrid(SPEC, BOUND, hash_functions=(HashFunction(), WARP_FN), backend=backend, init_scale=0.5, seed=3)
    xn = np.random.default_rng(5).uniform(-0.5, 2.0, (100, 3))
    out = grid(torch.tensor(xn, dtype=torch.float32), fn=1, normalised=True).detach().numpy()
    assert np.allclose(out, reference_encode(grid, xn, WARP_FN, normalised=True), atol=1e-5)
    x = torch.tensor(xn, dtype=torch.float32)
    (grid(x, fn=1, normalised=True).sum() + grid(x, fn=0, normalised=True).sum()).backward()
    rows, g = grid.take_sparse_grad()
    assert len(torch.unique(rows)) == len(rows)  # two calls, one set of rows


def assert_backends_agree(make, x: torch.Tensor, normalised: bool = False, encode=None) -> None:
    """Grids ``make(backend)`` of both backends give the same features, touched rows and row
    gradients for points ``x`` (``encode(grid, x)``: how the features are read; default one call)."""
    res = {}
    for b in BACKENDS:
        grid = make(b)
        y = encode(grid, x) if encode is not None else grid(x, normalised=normalised)
        (y * torch.arange(y.shape[1], dtype=torch.float32)).sum().backward()
        rows, g = grid.take_sparse_grad()
        order = torch.argsort(rows)
        res[b] = (y.detach(), rows[order], g[order])
    assert torch.allclose(res["torch"][0], res["numba"][0], atol=1e-6)
    assert torch.equal(res["torch"][1], res["numba"][1])
    assert torch.allclose(res["torch"][2], res["numba"][2], atol=1e-5)


def test_backends_agree_forward_and_backward(points):
    assert_backends_agree(make_grid, torch.tensor(points, dtype=torch.float32))


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradient_by_finite_differences(backend, points):
    grid = make_grid(backend)
    x = torch.tensor(points[:20], dtype=torch.float32)
    wts = torch.randn(SPEC.out_dim, generator=torch.Generator().manual_seed(1))
    (grid(x) @ wts).sum().backward()
    rows, g = grid.take_sparse_grad()
    eps = 1e-2
    for k in [0, len(rows) // 2, len(rows) - 1]:
        r = int(rows[k])
        for f in range(SPEC.features):
            with torch.no_grad():
                grid.table[r, f] += eps
                up = float((grid(x) @ wts).sum())
                grid.table[r, f] -= 2 * eps
                down = float((grid(x) @ wts).sum())
                grid.table[r, f] += eps
            assert (up - down) / (2 * eps) == pytest.approx(float(g[k, f]), rel=1e-2, abs=1e-3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_sparse_adam_touches_only_used_rows(backend, points):
    grid = make_grid(backend, init=1e-4)
    before = grid.table.detach().clone()
    x = torch.tensor(points[:10], dtype=torch.float32)
    target = torch.ones(10, SPEC.out_dim)
    losses = []
    for _ in range(30):
        loss = ((grid(x) - target) ** 2).mean()
        loss.backward()
        losses.append(float(loss.detach()))
        n = grid.sparse_adam_step(lr=5e-2)
        assert 0 < n <= 10 * SPEC.levels * 8
    changed = (grid.table.detach() != before).any(1)
    assert changed.sum() <= 10 * SPEC.levels * 8
    assert losses[-1] < 0.5 * losses[0]
    assert grid.table.grad is None  # never a dense gradient


def test_inference_stores_nothing(points):
    grid = make_grid("numba")
    with torch.no_grad():
        y = grid(torch.tensor(points, dtype=torch.float32))
    assert y.shape == (len(points), SPEC.out_dim)


def test_sparse_adam_backends_agree(points):
    x = torch.tensor(points, dtype=torch.float32)
    tables, steps = {}, {}
    for b in BACKENDS:
        grid = make_grid(b)
        for i in range(4):
            pts = x[:0] if i == 1 else x  # a step without points moves nothing and counts no step
            (grid(pts) ** 2).sum().backward()
            assert (grid.sparse_adam_step(lr=1e-2) == 0) == (i == 1)
        tables[b], steps[b] = grid.table.detach(), grid.adam_steps
    assert torch.allclose(tables["torch"], tables["numba"], atol=1e-6)
    assert steps["torch"] == steps["numba"] == 3


def test_backends_agree_over_several_hash_functions(points):
    """Gradients of several calls through different hash functions sum per row on both backends."""
    x = torch.tensor(points, dtype=torch.float32)
    res = {}
    for b in BACKENDS:
        grid = HashGrid(SPEC, BOUND, hash_functions=(HashFunction(), WARP_FN), backend=b, init_scale=0.5, seed=3)
        wts = torch.arange(SPEC.out_dim, dtype=torch.float32)
        y = grid(x) * 2 + grid(grid.normalise(x) * 0.3, fn=1, normalised=True)
        ((y * wts).sum() + (grid(x[:50]) * wts).sum()).backward()
        rows, g = grid.take_sparse_grad()
        order = torch.argsort(rows)
        res[b] = (rows[order], g[order])
    assert torch.equal(res["torch"][0], res["numba"][0])
    assert torch.allclose(res["torch"][1], res["numba"][1], atol=1e-4)


@pytest.mark.parametrize("backend", BACKENDS)
def test_coarsest_levels_only(backend, points):
    """``levels=n``: the first n levels' features as the full encoding has them, zeros after; the
    finer levels' table rows are neither read nor given a gradient."""
    grid = make_grid(backend)
    x = torch.tensor(points, dtype=torch.float32)
    full = grid(x).detach()
    F, T = SPEC.features, SPEC.table_size
    for n in range(1, SPEC.levels + 1):
        y = grid(x, levels=n)
        assert y.shape == full.shape
        assert torch.allclose(y[:, : n * F], full[:, : n * F], atol=1e-6)
        assert (y[:, n * F:] == 0).all()
        y.sum().backward()
        rows, g = grid.take_sparse_grad()
        assert len(rows) > 0 and int(rows.max()) < n * T  # no row of a level left out
        assert torch.isfinite(g).all()
    with pytest.raises(ValueError):
        grid(x, levels=0)
    with pytest.raises(ValueError):
        grid(x, levels=SPEC.levels + 1)


def test_coarsest_levels_backends_agree(points):
    assert_backends_agree(
        lambda b: HashGrid(SPEC, BOUND, hash_functions=(HashFunction(), WARP_FN), backend=b, init_scale=0.5, seed=3),
        torch.tensor(points, dtype=torch.float32),
        encode=lambda grid, x: grid(x, levels=2) + grid(x * 0.5, fn=1, normalised=True, levels=3))
