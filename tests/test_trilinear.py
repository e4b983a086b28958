"""The trilinear corner weights: one routine per backend, the same numbers."""

import numpy as np
import pytest
import torch

from h3edge.mapping.trilinear import CORNERS, corner_weights


def test_corner_weights_interpolate_exactly():
    rng = np.random.default_rng(0)
    f = torch.from_numpy(rng.random((100, 3)))
    w = corner_weights(f)
    assert torch.allclose(w.sum(-1), torch.ones(100, dtype=w.dtype))
    # a linear function of position is reproduced exactly from its corner values
    a = torch.tensor([0.3, -1.2, 2.0], dtype=w.dtype)
    corner_values = torch.from_numpy(CORNERS).to(w.dtype) @ a
    assert torch.allclose((w * corner_values).sum(-1), f @ a)
    at_corner = corner_weights(torch.from_numpy(CORNERS[5:6]).double())
    assert at_corner[0, 5] == 1 and at_corner.sum() == 1


def test_numba_twin_matches_torch():
    pytest.importorskip("numba")
    from h3edge.mapping._trilinear_kernel import corner_weight

    rng = np.random.default_rng(1)
    f = rng.random((50, 3))
    ref = corner_weights(torch.from_numpy(f)).numpy()
    got = np.array([[corner_weight(*p, c) for c in range(8)] for p in f])
    assert np.allclose(got, ref, atol=1e-12)
