"""Smooth camera trajectory through the simulated room.

Hand-placed key views (eye, look-at target) visit every wall, the floor, the ceiling and the
furniture, with close-ups (about 1 m) and far views across the room; a closed Catmull-Rom
spline through them, resampled at constant arc length, gives the camera-to-world poses. The
camera keeps the horizon level, as a hand-held or robot camera does, but like one it rolls at a
bounded rate: where the gaze passes near the zenith or nadir a level camera would spin about its
axis (67 degrees between two frames of the studio loop), so there the camera carries its roll
along and levels again afterwards.
"""

from __future__ import annotations

import numpy as np

from h3edge.geometry.camera import look_at

# (eye, target) in room coordinates (x east, y north, z up); see h3edge.sim.scene for the layout.
KEY_VIEWS: list[tuple[tuple[float, float, float], tuple[float, float, float]]] = [  # the "room" layout
    ((1.0, 1.0, 1.5), (5.8, 1.8, 1.0)),  # far view to the bookshelf
    ((3.0, 1.3, 1.4), (5.8, 1.8, 1.1)),
    ((4.5, 1.6, 1.3), (5.95, 1.8, 1.1)),  # close-up of the books
    ((4.8, 2.7, 1.5), (6.0, 3.4, 1.5)),  # astronaut poster
    ((4.6, 3.7, 1.4), (4.7, 5.0, 1.2)),  # tiles close-up
    ((3.0, 3.6, 1.6), (1.4, 5.0, 1.4)),  # brick wall and coffee poster
    ((2.1, 3.7, 1.3), (4.8, 4.3, 0.25)),  # bin and floor
    ((1.6, 3.0, 1.5), (0.0, 2.6, 1.6)),  # west posters
    ((1.1, 2.0, 1.3), (0.0, 1.0, 1.5)),  # hubble poster close-up
    ((1.3, 1.6, 1.7), (0.3, 4.2, 0.8)),  # cabinet corner
    ((1.6, 1.4, 1.6), (2.5, 0.0, 1.6)),  # blinds
    ((2.5, 1.1, 1.3), (2.6, 0.0, 1.5)),  # blinds close-up
    ((4.0, 1.3, 1.7), (0.5, 4.5, 0.9)),  # far view across the room
    ((3.1, 2.0, 2.0), (3.1, 2.8, 0.0)),  # table and rug from above
    ((2.2, 2.5, 1.6), (3.4, 2.9, 2.8)),  # ceiling
    ((1.4, 1.4, 1.5), (4.0, 1.0, 0.0)),  # floor and the floor box
]


# the "studio" layout (7 x 4.5 x 3 m): a different loop, lower and higher eyes, longer sight lines
STUDIO_KEY_VIEWS: list[tuple[tuple[float, float, float], tuple[float, float, float]]] = [
    ((1.0, 1.0, 1.6), (6.9, 2.5, 1.4)),  # far view to the brick wall
    ((3.0, 1.6, 1.2), (6.9, 1.2, 1.6)),  # rocket poster and crates
    ((5.2, 1.8, 1.1), (6.3, 1.9, 0.4)),  # crates close-up
    ((5.6, 2.4, 1.7), (6.9, 3.4, 1.4)),  # brick close-up, cabinet
    ((5.0, 3.5, 1.5), (5.2, 4.5, 1.4)),  # photographic tiles close-up
    ((4.0, 3.3, 1.9), (2.0, 4.5, 1.5)),  # blinds from the side
    ((3.2, 3.0, 1.3), (3.0, 4.0, 0.2)),  # planter from above
    ((2.4, 2.0, 1.0), (1.2, 3.0, 0.6)),  # desk, low
    ((1.6, 1.5, 1.5), (0.0, 1.1, 1.5)),  # notice board close-up
    ((1.2, 0.9, 2.2), (0.0, 3.5, 1.0)),  # plank cladding, high
    ((2.0, 1.2, 1.4), (4.4, 0.4, 0.4)),  # sofa
    ((2.6, 2.6, 1.7), (5.6, 0.0, 2.0)),  # south wall above the sofa
    ((2.4, 3.2, 1.5), (1.0, 0.0, 2.4)),  # south-west corner
    ((3.0, 2.2, 1.5), (1.5, 1.0, 3.0)),  # ceiling, west half
    ((3.0, 1.8, 1.0), (4.6, 2.9, 1.2)),  # column close-up
    ((3.6, 1.9, 2.3), (5.5, 2.0, 3.0)),  # ceiling, east half
    ((2.8, 2.3, 1.8), (4.2, 1.8, 0.0)),  # carpet and floor tiles
    ((1.4, 3.9, 1.6), (6.5, 1.0, 1.0)),  # far view across the studio
    ((0.9, 2.0, 1.4), (6.9, 3.0, 1.2)),
]
# the "loft" layout (5 x 4.2 x 2.7 m): a hand-held walk round the room from its middle, at a
# hand-held camera's pace (see h3edge.sim.make's preset), each wall and the floor at 1-2.5 m
LOFT_KEY_VIEWS: list[tuple[tuple[float, float, float], tuple[float, float, float]]] = [
    ((2.0, 2.6, 1.5), (2.5, 0.0, 1.3)),  # brick wall, far
    ((2.8, 2.2, 1.4), (3.9, 0.9, 1.2)),  # coin column
    ((3.4, 1.6, 1.5), (5.0, 1.1, 1.5)),  # motorcycle photograph
    ((3.6, 2.2, 1.4), (5.0, 2.6, 1.5)),  # astronaut, close
    ((3.6, 2.8, 1.3), (4.6, 3.7, 0.4)),  # stone crate
    ((3.2, 3.0, 1.5), (3.3, 4.2, 1.6)),  # hubble photograph
    ((2.4, 3.0, 1.2), (2.4, 4.2, 0.6)),  # micrograph mosaic, low
    ((1.8, 3.0, 1.5), (1.0, 4.2, 1.6)),  # camera photograph
    ((1.3, 2.8, 1.5), (0.0, 2.8, 1.4)),  # newspaper on the moss wall
    ((1.3, 2.2, 1.6), (0.0, 1.0, 1.0)),  # moss wall and the brick crate
    ((1.6, 1.6, 1.7), (2.5, 2.1, 0.5)),  # table and rug from above
    ((1.8, 2.0, 1.6), (2.6, 1.2, 0.0)),  # gravel floor
]
KEY_VIEW_SETS = {"room": KEY_VIEWS, "studio": STUDIO_KEY_VIEWS, "loft": LOFT_KEY_VIEWS}
# degrees a frame the camera may roll about its optical axis on its way to level (the scene's
# median turn is about 3 degrees a frame; a level camera spun 67 where the gaze nears the zenith)
MAX_ROLL_STEP_DEG = 8.0


