"""Angle wrapping; wall directions from LiDAR scans and camera frames (the Manhattan heading
observation)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pyro_slam.geometry import (
    image_background,
    image_wall_direction,
    image_wall_extents,
    wall_direction,
    wrap_angle,
)
from simulators import simulate_traversal
from simulators.camera import CEILING_ALBEDO, FLOOR_ALBEDO, Camera, CameraConfig
from simulators.maze import make_maze


def test_wrap_angle_takes_tensors_arrays_and_numbers_and_any_period():
    a = [-3 * math.pi, -math.pi, -0.5, 0.0, math.pi, 7.0]
    want = [-math.pi, -math.pi, -0.5, 0.0, -math.pi, 7.0 - 2 * math.pi]
    t = wrap_angle(torch.tensor(a, dtype=torch.float64))
    assert isinstance(t, torch.Tensor) and torch.allclose(t, torch.tensor(want, dtype=t.dtype))
    n = wrap_angle(a)
    assert isinstance(n, np.ndarray) and n.dtype == np.float64
    np.testing.assert_allclose(n, want, atol=1e-12)
    assert wrap_angle(np.float32(4.0)).dtype == np.float32  # a float array keeps its dtype
    assert float(wrap_angle(4)) == pytest.approx(4 - 2 * math.pi)  # an int: float64
    quarter = wrap_angle(np.array([0.9, -0.9, math.pi / 4]), math.pi / 2)
    np.testing.assert_allclose(quarter, [0.9 - math.pi / 2, math.pi / 2 - 0.9, -math.pi / 4])


def test_wall_direction_gives_the_heading_modulo_a_quarter_turn():
    """In a maze (walls along the world axes) every simulated scan's wall direction, added to
    the true heading, is a multiple of pi / 2 (to float precision in most scans), with several
    agreeing segments; a scan with fewer than two hits, or its hits masked out, has no
    support."""
    tr = simulate_traversal("moderate-medium", steps=300, seed=3)
    x = torch.as_tensor(tr.observations, dtype=torch.float64)  # [T, B]
    angles = torch.as_tensor(tr.beam_angles, dtype=torch.float64)
    direction, support, length2, _ = wall_direction(x, angles, tr.max_range)  # [T] x 3
    assert direction.shape == support.shape == length2.shape == (300,)
    assert float(length2.min()) > 0
    assert int(support.min()) >= 3  # measured 7 or more: several walls in every scan
    phi = torch.as_tensor(tr.poses[:, 2], dtype=torch.float64)
    r = torch.remainder(phi + direction + math.pi / 4, math.pi / 2) - math.pi / 4
    # measured 9e-5 at worst: a segment straddling two parallel walls can agree within tol
    assert float(r.abs().max()) < 3e-4
    assert float(r.abs().median()) < 1e-6
    # a rotated scan (the same readings, heading turned by 0.1) gives the same body-frame value
    d0 = wall_direction(x[0], angles, tr.max_range)[0]
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


def test_wall_direction_finds_no_straight_wall_in_a_round_room():
    """Every chord of a circular wall turns against its neighbours, so 200 scans from random
    places in a round room give no support (the heading observation switches off), where a
    square room of the same size gives support to every scan; noisy scans of the square room
    report a direction error (``scatter``) of the order of the noise's, exact scans zero."""
    gen = torch.Generator().manual_seed(0)
    angles = torch.arange(20, dtype=torch.float64) * 2 * math.pi / 20  # [B]
    p = (torch.rand(200, 1, 2, generator=gen, dtype=torch.float64) - 0.5) * 0.6  # [S, 1, 2]
    theta = torch.rand(200, 1, generator=gen, dtype=torch.float64) * 2 * math.pi  # [S, 1]
    d = torch.stack([torch.cos(angles + theta), torch.sin(angles + theta)], -1)  # [S, B, 2]
    pd = (p * d).sum(-1)  # [S, B]
    circle = -pd + torch.sqrt(pd**2 - ((p * p).sum(-1) - 0.5**2))  # radius 0.5
    assert int(wall_direction(circle, angles, 10.0, tol=1e-3).support.max()) == 0
    # the square room [-0.5, 0.5]^2: the nearest wall along each beam
    with torch.no_grad():
        t = torch.where(d.abs() > 1e-12, (torch.sign(d) * 0.5 - p) / d, torch.inf)  # [S, B, 2]
    square = t.min(-1).values  # [S, B]
    exact = wall_direction(square, angles, 10.0, tol=1e-3)
    assert int(exact.support.min()) >= 3
    r = torch.remainder(theta[:, 0] + exact.direction + math.pi / 4, math.pi / 2) - math.pi / 4
    assert float(exact.scatter.median()) < 1e-12 and float(r.abs().median()) < 1e-12
    # a segment across a corner may agree within tol: measured 7e-5 at worst
    assert float(exact.scatter.max()) < 1e-3 and float(r.abs().max()) < 1e-3
    noise = 0.005 * torch.randn(square.shape, generator=gen, dtype=torch.float64)
    noisy = wall_direction(square + noise, angles, 10.0, tol=0.2)
    err = torch.remainder(theta[:, 0] + noisy.direction + math.pi / 4, math.pi / 2) - math.pi / 4
    z = err / noisy.scatter  # the direction's errors in units of its reported standard error
    assert 0.5 < float(z.std()) < 2.0
