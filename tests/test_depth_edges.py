"""The near and far sides of depth edges (:mod:`h3edge.geometry.depth_edges`)."""

import numpy as np

from h3edge.geometry.depth_edges import far_side_of_edges, near_side_of_edges


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


def test_far_side_is_the_background_beside_the_outline():
    d = np.full((12, 24), 2.0, np.float32)
    d[:, :6] = 1.0  # a foreground, 1 m nearer
    d[:, 6:8] = 0.0  # the near side's rim, left out: the far side is found past it
    d[:, 12:] = 2.0 * 1.01 ** np.arange(1, 13, dtype=np.float32)  # a surface at a grazing angle, 1 % a pixel
    m = far_side_of_edges(d, radius=6, jump=0.05)
    assert m[:, 8:12].all()  # background within 6 px of the outline (column 5)
    assert not m[:, :8].any()  # never the foreground nor the invalid rim
    assert not m[:, 12:].any()  # the slope's depth grows 5 % within a few pixels, but it has no outline
    assert not far_side_of_edges(d, radius=0, jump=0.05).any()
    both = far_side_of_edges(d, radius=6, jump=0.05, near_too=True)
    assert both[:, :6].all() and both[:, 8:12].all() and not both[:, 6:8].any() and not both[:, 12:].any()
    assert not far_side_of_edges(np.zeros((5, 5), np.float32), radius=2, jump=0.05).any()