def _catmull_rom(points: np.ndarray, samples_per_segment: int) -> np.ndarray:
    """Closed uniform Catmull-Rom spline through ``points`` (N, D), densely sampled."""
    n = len(points)
    t = np.linspace(0, 1, samples_per_segment, endpoint=False)[:, None]
    out = []
    for i in range(n):
        p0, p1, p2, p3 = points[(i - 1) % n], points[i], points[(i + 1) % n], points[(i + 2) % n]
        out.append(0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t ** 2
                          + (-p0 + 3 * p1 - 3 * p2 + p3) * t ** 3))
    return np.concatenate(out)


def camera_path(n_frames: int, layout: str = "room") -> np.ndarray:
    """``n_frames`` camera-to-world poses (N, 4, 4) evenly spaced along the closed key-view loop of
    ``layout``."""
    if n_frames < 2:
        raise ValueError("a trajectory needs at least 2 frames")
    views = KEY_VIEW_SETS[layout]
    eyes = np.array([k[0] for k in views], float)
    targets = np.array([k[1] for k in views], float)
    dense = _catmull_rom(np.concatenate([eyes, targets], axis=1), 400)
    e, tg = dense[:, :3], dense[:, 3:]
    # arc length over eye motion plus (scaled) gaze motion, so pure turns also advance the camera
    gaze = tg - e
    gaze /= np.linalg.norm(gaze, axis=1, keepdims=True)
    step = np.linalg.norm(np.diff(e, axis=0), axis=1) + 0.8 * np.linalg.norm(np.diff(gaze, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(step)])
    # open the loop: the last pose stops one step before the first, so frames never repeat
    want = np.linspace(0, s[-1], n_frames, endpoint=False)
    idx = np.clip(np.searchsorted(s, want), 0, len(s) - 1)
    return steady_poses(e[idx], tg[idx])


def steady_poses(eyes: np.ndarray, targets: np.ndarray, max_roll_step_deg: float = MAX_ROLL_STEP_DEG) -> np.ndarray:
    """Camera-to-world poses (N, 4, 4) at ``eyes`` looking at ``targets`` (N, 3 each): level
    (:func:`look_at`) wherever that is at most ``max_roll_step_deg`` of roll from the previous
    frame's x axis carried to the new gaze; elsewhere that carried axis turns towards level by
    ``max_roll_step_deg``. The gaze is always the target's."""
    limit = np.radians(max_roll_step_deg)
    poses = []
    for eye, target in zip(eyes, targets):
        T = look_at(eye, target)
        if poses:
            z, level = T[:3, 2], T[:3, 0]
            x = poses[-1][:3, 0] - (poses[-1][:3, 0] @ z) * z  # the previous x, carried to the new gaze
            norm = np.linalg.norm(x)
            if norm < 1e-9:  # the gaze turned onto the previous x axis: start level
                poses.append(T)
                continue
            x /= norm
            phi = np.arctan2(np.cross(x, level) @ z, x @ level)  # roll from there to level
            if abs(phi) > limit:
                step = np.sign(phi) * limit
                x = np.cos(step) * x + np.sin(step) * np.cross(z, x)
                T[:3, 0], T[:3, 1] = x, np.cross(z, x)
        poses.append(T)
    return np.stack(poses)


def midpoint_poses(poses: np.ndarray, every: int) -> np.ndarray:
    """Held-out views: SLERP/linear midpoints between training poses i and i+1, every ``every``-th i."""
    from h3edge.geometry.poses import interpolate_pose

    out = [interpolate_pose(poses[i], poses[i + 1], 0.5) for i in range(0, len(poses) - 1, every)]
    return np.stack(out)
