"""The observation-target agent (pyro_slam.planning.seek): it visits the inverse model's modes
best first, stops at the first whose view matches the target, else returns to the best view."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from pyro_slam.planning import (
    GroundTruthEnv,
    Look,
    execute,
    free_grid,
    seek_observation,
    seek_pose,
    sensor,
)
from pyro_slam.planning.planner import inside_scan, segments_cross
from pyro_slam.planning.seek import approach, match_view
from simulators import make_maze, raycast
from simulators.traversal import integrate_controls


@pytest.fixture(scope="module")
def world():
    """A 3 x 3 maze, planned in its true geometry; the target is the last grid point's scan,
    which every other grid point sees differently by more than 0.03."""
    maze = make_maze("simple-medium", 3)
    env = GroundTruthEnv(maze)
    pts = free_grid(maze)
    target = np.array([*pts[-1], 0.3])
    scan = env.scan(target)[0].numpy()  # [B]
    return maze, env, pts, target, scan


def _seek(world, hypotheses, accept_tol):
    maze, env, pts, target, scan = world
    return seek_observation(
        env,
        np.array([*pts[0], 0.0]),
        hypotheses,
        lambda z, u: execute(maze, z, u)[0],
        Look(env, scan),
        accept_tol=accept_tol,
        max_expansions=1000,
    )


def test_a_wrong_first_mode_is_left_for_the_next(world):
    """The first hypothesis is another grid point: its view differs, so the agent goes on to
    the second, the target, and stops there."""
    _, _, pts, target, _ = world
    res = _seek(world, np.array([pts[12], target[:2]]), accept_tol=0.02)
    assert res.found and res.accepted == 1 and len(res.goals) == 2
    assert res.diffs[0] > 0.02 > res.diffs[1]
    assert np.hypot(*(res.poses[-1, :2] - target[:2])) < 0.05
    assert np.allclose(res.stops[1], res.poses[-1])
    assert len(res.poses) == len(res.controls) + 1 == len(res.path)


def test_no_match_returns_to_the_best_view(world):
    """Nothing is accepted (tolerance 0): after the last hypothesis the agent goes back to the
    one whose view matched best, the target."""
    _, _, pts, target, _ = world
    res = _seek(world, np.array([target[:2], pts[12]]), accept_tol=0.0)
    assert res.found and res.accepted is None and len(res.goals) == 2
    assert res.diffs[0] < res.diffs[1]
    # at the hypothesis itself (A* stops within 0.025 of it, the approach closes the rest)
    assert np.hypot(*(res.poses[-1, :2] - target[:2])) < 1e-3
    assert all(np.hypot(*(z[:2] - g)) < 1e-3 for z, g in zip(res.stops, res.goals))
    assert np.hypot(*(res.stops[1][:2] - target[:2])) > 0.1  # it had left the target


def test_accepted_first_mode_ends_the_search(world):
    _, _, pts, target, _ = world
    res = _seek(world, np.array([target[:2], pts[12]]), accept_tol=0.02)
    assert res.accepted == 0 and len(res.goals) == 1


def test_look_finds_the_target_view_near_the_agent(world):
    """The agent's view, 0.03 from the target at another heading, differs from the target scan
    by more than 0.01; matched over nearby offsets it shows the target's view at the offset
    that leads back to the target. Against a wall the look is still defined."""
    maze, env, _, target, scan = world
    look = Look(env, scan)
    d, offset = look(target)
    assert d < 0.003 and np.hypot(*offset) < 1e-9
    here = target + np.array([0.03, -0.02, 1.0])
    ang = 2 * np.pi * np.arange(360) / 360 - np.pi
    rays = raycast(maze.walls, here[None, :2], ang[None], env.lidar.max_range)[0]  # [360]
    assert match_view(rays, scan, env.lidar.max_range, radius=0.0)[0] > 0.01  # not from here
    d, offset = look(here)
    assert d < 0.005 and np.allclose(offset, [-0.03, 0.02], atol=1e-9)
    (x0, y0), (x1, y1) = maze.walls[len(maze.walls) // 2].reshape(2, 2)
    d, _ = look(np.array([(x0 + x1) / 2 + 5e-4, (y0 + y1) / 2 + 5e-4, 0.0]))
    assert np.isfinite(d)
    with pytest.raises(ValueError, match="multiple of the 20 beams"):
        Look(env, scan, headings=50)


def test_approach_drives_to_the_goal_in_primitive_steps():
    u = approach(np.array([0.1, 0.2, 3.0]), np.array([0.13, 0.18]))
    assert np.abs(u[:, 0]).max() <= 0.3 + 1e-12 and u[:, 1].max() <= 0.008 + 1e-12
    assert np.allclose(integrate_controls(np.array([0.1, 0.2, 3.0]), u)[-1, :2], [0.13, 0.18])
    assert approach(np.array([0.1, 0.2, 0.0]), np.array([0.1, 0.2])).shape == (0, 2)
    ahead = approach(np.array([0.1, 0.2, 0.0]), np.array([0.12, 0.2]))  # facing it: no turn
    assert np.all(ahead[:, 0] == 0) and np.isclose(ahead[:, 1].sum(), 0.02)


class _Unexplored(GroundTruthEnv):
    """True geometry, but a band 0.2 < x < 0.3 is unexplored until the agent's own scans show
    it, as in :meth:`~pyro_slam.planning.LearnedEnv.with_observation`."""

    seen: list = []

    def valid(self, z) -> np.ndarray:
        xy = np.asarray(z)[:, :2]
        ok = ~((xy[:, 0] > 0.2) & (xy[:, 0] < 0.3))
        for pose, scan in self.seen:
            ok |= inside_scan(xy, pose, scan)
        return ok

    def with_observation(self, pose, scan):
        out = copy.copy(self)
        out.seen = [*self.seen, (np.asarray(pose, float), np.asarray(scan, float))]
        return out


def test_a_goal_beyond_unexplored_space_is_reached_by_scanning_towards_it():
    """No plan crosses the unexplored band; the agent that scans at the reached place nearest
    to the goal, trusts what it sees and plans again gets through, in a few scans. Without its
    sensor, or with no rounds, it gives up where it stands."""
    maze = make_maze("simple-medium", 3)
    env = _Unexplored(maze)
    start, goal = np.array([0.08, 0.08, 0.0]), np.array([0.42, 0.08])

    def move(z, u):
        return execute(maze, z, u)[0]

    def go(**kw):
        return seek_pose(env, start, goal, move, **kw)

    blind = go(max_expansions=600)
    assert not blind.found and blind.scans == 0 and len(blind.poses) == 1
    assert not go(sense=sensor(env), rounds=0, max_expansions=600).found
    res = go(sense=sensor(env), rounds=3, max_expansions=600)
    assert res.found and 1 <= res.scans <= 3
    assert np.hypot(*(res.poses[-1, :2] - goal)) < 1e-3
    assert not segments_cross(res.poses[:, :2], maze.walls)
    # where a plan exists the agent does not scan
    near = seek_pose(env, start, [0.15, 0.08], move, sense=sensor(env), max_expansions=600)
    assert near.found and near.scans == 0
    with pytest.raises(TypeError, match="with_observation"):  # an env that cannot trust a scan
        seek_pose(GroundTruthEnv(maze), start, goal, move, sense=sensor(env))
