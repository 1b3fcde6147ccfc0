from collections import deque

import numpy as np
import pytest

from simulators import SCALES, make_maze, raycast

TABLE_II = {  # name: (side, map w, steps, tiles)
    "simple-small": (0.25, 7, 1500, 3),
    "simple-medium": (0.5, 12, 3000, 6),
    "simple-large": (0.75, 18, 4500, 9),
    "moderate-small": (0.5, 12, 3000, 6),
    "moderate-medium": (1.0, 25, 6000, 12),
    "moderate-large": (1.5, 37, 9000, 18),
    "complex-small": (1.0, 25, 6000, 12),
    "complex-medium": (2.0, 50, 12000, 18),
    "complex-large": (3.0, 75, 18000, 24),
}


def test_scales_reproduce_table_ii():
    assert set(SCALES) == set(TABLE_II)
    for name, (side, w, steps, tiles) in TABLE_II.items():
        s = SCALES[name]
        assert s.side == pytest.approx(side)
        assert s.cells * s.corridor_width == pytest.approx(side)
        assert s.map_dims == (w, w, 20)
        assert (s.steps, s.tiles) == (steps, tiles)
        assert s.cells == {"simple": 3, "moderate": 6, "complex": 12}[name.split("-")[0]]


def _reachable_cells(maze) -> int:
    """BFS over cells; neighbours connect when the centre-to-centre segment hits no wall."""
    w, n = maze.corridor_width, maze.cells
    seen, queue = {(0, 0)}, deque([(0, 0)])
    while queue:
        i, j = queue.popleft()
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            a, b = i + di, j + dj
            if not (0 <= a < n and 0 <= b < n) or (a, b) in seen:
                continue
            angle = np.arctan2(dj, di)
            r = raycast(maze.walls, maze.cell_center(i, j)[None], np.array([[angle]]), w)[0, 0]
            if r >= w:
                seen.add((a, b))
                queue.append((a, b))
    return len(seen)


@pytest.mark.parametrize("name", sorted(TABLE_II))
def test_every_scale_builds_a_connected_maze(name):
    maze = make_maze(name, seed=3)
    side = TABLE_II[name][0]
    assert maze.side == pytest.approx(side)
    assert maze.walls.dtype == np.float64 and maze.walls.shape[1] == 4
    assert maze.walls.min() >= 0 and maze.walls.max() == pytest.approx(side)
    # the boundary is closed: each side is covered by one merged segment
    for seg in ([0, 0, side, 0], [0, side, side, side], [0, 0, 0, side], [side, 0, side, side]):
        assert np.any(np.all(np.isclose(maze.walls, seg), axis=1)), seg
    assert _reachable_cells(maze) == maze.cells**2


def test_walls_are_maximal_collinear_segments():
    maze = make_maze("complex-medium", seed=0)
    walls = maze.walls
    for a in range(len(walls)):
        for b in range(a + 1, len(walls)):
            p, q = walls[a], walls[b]
            same_h = p[1] == p[3] == q[1] == q[3]
            same_v = p[0] == p[2] == q[0] == q[2]
            if same_h:
                assert max(p[0], q[0]) > min(p[2], q[2]) + 1e-12  # gap between them
            if same_v:
                assert max(p[1], q[1]) > min(p[3], q[3]) + 1e-12


def _open_passages(maze) -> int:
    n = maze.cells
    return sum(len(maze.neighbours(i, j)) for i in range(n) for j in range(n)) // 2


def test_dfs_is_a_tree_and_extra_removals_add_loops():
    tree = make_maze("complex-small", seed=5, loop_fraction=0.0)
    assert _open_passages(tree) == tree.cells**2 - 1  # spanning tree
    loopy = make_maze("complex-small", seed=5)
    extra = _open_passages(loopy) - (loopy.cells**2 - 1)
    interior_walls = 2 * loopy.cells * (loopy.cells - 1) - (loopy.cells**2 - 1)
    assert extra == round(0.1 * interior_walls) > 0


def test_same_seed_same_maze_different_seed_different():
    a, b, c = (make_maze("moderate-medium", s) for s in (7, 7, 8))
    np.testing.assert_array_equal(a.walls, b.walls)
    assert a.walls.shape != c.walls.shape or not np.array_equal(a.walls, c.walls)


def test_helpers():
    maze = make_maze("moderate-medium", seed=0)
    w = maze.corridor_width
    np.testing.assert_allclose(maze.cell_center(2, 3), [2.5 * w, 3.5 * w])
    assert maze.free_cells().shape == (36, 2)
    rng = np.random.default_rng(0)
    poses = np.array([maze.random_free_pose(rng) for _ in range(200)])
    assert maze.contains(poses[:, :2]).all()
    assert np.all((poses[:, 2] >= -np.pi) & (poses[:, 2] < np.pi))
    off = (poses[:, :2] / w) % 1.0
    assert np.all((off >= 0.25) & (off <= 0.75))  # margin from the cell's walls
    assert maze.contains([[0.5, 0.5], [1.2, 0.5], [0.0, 0.5]]).tolist() == [True, False, False]
    np.testing.assert_array_equal(maze.cell_of([[0.01, 0.99], [0.55, 0.2]]), [[0, 5], [3, 1]])
    with pytest.raises(ValueError, match="unknown maze scale"):
        make_maze("huge-medium")
