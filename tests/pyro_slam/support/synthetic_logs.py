"""A synthetic metric laser log (a 10 x 6 m room, a 180 deg scanner) for the tests of the real-log
path: the ``real`` preset, the readers' round trips, SLAM on metric data."""

from __future__ import annotations

import math

import numpy as np

from pyro_slam.data import Traversal
from pyro_slam.io.common import relative

ROOM = (0.0, 0.0, 10.0, 6.0)  # x0 y0 x1 y1, metres


def box_ranges(pose, angles, room=ROOM):
    """Ranges from ``pose`` to the walls of an axis-aligned room along ``heading + angles``."""
    x0, y0, x1, y1 = room
    a = pose[2] + angles
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (x1 - pose[0]) / c, np.where(c < 0, (x0 - pose[0]) / c, np.inf))
        ty = np.where(s > 0, (y1 - pose[1]) / s, np.where(s < 0, (y0 - pose[1]) / s, np.inf))
    return np.minimum(tx, ty)


def room_log(T=16, B=361, no_return_every=17):
    """A metric log in a 10 x 6 m room: 180 deg scanner, some no-return beams (81.91 m)."""
    angles = np.linspace(-math.pi / 2, math.pi / 2, B)
    t = np.arange(T)
    poses = np.column_stack([2.0 + 5.0 * t / (T - 1), 3.0 + 0.05 * np.sin(t), 0.3 * t / T])
    obs = np.stack([box_ranges(p, angles) for p in poses])
    obs[:, ::no_return_every] = 81.91
    mask = obs < 81.91
    return Traversal(
        observations=obs,
        controls=relative(poses[:-1], poses[1:]),
        walls=np.zeros((0, 4)),
        beam_angles=angles,
        max_range=81.91,
        obs_mask=mask,
        timestamps=0.2 * t,
        metadata={"control_model": "odometry_delta", "odometry_origin": [0.0, 0.0, 0.0]},
    ), poses
