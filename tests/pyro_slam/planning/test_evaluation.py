"""Navigation measures: a run's verdict by position and in observation space, the look-alikes
of observation targets, and the ratios and counts over a sample of run records."""

from __future__ import annotations

import numpy as np
import pytest

from pyro_slam.planning import GroundTruthEnv, free_grid
from pyro_slam.planning.evaluation import (
    aliasing,
    mean_or_none,
    miss_counts,
    observation_reached,
    observation_targets,
    pose_reached,
    reached_within,
    scan_match,
    scan_reached,
    success_ratios,
)
from simulators import LidarConfig, make_maze
from simulators.maze import Maze


def empty_room(n: int = 6) -> Maze:
    """A unit square with its outer walls only: every scan but the centre's is seen at four
    places, the room's quarter turns."""
    h, v = np.zeros((n, n + 1), bool), np.zeros((n + 1, n), bool)
    h[:, [0, n]], v[[0, n], :] = True, True
    return Maze("room", 0, n, 1 / n, h, v)


def test_scan_match_finds_the_target_view_near_it_and_not_elsewhere():
    maze = make_maze("moderate-medium", 1001)
    env, pts = GroundTruthEnv(maze), free_grid(maze)
    scan = env.scan(np.array([*pts[3], 0.7]))[0].numpy()  # a target seen with heading 0.7
    # at the target, or within the 0.05 success radius, some heading sees (almost) that scan
    assert scan_match(env, pts[3], scan) < 0.01
    assert scan_match(env, pts[3] + 0.03, scan) < 0.01
    # the other grid points of this maze do not look like it
    others = [scan_match(env, q, scan) for i, q in enumerate(pts[:8]) if i != 3]
    assert min(others) > 0.02
    # every heading's scan is a rotation of the rays cast from each position: the exact scan
    # at a grid heading is found to float precision
    h = 2 * np.pi * 37 / 360 - np.pi
    exact = env.scan(np.array([*pts[3], h]))[0].numpy()
    assert scan_match(env, pts[3], exact) < 1e-6
    with pytest.raises(ValueError, match="multiple of the 20 beams"):
        scan_match(env, pts[3], scan, headings=72)


def test_observation_space_verdict_counts_both_places_of_an_aliased_pair():
    """An agent that stops at the twin of the target's place (the room turned by half a turn)
    has reached the observation, although it is not within 0.05 of the target; a place that
    looks different has not."""
    env = GroundTruthEnv(empty_room())
    target = np.array([0.3, 0.4, 0.7])
    scan = env.scan(target)[0].numpy()
    here, d_here = scan_reached(env, target[:2], scan)
    there, d_there = scan_reached(env, np.array([0.7, 0.6]), scan)  # turned by half a turn
    assert here and there and d_here < 0.01 and d_there < 0.01
    assert np.hypot(*(np.array([0.7, 0.6]) - target[:2])) > 0.05  # missed by position
    # nearby, within the 0.05 radius, still reached; elsewhere in the room, not
    assert scan_reached(env, np.array([0.73, 0.6]), scan)[0]
    far, d_far = scan_reached(env, np.array([0.5, 0.5]), scan)
    assert not far and d_far > 0.01
    # the tolerance decides: the verdict at the twin place flips below its difference
    assert not scan_reached(env, np.array([0.7, 0.6]), scan, tol=d_there / 2)[0]


def test_a_pose_target_is_reached_within_the_radius_and_only_with_a_plan():
    target = np.array([0.5, 0.5])
    ok, err = pose_reached(True, np.array([0.524, 0.532, 2.0]), target)  # heading ignored
    assert ok and err == pytest.approx(0.04)
    assert pose_reached(True, [0.5, 0.56], target) == (False, pytest.approx(0.06))
    assert pose_reached(False, [0.5, 0.5], target) == (False, 0.0)  # stopped there by chance
    assert pose_reached(True, [0.5, 0.56], target, radius=0.1)[0]


def test_an_observation_target_is_reached_at_its_place_or_at_a_look_alike_with_a_plan():
    env = GroundTruthEnv(empty_room())
    target = np.array([0.3, 0.4, 0.7])
    scan = env.scan(target)[0].numpy()
    twin = np.array([0.7, 0.6, -1.0])  # the room turned by half a turn: the same scan
    assert observation_reached(True, twin, target, env, scan)[0]
    assert not pose_reached(True, twin, target)[0]
    assert not observation_reached(False, twin, target, env, scan)[0]  # no plan, no success
    ok, d = observation_reached(True, np.array([0.5, 0.5]), target, env, scan)
    assert not ok and d > 0.01
    # within the radius of the target it is reached whatever the tolerance
    assert observation_reached(True, target + [0.02, 0, 0], target, env, scan, tol=0.0)[0]


def test_observation_targets_are_every_point_twice_with_headings_seeded_per_maze():
    pts = np.array([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6]])
    t = observation_targets(pts, 1001, 0)
    assert t.shape == (6, 3)
    np.testing.assert_array_equal(t[:, :2], np.repeat(pts, 2, 0))
    assert np.all((-np.pi <= t[:, 2]) & (t[:, 2] < np.pi)) and t[0, 2] != t[1, 2]
    np.testing.assert_array_equal(observation_targets(pts, 1001, 0), t)  # reproducible
    assert not np.allclose(observation_targets(pts, 1002, 0)[:, 2], t[:, 2])  # per maze
    assert not np.allclose(observation_targets(pts, 1001, 1)[:, 2], t[:, 2])  # per seed


