"""Cross-view free space (:mod:`h3edge.mapping.visibility`): pooled depth and the seen-through test."""

import numpy as np
import torch

from h3edge.geometry.camera import Intrinsics, look_at
from h3edge.mapping.visibility import PooledDepth, pool_depth, seen_through

INTR = Intrinsics(64, 48, 40.0, 40.0, 32.0, 24.0)


def test_pooled_blocks_keep_their_nearest_depth_and_know_nothing_with_a_hole():
    d = np.full((8, 8), 3.0, np.float32)
    d[0, 1] = 1.0  # a near pixel in the first block
    d[5, 6] = 0.0  # a hole in the last block
    p = pool_depth(d, 4)
    assert p.shape == (2, 2) and p.dtype == np.float32
    assert p[0, 0] == 1.0 and p[0, 1] == 3.0 and p[1, 1] == 0.0
    assert pool_depth(np.ones((9, 10), np.float32), 4).shape == (2, 2)  # trailing pixels dropped
    d[1, 5], d[6, 2] = np.nan, np.inf  # not finite = invalid
    p = pool_depth(d, 4)
    assert p[0, 1] == 0.0 and p[1, 0] == 0.0 and p[0, 0] == 1.0


def test_a_point_is_seen_through_only_well_in_front_of_what_a_view_measured():
    pose = look_at(np.zeros(3), np.array([0.0, 1.0, 0.0]))  # looking along +y at a wall 2 m away
    view = PooledDepth.of(np.full((INTR.height, INTR.width), 2.0, np.float32), pose, INTR, stride=4)
    pts = torch.tensor([[0.0, 1.5, 0.0],  # well in front of the wall: free
                        [0.0, 1.98, 0.0],  # within the margin of the wall: not
                        [0.0, 2.5, 0.0],  # behind the wall: not
                        [0.0, -1.0, 0.0],  # behind the camera: not
                        [5.0, 1.5, 0.0]], dtype=torch.float64)  # outside the image: not
    assert seen_through(pts, [view], margin=0.03).tolist() == [True, False, False, False, False]
    # a side view that sees 4 m deep past all three points on the axis: behind the first view's
    # wall is free for it (a thin wall's far side), and that is enough
    side = look_at(np.array([2.0, 1.5, 0.0]), np.array([0.0, 1.5, 0.0]))
    far = PooledDepth.of(np.full((INTR.height, INTR.width), 4.0, np.float32), side, INTR, stride=4)
    assert seen_through(pts, [far], margin=0.03).tolist() == [True, True, True, False, False]
    assert seen_through(pts, [view, far], margin=0.03).tolist() == [True, True, True, False, False]
    near = PooledDepth.of(np.full((INTR.height, INTR.width), 2.02, np.float32), side, INTR, stride=4)
    assert seen_through(pts, [near], margin=0.03).tolist() == [False] * 5  # within its margin
    assert seen_through(pts[:0], [view], 0.03).shape == (0,)
