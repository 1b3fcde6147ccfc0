"""Hybrid A* navigation (pyro_slam.planning): safety term, no paths through walls, planning in
the learned model on a small maze."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from pyro_slam.planning import (
    GroundTruthEnv,
    ScanHits,
    execute,
    free_grid,
    inside_scan,
    learned_env,
    lookalikes,
    plan,
    safety,
    safety_cost,
    segments_cross,
)
from simulators import make_maze
from simulators.world import point_segment_distance


def test_safety_monotone_decreasing():
    x = torch.linspace(0.0, 0.6, 601, dtype=torch.float64)
    s = safety(x)
    assert torch.all(s[1:] < s[:-1])
    assert s[0] > 0.9 * 1e4 and s[-1] < 1e-10
    assert float(safety(torch.tensor(0.03))) == pytest.approx(5e3)
    scans = torch.stack([torch.full((20,), 0.02), torch.full((20,), 0.2)])
    c = safety_cost(scans)
    assert c[0] > c[1] and c.shape == (2,)


def test_segments_cross():
    walls = np.array([[0.5, 0.0, 0.5, 1.0]])
    assert segments_cross(np.array([[0.4, 0.5], [0.6, 0.5]]), walls)
    assert not segments_cross(np.array([[0.1, 0.5], [0.4, 0.5]]), walls)


def test_ground_truth_plan_never_crosses_walls():
    maze = make_maze("simple-medium", 3)  # 3 x 3 cells, side 0.5
    env = GroundTruthEnv(maze)
    pts = free_grid(maze, 3)
    for a, b in [(0, 8), (2, 6), (8, 1)]:
        start = np.array([*pts[a], 0.0])
        r = plan(env, start, pts[b], max_expansions=800)
        assert r.success
        assert not segments_cross(r.path[:, :2], maze.walls)
        ex, coll = execute(maze, start, r.controls)
        assert not segments_cross(ex[:, :2], maze.walls)
        assert coll == 0
        assert np.hypot(*(ex[-1, :2] - pts[b])) <= 0.05


def test_learned_plan_on_simple_maze():
    torch.manual_seed(0)
    maze = make_maze("simple-medium", 3)
    env, _, _ = learned_env(maze, steps=1200, fit_steps=400)
    pts = free_grid(maze, 3)
    start = np.array([*pts[0], 0.0])
    r = plan(env, start, pts[2], max_expansions=800)
    assert r.success
    ex, _ = execute(maze, start, r.controls)
    assert not segments_cross(ex[:, :2], maze.walls)
    assert np.hypot(*(ex[-1, :2] - pts[2])) <= 0.05


def test_learned_rollouts_sample_the_model_and_plans_are_deterministic():
    """``LearnedEnv.rollout`` draws ``samples`` runs of ``DVBFLM.model`` for a batch of start
    poses in one trace: each row's successors are the draws' mean poses, close to the model's
    noise-free kinematics (its transition's noise is small), and its end scans are draws of the
    observation site about the predicted scan (the model's own, with the noise fitted to the
    mapping traversal); a rollout is a function of its start poses (kept per start pose, so a
    repeated plan runs the model no more) and a search that rolls out its next open nodes in
    batches plans as one node at a time does (both reach the target)."""
    from pyro_slam.planning import Primitives

    torch.manual_seed(0)
    maze = make_maze("simple-medium", 3)
    env, _, _ = learned_env(maze, steps=600, fit_steps=100)
    assert env.model.sigma_emission < 0.05  # the fitted noise, not the training noise of 0.1
    prims = Primitives().padded()  # [P, L, 2]
    P, L, _ = prims.shape
    S = env.samples
    z0 = np.array([[0.08, 0.08, 0.0], [0.25, 0.1, 1.2], [0.4, 0.42, -2.0]])
    ends, travel, scans, paths = env.rollout(z0, prims)
    assert ends.shape == (3, P, 3) and scans.shape == (3, P, S, 20)
    assert paths.shape == (3, P, L + 1, 3)
    again = env._rollout(z0, prims)  # the model run again: the same draws
    assert np.array_equal(again[3], paths) and torch.equal(again[2], scans)
    z, M = torch.as_tensor(z0, dtype=prims.dtype)[:, None].expand(3, P, 3), env.M
    model = env.model
    for t in range(L):  # the noise-free kinematics, clipped by the predicted scans
        z = model.transition.mean(z, prims[:, t], model.emission_mean(M, z))
    assert np.abs(paths[:, :, -1, :2] - z[..., :2].numpy()).max() < 0.01
    mean_scan = model.emission_mean(M, torch.as_tensor(ends, dtype=prims.dtype))  # [3, P, 20]
    err = (scans.mean(2) - mean_scan).abs().mean()
    assert err < 4 * model.sigma_emission / math.sqrt(S) + 0.01
    # 5 steps at most, plus the mean path's jitter from the transition's noise
    jitter = (L + 1) * float(model.transition.sigma[:2].max()) / math.sqrt(S)
    assert (travel > 0).any() and np.all(travel <= 5 * 0.008 + 2 * jitter)

    pts = free_grid(maze, 3)
    start, runs = np.array([*pts[0], 0.0]), []
    env._rollout = lambda z, c, f=env._rollout: runs.append(len(z)) or f(z, c)
    first = plan(env, start, pts[8], max_expansions=400)
    assert first.success and max(runs) > 1  # several nodes per model run
    n = len(runs)
    again = plan(env, start, pts[8], max_expansions=400)
    assert len(runs) == n  # every rollout of the repeated search was kept
    seen = env.with_observation(start, GroundTruthEnv(maze).scan(start)[0].numpy())
    assert seen._memos is env._memos  # and shared by the copies that trust a real scan
    assert np.array_equal(again.controls, first.controls)
    one = copy.copy(env)  # the same model and map, nothing kept, one node per model run
    one._memos, one.rollout_batch = {}, 1
    assert plan(one, start, pts[8], max_expansions=400).success


def test_learned_env_fitted_emission_beats_shipped_on_its_maze():
    """``emission_steps > 0``: an emission with ``n_world`` directions fitted to the mapping
    traversal predicts that traversal's scans better than the shipped 20-direction one."""
    torch.manual_seed(0)
    maze = make_maze("simple-medium", 3)
    shipped, (loc0, _), tr = learned_env(maze, steps=600, fit_steps=300)
    fitted, (loc1, _), _ = learned_env(maze, tr, fit_steps=300, emission_steps=400, n_world=40)
    assert fitted.model.emission.n_world == 40 and shipped.model.emission.n_world == 20
    z = torch.as_tensor(tr.poses, dtype=torch.float32)
    x = torch.as_tensor(tr.observations, dtype=torch.float32)
    with torch.no_grad():
        rms = [
            (e.model.emission_mean(m, z) - x).pow(2).mean().sqrt()
            for e, m in ((shipped, loc0), (fitted, loc1))
        ]
    assert rms[1] < 0.8 * rms[0], rms


def test_learned_env_is_seeded_whatever_ran_before():
    """The fitted emission and map depend on ``seed`` only, not on the random numbers drawn
    before in the process (e.g. a SLAM run, or another maze in the same worker)."""
    maze = make_maze("simple-medium", 3)
    kw = dict(steps=200, fit_steps=20, emission_steps=20, n_world=20)
    torch.manual_seed(1)
    _, (a, _), _ = learned_env(maze, **kw)
    torch.rand(1000)  # something else ran
    _, (b, _), _ = learned_env(maze, **kw)
    _, (c, _), _ = learned_env(maze, seed=2, **kw)
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_scan_hits_keep_the_planner_off_walls_that_the_map_belief_lost():
    """A map belief fitted in an empty room knows none of the maze's inner walls: its plan
    goes straight through one. With the returns of the maze's own mapping scans
    (``ScanHits``, placed from the true poses: they lie on the walls), every step keeps
    ``hit_margin`` from them, and the plan goes round."""
    from simulators import simulate_traversal
    from simulators.maze import Maze

    maze = make_maze("simple-medium", 3)  # 3 x 3 cells, side 0.5; a wall at y = 1/6
    h, v = np.zeros((3, 4), bool), np.zeros((4, 3), bool)
    h[:, [0, 3]], v[[0, 3], :] = True, True  # the same square, outer walls only
    torch.manual_seed(0)
    room, _, _ = learned_env(
        Maze("room", 0, 3, maze.corridor_width, h, v), steps=600, fit_steps=100
    )
    hits = ScanHits(simulate_traversal(maze, steps=600, seed=1))
    on_wall = [point_segment_distance(q, maze.walls).min() for q in hits.points]
    assert len(hits.points) > 1000 and max(on_wall) < 1e-6
    assert np.isinf(hits.clearance(np.array([[0.25, 0.25]]), upto=0.05))[0]
    assert hits.clearance(np.array([[0.25, 1 / 6 + 0.004]]))[0] == pytest.approx(0.004, abs=1e-3)
    pts = free_grid(maze, 3)
    start = np.array([*pts[2], np.pi / 2])  # below the wall, far from its open end
    blind = plan(room, start, pts[4], max_expansions=400)
    assert blind.success and segments_cross(blind.path[:, :2], maze.walls)
    kept = copy.copy(room)
    kept.hits, kept.hit_margin, kept._memos = hits, 0.01, {}
    r = plan(kept, start, pts[4], max_expansions=2000)
    assert r.success and not segments_cross(r.path[:, :2], maze.walls)
    assert hits.clearance(r.path[1:, :2]).min() >= 0.01
    assert r.path[:, 0].min() < 1 / 6  # round the wall's open end, on the left


class _StripEnv(GroundTruthEnv):
    """True geometry, but positions in a thin vertical strip count as unexplored."""

    def valid(self, z) -> np.ndarray:
        x = np.asarray(z)[:, 0]
        return ~((x > 0.2) & (x < 0.215))

    def rollout(self, z0, controls):  # single precision, as the learned model's rollouts
        return tuple(
            np.float32(v) if i != 2 else v for i, v in enumerate(super().rollout(z0, controls))
        )


def test_check_path_rejects_primitives_crossing_unexplored_space():
    """A primitive's end poses (0.04 apart) can jump a strip narrower than that; with
    ``check_path`` every step (0.008 apart) must be valid, so no plan crosses the strip."""
    maze = make_maze("simple-medium", 3)
    env = _StripEnv(maze)
    start, goal = np.array([0.08, 0.08, 0.0]), np.array([0.42, 0.08])
    loose = plan(env, start, goal, max_expansions=600, check_path=False)
    assert loose.success
    assert np.any((loose.path[:, 0] > 0.2) & (loose.path[:, 0] < 0.215))  # it went through
    strict = plan(env, start, goal, max_expansions=600, check_path=True)
    assert not strict.success
    assert strict.expansions < 600  # the search exhausted the reachable side
    assert np.all(strict.visited[:, 0] <= 0.2 + 1e-6)


def test_check_path_allows_leaving_an_unexplored_start():
    """Turning on the spot at an unexplored start is not a step into unexplored space."""
    maze = make_maze("simple-medium", 3)
    env = _StripEnv(maze)
    start, goal = np.array([0.207, 0.08, 0.0]), np.array([0.42, 0.08])
    r = plan(env, start, goal, max_expansions=600, check_path=True)
    assert r.success and r.expansions > 1


def test_inside_scan_is_the_seen_free_space_minus_a_margin():
    maze = make_maze("simple-medium", 3)
    gt = GroundTruthEnv(maze)
    pose = np.array([*free_grid(maze, 3)[4], 0.3])
    scan = gt.scan(pose[None])[0].numpy()
    rng = np.random.default_rng(0)
    xy = pose[:2] + rng.uniform(-0.25, 0.25, (2000, 2))
    ok = inside_scan(xy, pose, scan, margin=0.03)
    assert 0.05 < ok.mean() < 0.95
    seg = np.stack([np.broadcast_to(pose[:2], xy.shape), xy], 1)  # [N, 2, 2]
    assert not any(segments_cross(s, maze.walls) for s in seg[ok])  # seen, so free
    assert np.all(np.hypot(*(xy[ok] - pose[:2]).T) <= 0.1)  # trusted radius
    # a beam's own direction: free up to its range minus the margin, not beyond
    d = np.array([[np.cos(0.3), np.sin(0.3)]])
    far = dict(margin=0.03, radius=np.inf)
    assert inside_scan(pose[:2] + (scan[0] - 0.031) * d, pose, scan, **far)[0]
    assert not inside_scan(pose[:2] + (scan[0] - 0.029) * d, pose, scan, **far)[0]


def test_with_observation_trusts_the_seen_free_space_without_changing_the_env():
    torch.manual_seed(0)
    maze = make_maze("simple-medium", 3)
    env, _, _ = learned_env(maze, steps=300, fit_steps=30, max_std=0.0)  # nothing explored
    start = np.array([*free_grid(maze, 3)[0], 0.0])
    seen = env.with_observation(start, GroundTruthEnv(maze).scan(start[None])[0].numpy())
    near = start + np.array([[0.03, 0.0, 0.0], [0.0, 0.03, 0.0]])
    assert not env.valid(near).any() and seen.valid(near).all()
    assert env.seen == [] and len(seen.seen) == 1
    r = plan(seen, start, start[:2] + [0.0, 0.3], max_expansions=200)
    assert not r.success and r.expansions > 1  # moves in the seen free space, no further
    assert np.all(np.hypot(*(r.visited[:, :2] - start[:2]).T) < 0.3)


def test_ground_truth_places_finds_every_exact_look_alike():
    """The truth's inverse of a noise-free scan: in an empty square room a pose has exactly
    four look-alikes (the room's rotations by 90 degrees), found to float precision; a grid
    point of a test maze whose view is unique has one place, and a near look-alike elsewhere
    is ranked behind it by its (non-zero) difference."""
    from simulators.maze import Maze

    n = 6
    h, v = np.zeros((n, n + 1), bool), np.zeros((n + 1, n), bool)
    h[:, [0, n]], v[[0, n], :] = True, True  # outer walls only
    env = GroundTruthEnv(Maze("room", 0, n, 1 / n, h, v))
    poses, diffs = env.places(env.scan(np.array([0.3, 0.4, 0.7])))[0]
    assert len(poses) == 4 and diffs.max() < 1e-6
    want = {(0.3, 0.4), (0.6, 0.3), (0.7, 0.6), (0.4, 0.7)}
    assert {tuple(np.round(p[:2], 4)) for p in poses} == want
    # three look-alikes besides the target: an ideal inverse picks the wrong one 3 times in 4
    assert lookalikes(poses, diffs, [0.3, 0.4]) == (3, 0.75)
    assert lookalikes(poses, diffs, [0.3, 0.4], radius=0.5) == (0, 0.0)
    for p in poses:  # each rotation of the room turns the heading by a multiple of pi / 2
        k = (p[2] - 0.7) / (np.pi / 2)
        assert abs(k - round(k)) < 1e-4

    maze = make_maze("moderate-medium", 1001)
    env, pts = GroundTruthEnv(maze), free_grid(maze)
    unique, near = env.places(env.scan(np.array([[*pts[3], 0.7], [*pts[0], 0.2]])))
    assert len(unique[0]) == 1 and unique[1][0] < 1e-6
    assert np.hypot(*(unique[0][0, :2] - pts[3])) < 1e-4
    assert np.hypot(*(near[0][0, :2] - pts[0])) < 1e-4 and near[1][0] < 1e-6
    assert near[1][1] > 1e-3  # the best place elsewhere differs: not a look-alike
    with pytest.raises(ValueError, match="multiple of the 20 beams"):
        env.places(env.scan(np.array([0.1, 0.1, 0.0])), n_headings=50)
    with pytest.raises(ValueError, match="19 beams"):
        env.places(np.zeros((1, 19)))


def test_ground_truth_coarse_search_skips_only_positions_that_cannot_match():
    """The coarse search of ``places`` compares only positions whose sorted ranges are within
    the tolerance of the sorted scan: for every position whose best heading is within it, the
    same difference and heading as comparing every position at every heading."""
    maze = make_maze("moderate-medium", 1001)
    env = GroundTruthEnv(maze)
    xy, rays, ranked = env._ray_grid(0.02, 360)
    rng = np.random.default_rng(0)
    z = np.concatenate([free_grid(maze)[:6], rng.uniform(-np.pi, np.pi, (6, 1))], 1)
    beams = (np.arange(360)[:, None] + 18 * np.arange(20)) % 360  # [H, B]
    for x in env.scan(z).numpy().astype(np.float64):
        full = np.abs(rays.numpy()[:, beams] - x).mean(-1)  # [P, H]: every pose
        best, h = env._coarse(x, rays, ranked, 0.03)
        near = full.min(1) <= 0.03
        assert near.any() and (best.numpy()[~near] > 0.03).all()
        assert np.allclose(best.numpy()[near], full.min(1)[near], atol=1e-12)
        assert np.array_equal(h.numpy()[near], full.argmin(1)[near])
        assert (best.numpy() < np.inf).sum() < 0.5 * len(xy)  # most positions were skipped
