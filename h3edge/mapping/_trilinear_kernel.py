"""The numba twin of :func:`h3edge.mapping.trilinear.corner_weights` (same corner order), inlined
into the fused hash-encoding and prior-march kernels."""

import numba as nb


@nb.njit(inline="always", fastmath=True)
def corner_weight(fx, fy, fz, c):
    """Trilinear weight of corner ``c`` (0..7: x = bit 0, y = bit 1, z = bit 2) at fraction (fx, fy, fz)."""
    wx = fx if (c & 1) else 1.0 - fx
    wy = fy if ((c >> 1) & 1) else 1.0 - fy
    wz = fz if ((c >> 2) & 1) else 1.0 - fz
    return wx * wy * wz
