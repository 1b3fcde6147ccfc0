import importlib

import numpy as np
import pytest

from simulators import make_maze, raycast

# the package re-exports the function under the module's name, so fetch the module explicitly
rc = importlib.import_module("simulators.raycast")


def _reference(walls, origin, angle, max_range):
    """Per ray and wall: solve o + t d = a + s (b - a) as a 2x2 linear system."""
    d = np.array([np.cos(angle), np.sin(angle)])
    best = max_range
    for x1, y1, x2, y2 in walls:
        e = np.array([x2 - x1, y2 - y1])
        m = np.column_stack([d, -e])
        if abs(np.linalg.det(m)) < 1e-14:
            continue
        t, s = np.linalg.solve(m, np.array([x1, y1]) - origin)
        if t >= 0 and 0 <= s <= 1:
            best = min(best, t)
    return best


def test_unit_square_from_centre():
    square = np.array([[0, 0, 1, 0], [1, 0, 1, 1], [1, 1, 0, 1], [0, 1, 0, 0]], dtype=float)
    angles = np.array([[0, np.pi / 4, np.pi / 2, np.pi, -np.pi / 2]])
    r = raycast(square, [[0.5, 0.5]], angles, 2.0)
    np.testing.assert_allclose(r, [[0.5, 0.5 * np.sqrt(2), 0.5, 0.5, 0.5]], atol=1e-15)
    assert raycast(square, [[0.5, 0.5]], angles, 0.4).tolist() == [[0.4] * 5]  # out of range


def test_matches_linear_solve_reference():
    maze = make_maze("complex-small", seed=2)
    rng = np.random.default_rng(0)
    origins = rng.uniform(0.01, maze.side - 0.01, (60, 2))
    angles = rng.uniform(-np.pi, np.pi, (60, 7))
    r, idx = raycast(maze.walls, origins, angles, 0.53, return_index=True)
    ref = [[_reference(maze.walls, o, a, 0.53) for a in row] for o, row in zip(origins, angles)]
    np.testing.assert_allclose(r, ref, atol=1e-12)
    assert np.all((idx == -1) == (r == 0.53))


def test_chunking_is_invisible(monkeypatch):
    maze = make_maze("moderate-medium", seed=0)
    rng = np.random.default_rng(1)
    origins = rng.uniform(0, 1, (50, 2))
    angles = rng.uniform(-np.pi, np.pi, (50, 20))
    full = raycast(maze.walls, origins, angles, 0.53)
    monkeypatch.setattr(rc, "_CHUNK_ELEMENTS", 100)  # forces one pose per chunk
    np.testing.assert_array_equal(raycast(maze.walls, origins, angles, 0.53), full)


def test_shared_angles_and_no_walls():
    r = raycast(np.zeros((0, 4)), [[0, 0], [1, 1]], np.array([0.0, 1.0]), 0.7)
    assert r.shape == (2, 2) and np.all(r == pytest.approx(0.7))


def test_a_ray_along_a_wall_hits_its_end():
    # an agent standing on a wall's line (grid points at 0.5 in a maze of 1/6 cells) used to
    # see straight through the wall: parallel segments never counted as hits
    wall = np.array([[0.5, 0.5, 5 / 6, 0.5]])
    r = raycast(
        wall, [[0.9, 0.5], [0.7, 0.5], [0.2, 0.5]], np.array([[np.pi], [np.pi], [0.0]]), 0.53
    )
    np.testing.assert_allclose(r[:, 0], [0.9 - 5 / 6, 0.0, 0.3], atol=1e-12)
    # just off the line, or pointing away, it passes by
    off = raycast(wall, [[0.9, 0.5001], [0.9, 0.5]], np.array([[np.pi], [0.0]]), 0.53)
    np.testing.assert_allclose(off[:, 0], [0.53, 0.53])
