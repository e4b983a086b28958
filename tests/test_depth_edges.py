"""The near and far sides of depth edges (:mod:`h3edge.geometry.depth_edges`)."""

import numpy as np

from h3edge.geometry.depth_edges import depth_discontinuities, far_side_of_edges, near_side_of_edges


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


def _tilted_plane(w: int, h: int, focal: float, tilt_deg: float) -> np.ndarray:
    """z-depth of a plane 1 m from the camera whose normal is tilted ``tilt_deg`` from the optical
    axis (a floor or ceiling seen at incidences up to ~90 degrees); 0 where the rays miss it."""
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([(u - w / 2) / focal, (v - h / 2) / focal, np.ones_like(u)], -1)
    a = np.radians(tilt_deg)
    z = 1.0 / (rays @ np.array([0.0, np.sin(a), np.cos(a)]))
    return np.where((z > 0) & (z < 10), z, 0).astype(np.float32)


def test_a_surface_at_a_grazing_angle_is_no_edge_at_any_resolution():
    """At 160x120 with a 95 px focal length a 5 % jump over 2 px is any surface beyond ~67 degrees of
    incidence: a third of a tilted plane went missing from the mapper's input. The jump raised to
    what an 80-degree surface gives over the window keeps it, at low and at high resolution."""
    from h3edge.geometry.depth_edges import discontinuity_jump

    for w, h, focal in ((160, 120, 95.0), (640, 480, 525.0)):
        z = _tilted_plane(w, h, focal, 60.0)
        jump = discontinuity_jump(0.05, 2, focal, 80.0)
        assert near_side_of_edges(z, 2, jump).sum() < 0.08 * (z > 0).sum(), (w, jump)  # the rows beyond 80 degrees
        step = z.copy()
        step[: h // 2] *= 0.7  # a real edge, 30 % nearer: still found
        assert near_side_of_edges(step, 2, jump)[h // 2 - 2:h // 2].all()
    low = _tilted_plane(160, 120, 95.0, 60.0)
    assert near_side_of_edges(low, 2, 0.05).sum() > 0.25 * (low > 0).sum()  # before: the 5 % everywhere
    assert discontinuity_jump(0.05, 2, 525.0, 80.0) == 0.05  # Kinect frames: the 5 % as measured


def test_discontinuities_are_both_sides_of_a_relative_jump_and_the_rim_of_holes():
    d = np.full((10, 12), 2.0, np.float32)
    d[:, :4] = 1.0  # a foreground, 1 m nearer: columns 3 and 4 are the edge's two sides
    d[:, 8:] *= np.float32(1.02)  # a 2 % step (sensor quantisation): no edge at 5 %
    d[7, 10] = 0.0  # a hole: it and its 8 neighbours are marked
    m = depth_discontinuities(d, 0.05)
    assert m[:, 3:5].all() and not m[:, :3].any()
    assert not m[:6, 5:].any()
    assert m[6:9, 9:12].all() and m[:, 5:].sum() == 9
    assert depth_discontinuities(np.zeros((3, 3), np.float32), 0.05).all()
