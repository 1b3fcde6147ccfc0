"""A tiny numpy stand-in for the simulator, for PF-net tests (no pymunk, no distractors).

``make_maze(seed, cells)`` builds a perfect maze of ``cells x cells`` cells in ``[0, 1]^2``;
``StandInWorld`` implements the members :func:`pyro_slam.pfnet.data.generate` needs: it moves
without physics (a move that would cross a wall stops short) and renders a LiDAR scan and a
column-wise depth image by ray casting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def raycast(walls, origins, angles, max_range):
    """Ranges ``[N, B]`` from ``origins [N, 2]`` along ``angles [N, B]`` to segments ``[W, 4]``."""
    o = origins[:, None, None, :]  # [N, 1, 1, 2]
    d = np.stack([np.cos(angles), np.sin(angles)], -1)[:, :, None, :]  # [N, B, 1, 2]
    a, b = walls[None, None, :, :2], walls[None, None, :, 2:]  # [1, 1, W, 2]
    e = b - a
    den = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]  # [N, B, W]
    ao = a - o
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ao[..., 0] * e[..., 1] - ao[..., 1] * e[..., 0]) / den
        s = (ao[..., 0] * d[..., 1] - ao[..., 1] * d[..., 0]) / den
    hit = (np.abs(den) > 1e-12) & (t > 0) & (s >= 0) & (s <= 1)
    t = np.where(hit, t, np.inf).min(-1)
    return np.minimum(t, max_range)


@dataclass
class Maze:
    walls: np.ndarray
    side: float = 1.0
    cells: int = 6

    def random_free_pose(self, rng):
        c = self.side / self.cells
        i, j = rng.integers(self.cells, size=2)
        return np.array(
            [
                (i + 0.5) * c + rng.uniform(-0.2, 0.2) * c,
                (j + 0.5) * c + rng.uniform(-0.2, 0.2) * c,
                rng.uniform(-math.pi, math.pi),
            ]
        )


def make_maze(seed: int = 0, cells: int = 6, side: float = 1.0) -> Maze:
    rng = np.random.default_rng(seed)
    c = side / cells
    # walls between cells: h[i, j] wall on top of cell (i, j); v[i, j] wall right of cell (i, j)
    h = np.ones((cells, cells), bool)
    v = np.ones((cells, cells), bool)
    seen = np.zeros((cells, cells), bool)
    stack = [(0, 0)]
    seen[0, 0] = True
    while stack:
        i, j = stack[-1]
        nb = [
            (i + di, j + dj)
            for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1))
            if 0 <= i + di < cells and 0 <= j + dj < cells and not seen[i + di, j + dj]
        ]
        if not nb:
            stack.pop()
            continue
        ni, nj = nb[rng.integers(len(nb))]
        if ni == i + 1:
            v[i, j] = False
        elif ni == i - 1:
            v[ni, nj] = False
        elif nj == j + 1:
            h[i, j] = False
        else:
            h[ni, nj] = False
        seen[ni, nj] = True
        stack.append((ni, nj))
    walls = [[0, 0, side, 0], [0, 0, 0, side]]
    for i in range(cells):
        for j in range(cells):
            if h[i, j]:
                walls.append([i * c, (j + 1) * c, (i + 1) * c, (j + 1) * c])
            if v[i, j]:
                walls.append([(i + 1) * c, j * c, (i + 1) * c, (j + 1) * c])
    return Maze(np.asarray(walls, dtype=float), side, cells)


class StandInWorld:
    """Kinematic world: rotate, then move forward; stops 0.01 short of a wall."""

    def __init__(
        self, maze: Maze, n_beams=20, max_range=0.53, image_shape=(24, 32), fov=math.pi / 2
    ):
        self.maze, self.max_range = maze, max_range
        self.beam_angles = np.linspace(-math.pi, math.pi, n_beams, endpoint=False)
        self.image_shape, self.fov = image_shape, fov
        self.column_angles = fov / 2 - (np.arange(image_shape[1]) + 0.5) * fov / image_shape[1]
        self.pose = np.zeros(3)

    def random_start(self, rng):
        return self.maze.random_free_pose(rng)

    def reset(self, pose):
        self.pose = np.array(pose, dtype=float)

    def step(self, u):
        h = self.pose[2] + u[0]
        free = raycast(self.maze.walls, self.pose[None, :2], np.array([[h]]), 10.0)[0, 0]
        f = min(u[1], max(free - 0.01, 0.0))
        blocked = f < u[1]
        self.pose = np.array(
            [
                self.pose[0] + f * np.cos(h),
                self.pose[1] + f * np.sin(h),
                (h + np.pi) % (2 * np.pi) - np.pi,
            ]
        )
        return not blocked

    def lidar(self):
        a = self.pose[2] + self.beam_angles
        return raycast(self.maze.walls, self.pose[None, :2], a[None], self.max_range)[0]

    def depth_images(self, poses):
        out = []
        for p in poses:
            self.pose = np.asarray(p, dtype=float)
            out.append(self.depth())
        return np.stack(out)

    def depth(self):
        H, W = self.image_shape
        cols = self.fov / 2 - (np.arange(W) + 0.5) / W * self.fov  # left to right
        d = raycast(self.maze.walls, self.pose[None, :2], (self.pose[2] + cols)[None], 1.0)[0]
        perp = d * np.cos(cols)  # [W]
        f = (W / 2) / math.tan(self.fov / 2)
        rows = (np.arange(H) + 0.5 - H / 2) / f  # tan of the angle below the horizon
        cam_h = 0.05
        floor = np.where(rows > 0, cam_h / np.maximum(rows, 1e-6), np.inf)[:, None]  # [H, 1]
        ceil = np.where(rows < 0, cam_h / np.maximum(-rows, 1e-6), np.inf)[:, None]
        img = np.minimum(np.minimum(perp[None, :], floor), ceil)
        return np.clip(img, 0.0, 1.0).astype(np.float32)
