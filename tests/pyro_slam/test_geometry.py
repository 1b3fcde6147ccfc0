"""LiDAR scan reprojection (pyro_slam.geometry.reproject_scan) against exact raycasting."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pyro_slam.geometry import reproject_scan
from simulators import make_maze, raycast, simulate_traversal

ANGLES = 2 * math.pi * torch.arange(20, dtype=torch.float64) / 20  # [B] the simulator's beams


def test_straight_wall_is_reprojected_exactly():
    # a sensor at 0 inside a square room [-0.3, 0.3]^2 (max range 0.53 clips the corners)
    walls = np.array([[-0.3, -0.3, 0.3, -0.3], [0.3, -0.3, 0.3, 0.3], [0.3, 0.3, -0.3, 0.3],
                      [-0.3, 0.3, -0.3, -0.3]])  # fmt: skip
    x = torch.as_tensor(raycast(walls, np.zeros((1, 2)), ANGLES.numpy()[None], 0.53))[0]
    d = torch.tensor([[0.0, 0.0], [0.02, 0.0], [-0.01, 0.015]], dtype=torch.float64)  # [A, 2]
    s, valid = reproject_scan(x, ANGLES, d, 0.53)  # [A, B]
    truth = torch.as_tensor(raycast(walls, d.numpy(), np.tile(ANGLES.numpy(), (3, 1)), 0.53))
    assert valid.shape == (3, 20) and valid[0].sum() >= 10
    torch.testing.assert_close(s[valid], truth[valid], rtol=0, atol=1e-9)
    torch.testing.assert_close(s[0], x.expand(20), rtol=0, atol=1e-12)
    # beams next to a room corner (the polyline turns there) and max-range readings are invalid
    corner = int(torch.argmin((ANGLES - math.pi / 4).abs()))
    assert not valid[:, corner].any()
    assert not valid[:, x >= 0.53].any()


def test_reprojection_matches_raycasting_in_a_maze():
    maze = make_maze("moderate-medium", seed=1001)
    tr = simulate_traversal(maze, steps=300, seed=1)
    P, X = tr.poses[::3], tr.observations[::3]  # [N, 3], [N, B]
    rng = np.random.default_rng(0)
    r = 0.02 * np.sqrt(rng.uniform(0, 1, (len(P), 4)))
    a = rng.uniform(0, 2 * np.pi, (len(P), 4))
    d = np.stack([r * np.cos(a), r * np.sin(a)], -1)  # [N, A, 2]
    world = P[:, 2:3] + tr.beam_angles[None]  # [N, B]
    s, valid = reproject_scan(torch.tensor(X), torch.tensor(world), torch.tensor(d), tr.max_range)
    origins = (P[:, None, :2] + d).reshape(-1, 2)
    truth = raycast(maze.walls, origins, np.repeat(world, 4, 0), tr.max_range)
    err = np.abs(s.numpy() - truth.reshape(s.shape))[valid.numpy()]
    unshifted = np.abs(X[:, None] - truth.reshape(s.shape))[valid.numpy()]
    # measured: 67% valid, median error 0, 90th percentile 0.0011 (0.0203 without reprojection)
    assert valid.float().mean() > 0.5
    assert np.median(err) < 1e-6 and np.quantile(err, 0.9) < 0.003
    assert np.quantile(unshifted, 0.9) > 5 * np.quantile(err, 0.9)


def test_masked_and_non_wrapping_beams_are_invalid():
    x = torch.full((20,), 0.2, dtype=torch.float64)  # a circle of radius 0.2: every beam a hit
    mask = torch.ones(20, dtype=torch.bool)
    mask[5] = False
    d = torch.zeros(1, 2, dtype=torch.float64)
    _, valid = reproject_scan(x, ANGLES, d, 0.53, mask=mask)
    assert not valid[0, 4:7].any() and valid[0, :4].all() and valid[0, 7:].all()
    _, valid = reproject_scan(x, ANGLES, d, 0.53, wrap=False)
    assert not valid[0, 0] and not valid[0, -1] and valid[0, 1:-1].all()


@pytest.mark.parametrize("shape", [(), (3,), (2, 5)])
def test_batch_shapes(shape):
    x = 0.1 + 0.3 * torch.rand(*shape, 20, dtype=torch.float64)
    world = ANGLES + torch.rand(*shape, 1, dtype=torch.float64)
    s, valid = reproject_scan(x, world, torch.zeros(*shape, 6, 2, dtype=torch.float64), 0.53)
    assert s.shape == valid.shape == (*shape, 6, 20)


def test_wall_direction_gives_the_heading_modulo_a_quarter_turn():
    """In a maze (walls along the world axes) every simulated scan's wall direction, added to
    the true heading, is a multiple of pi / 2 to float precision, with several agreeing
    segments; a scan with fewer than two hits, or its hits masked out, has no support."""
    from pyro_slam.geometry import wall_direction

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
    from pyro_slam.geometry import image_background, image_wall_direction, image_wall_extents
    from simulators.camera import CEILING_ALBEDO, FLOOR_ALBEDO, Camera, CameraConfig
    from simulators.maze import make_maze

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