def test_aliasing_counts_exact_look_alikes_and_the_ideal_failure():
    """In an empty square room every pose but the centre has three exact look-alikes (the
    room's rotations), so an ideal inverse picks the right one of four: it fails 3/4 of the
    time; the centre is unique. A longer range does not help in an empty room."""
    room = empty_room()
    tposes = np.array([[0.3, 0.4, 0.7], [0.5, 0.5, 0.2], [0.2, 0.2, -1.0]])
    by_tol = aliasing(room, tposes, LidarConfig(), tols=[1e-6, 0.0], spacing=0.01)
    r = by_tol[1e-6]
    assert r["lookalikes"] == [3, 0, 3]
    assert r["ideal_failure"] == pytest.approx([0.75, 0.0, 0.75])
    # each tolerance is its own verdict: below every difference nothing looks alike
    assert by_tol[0.0] == {"lookalikes": [0, 0, 0], "ideal_failure": [0.0, 0.0, 0.0]}
    r = aliasing(room, tposes[:1], LidarConfig(n_beams=40, max_range=1.5), [1e-6], 0.01)
    assert r[1e-6]["lookalikes"] == [3]


def row(maze, goal, planner, ok, **kw):
    """A run record of pair ``(0, goal)`` in ``maze``."""
    return {
        "maze": maze,
        "start": 0,
        "goal": goal,
        "planner": planner,
        "found": True,
        "success_noiseless": ok,
        **kw,
    }


def obs(maze, goal, ok, scan_ok, found=True, inference_error=0.01, aliased=0, near=0):
    """A ``learned_obs`` run record: ``aliased`` exact look-alikes, ``near`` within the
    tolerance."""
    return row(
        maze,
        goal,
        "learned_obs",
        ok,
        scan_success_noiseless=scan_ok,
        found=found,
        inference_error=inference_error,
        target_lookalikes_exact=aliased,
        target_lookalikes_tol=max(near, aliased),
    )


RUNS = [
    *(row(1001, g, "ground_truth", g != 4) for g in range(1, 6)),  # 4 solved by the truth
    *(row(1001, g, "learned", g not in (3, 4)) for g in range(1, 6)),  # misses 3 (and 4)
    obs(1001, 1, True, True),
    obs(1001, 2, False, True, inference_error=0.3, aliased=2),  # a look-alike: reached
    *(row(1001, g, "ground_truth_obs", g not in (2, 4)) for g in range(1, 6)),
    obs(1001, 3, False, False, found=False),
    obs(1001, 4, False, False, inference_error=0.3, near=1),  # a wrong goal, near-alike
    obs(1001, 5, False, False),  # right goal, ended elsewhere
    row(1002, 1, "ground_truth", True),
    row(1002, 1, "learned", True),
    obs(1002, 1, False, False, inference_error=0.2),
]


def test_miss_counts_sort_the_missed_observation_targets_by_cause():
    c = miss_counts(RUNS)
    assert c["1001"] == {
        "pairs": 5,
        "gt_solved": 4,
        "learned_on_gt_solved": 3,
        "obs_missed": 4,
        "obs_missed_scan": 3,
        "obs_missed_scan_not_found": 1,
        "obs_missed_scan_wrong_goal": 1,
        "obs_missed_scan_execution": 1,
        "obs_unaliased": 3,
        "obs_unaliased_missed": 2,
        "obs_target_aliased": 1,
        "gt_obs_missed": 2,
    }
    assert c["1002"]["obs_missed_scan_wrong_goal"] == 1 and c["1002"]["gt_solved"] == 1
    assert c["all"]["pairs"] == 6 and c["all"]["obs_missed_scan"] == 4
    assert c["all"]["learned_on_gt_solved"] == 4
    assert list(c) == ["1001", "1002", "all"]
    assert miss_counts([]) == {"all": {}}


def test_success_ratios_judge_observation_targets_in_observation_space_and_unaliased():
    """4 of 6 observation runs missed in observation space; by position 3 of the 4 runs whose
    target has no look-alike within the tolerance; pose targets 4 of the 5 pairs the truth
    solves."""
    assert success_ratios(RUNS) == {
        "obs_failure_ratio_obs_space": 4 / 6,
        "obs_failure_ratio_position_unaliased": 3 / 4,
        "unaliased_targets": 4,
        "pose_success_ratio": 4 / 5,
    }
    # a sample without observation targets or solved pairs has no ratio, not a zero one
    poses_only = [r for r in RUNS if r["planner"] == "learned"]
    assert success_ratios(poses_only) == {
        "obs_failure_ratio_obs_space": None,
        "obs_failure_ratio_position_unaliased": None,
        "unaliased_targets": 0,
        "pose_success_ratio": None,
    }


def test_a_run_reaches_the_targets_view_within_a_tolerance_only_with_a_plan():
    run = {"success_noiseless": False, "found": True, "scan_diff_noiseless": 0.004}
    assert reached_within(run, 0.005) and not reached_within(run, 0.004)
    assert not reached_within({**run, "found": False}, 0.005)
    assert reached_within({**run, "success_noiseless": True, "scan_diff_noiseless": 1.0}, 0.0)


def test_mean_or_none_is_the_share_of_true_values_and_none_without_values():
    assert mean_or_none([True, False, False, True]) == 0.5
    assert mean_or_none([0.25, 0.75, 1.0]) == pytest.approx(2 / 3)
    assert mean_or_none([]) is None
