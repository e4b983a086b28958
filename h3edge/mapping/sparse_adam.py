"""Row-sparse ("lazy") Adam: the one Adam update of the hash-grid tables and the SDF priors.

Only the rows that received a gradient are updated; every other row keeps its parameters and its
moment estimates untouched (no decay of m and v where there is no gradient, as PyTorch's
SparseAdam). With step count t shared by the whole tensor, for each updated row r:

    m_r <- b1 m_r + (1 - b1) g_r,    v_r <- b2 v_r + (1 - b2) g_r^2
    p_r <- p_r - lr * (m_r / (1 - b1^t)) / (sqrt(v_r / (1 - b2^t)) + eps)

:func:`lazy_adam_rows` is the PyTorch version (CPU and CUDA); the numba CPU kernel of the hash
grid (``mapping/_hash_kernels.py`` ``adam``) computes the same numbers in one fused pass.
"""

from __future__ import annotations

import torch


@torch.no_grad()
def lazy_adam_rows(param: torch.Tensor, m: torch.Tensor, v: torch.Tensor, rows: torch.Tensor, grads: torch.Tensor,
                   step: int, lr: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15) -> None:
    """Update ``param[rows]`` and its moments ``m[rows]``, ``v[rows]`` in place with ``grads``
    (one row of gradient per entry of ``rows``, rows unique) at Adam step ``step`` (>= 1).

    Example::

        rows = torch.tensor([3, 7]); g = torch.ones(2, 2)
        lazy_adam_rows(table, m, v, rows, g, step=1, lr=1e-2)   # rows 3 and 7 move by -lr
    """
    b1, b2 = betas
    mr = m[rows].mul_(b1).add_(grads, alpha=1 - b1)
    vr = v[rows].mul_(b2).addcmul_(grads, grads, value=1 - b2)
    m[rows], v[rows] = mr, vr
    param[rows] -= lr * (mr / (1 - b1 ** step)) / ((vr / (1 - b2 ** step)).sqrt() + eps)
