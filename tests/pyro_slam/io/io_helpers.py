"""Helpers shared by the log-reader tests: hand-made CARMEN lines, an independent FLASER
field reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pyro_slam.data import Traversal
from pyro_slam.io import odometry_poses


def flaser(ranges, pose=(0.0, 0.0, 0.0), odom=None, t=0.0) -> str:
    """A valid FLASER line."""
    odom = pose if odom is None else odom
    nums = " ".join(str(v) for v in [*ranges, *pose, *odom])
    return f"FLASER {len(ranges)} {nums} {t} host {t}"


def odom_line(pose, t) -> str:
    return f"ODOM {pose[0]} {pose[1]} {pose[2]} 0 0 0 {t} host {t}"


def raw_flaser_fields(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Independent parse of a log's FLASER lines: ranges ``[T, n]`` and the 7 numbers after
    them ``[T, 7]`` (x y theta odom_x odom_y odom_theta ipc_timestamp)."""
    ranges, tails = [], []
    for line in path.read_text().splitlines():
        tok = line.split()
        if tok and tok[0] == "FLASER":
            n = int(tok[1])
            ranges.append([float(v) for v in tok[2 : 2 + n]])
            tails.append([float(v) for v in tok[2 + n : 9 + n]])
    return np.array(ranges), np.array(tails)


def synthetic_traversal(T=6, B=5, seed=0) -> Traversal:
    rng = np.random.default_rng(seed)
    obs = rng.uniform(0.2, 6.0, (T, B))
    mask = obs < 5.0
    controls = rng.normal(0, 0.3, (T - 1, 3))
    start = np.array([1.0, -2.0, 0.3])
    poses = odometry_poses(
        Traversal(
            obs,
            controls,
            np.zeros((0, 4)),
            np.zeros(B),
            5.0,
            metadata={"control_model": "odometry_delta", "odometry_origin": list(start)},
        )
    ) + rng.normal(0, 0.05, (T, 3))
    poses[:, 2] = (poses[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return Traversal(
        observations=np.where(mask, obs, 5.0),
        controls=controls,
        walls=np.zeros((0, 4)),
        beam_angles=np.linspace(-1.2, 1.2, B),
        max_range=5.0,
        poses=poses,
        obs_mask=mask,
        timestamps=np.arange(T) * 0.25 + 100,
        metadata={"control_model": "odometry_delta", "odometry_origin": list(start)},
    )
