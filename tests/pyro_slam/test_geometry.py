"""Wall directions from LiDAR scans and camera frames (the Manhattan heading observation)."""

from __future__ import annotations

import math

import pytest
import torch

from pyro_slam.geometry import (
    image_background,
    image_wall_direction,
    image_wall_extents,
    wall_direction,
)
from simulators import simulate_traversal
from simulators.camera import CEILING_ALBEDO, FLOOR_ALBEDO, Camera, CameraConfig
from simulators.maze import make_maze


def test_wall_direction_gives_the_heading_modulo_a_quarter_turn():
    """In a maze (walls along the world axes) every simulated scan's wall direction, added to
    the true heading, is a multiple of pi / 2 to float precision, with several agreeing
    segments; a scan with fewer than two hits, or its hits masked out, has no support."""
    tr = simulate_traversal("moderate-medium", steps=300, seed=3)
    x = torch.as_tensor(tr.observations, dtype=torch.float64)  # [T, B]
    angles = torch.as_tensor(tr.beam_angles, dtype=torch.float64)
    direction, support = wall_direction(x, angles, tr.max_range)  # [T], [T]
    assert direction.shape == support.shape == (300,)
    assert int(support.min()) >= 3  # measured 7 or more: several walls in every scan
    phi = torch.as_tensor(tr.poses[:, 2], dtype=torch.float64)
    r = torch.remainder(phi + direction + math.pi / 4, math.pi / 2) - math.pi / 4
    assert float(r.abs().max()) < 1e-6
    # a rotated scan (the same readings, heading turned by 0.1) gives the same body-frame value
    d0, _ = wall_direction(x[0], angles, tr.max_range)
    assert float(d0) == pytest.approx(float(direction[0]))
    lone = torch.full((20,), 0.53, dtype=torch.float64)
    lone[3] = 0.2
    assert int(wall_direction(lone, angles, 0.53)[1]) == 0
    mask = torch.zeros(20, dtype=torch.bool)
    assert int(wall_direction(x[0], angles, tr.max_range, mask)[1]) == 0


def test_image_wall_direction_reads_the_walls_edges():
    """First-person frames: the per-row background is the camera's floor / ceiling, the wall
    edges' distances from the horizon are the camera's ``f a / d`` and ``f b / d`` where
    measured, and the walls' direction gives the heading modulo pi / 2 in most frames."""
    maze = make_maze("moderate-medium", 3)
    tr = simulate_traversal(maze, steps=300, seed=3, images=True)
    img = torch.as_tensor(tr.images, dtype=torch.float64)  # [T, 24, 32]
    cam, cfg = Camera(maze.walls, maze.corridor_width), CameraConfig()
    bg = image_background(img)  # [24]
    y = torch.arange(24, dtype=torch.float64) + 0.5 - 12
    w, f = maze.corridor_width, cfg.focal
    plane = 0.5 * w * f / y.abs()  # floor / ceiling depth per row (eye at half the wall)
    truth = torch.where(y < 0, CEILING_ALBEDO, FLOOR_ALBEDO) / (1 + plane / (cfg.fog * w))
    far = (y.abs() > 3).nonzero()[:, 0]  # rows a wall rarely covers
    assert torch.allclose(bg[far], truth[far], atol=1e-4)

    ext = image_wall_extents(img, bg)  # [T, 2, 32]
    d = torch.as_tensor(cam.column_depth(tr.poses))  # [T, 32] perpendicular depth
    expected = (f * 0.5 * w / d).unsqueeze(-2).expand_as(ext)  # a = b = w / 2 (eye at half)
    ok = ~ext.isnan()
    assert float(ok.double().mean()) > 0.3  # measured 0.38: 27 % of the walls fill the frame
    assert float((ext[ok] - expected[ok]).abs().max()) < 1e-3

    angles = torch.as_tensor(cfg.column_offsets)
    direction, support = image_wall_direction(img, angles, bg)  # [T], [T]
    found = support >= 2
    assert float(found.double().mean()) > 0.85  # measured 0.93 (and on maze 100)
    phi = torch.as_tensor(tr.poses[:, 2], dtype=torch.float64)
    r = torch.remainder(phi + direction + math.pi / 4, math.pi / 2) - math.pi / 4
    assert float(r[found].abs().max()) < 1e-3
    # a blank frame has no walls: no support, and a bad background shape is named
    assert int(image_wall_direction(torch.zeros(24, 32), angles, bg)[1]) == 0
    with pytest.raises(ValueError, match="background"):
        image_wall_extents(img, bg[:5])
