"""The near side of depth edges (:mod:`h3edge.geometry.depth_edges`)."""

import numpy as np

from h3edge.geometry.depth_edges import near_side_of_edges


def test_only_the_foreground_rim_and_flying_pixels_are_marked():
    d = np.full((12, 12), 2.0, np.float32)
    d[:, :6] = 1.0  # a foreground half, 1 m nearer
    d[3, 9] = 1.5  # a flying pixel in the background, between the two
    d[8, 9] = 1.99  # sensor noise on the background: not an edge
    d[0, 0] = 0.0  # invalid stays unmarked
    m = near_side_of_edges(d, radius=2, jump=0.05)
    assert m[:, 4:6].all() and not m[:, :4].any()  # the foreground's last 2 columns
    assert m[:, 6:].sum() == 1 and m[3, 9]  # of the background, the flying pixel only
    assert m[3, 9] and not m[8, 9] and not m[0, 0]
    assert not near_side_of_edges(d, radius=0, jump=0.05).any()
