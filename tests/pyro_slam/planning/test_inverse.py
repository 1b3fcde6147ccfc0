"""Amortised inverse model q(z | x) (pyro_slam.inverse): shapes, bad input, the ELBO improves,
and observation -> pose recovery on a small maze with a map fitted at the true poses."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pyro_slam.planning import GroundTruthEnv, free_grid, learned_env
from pyro_slam.planning.inverse import InversePose, PoseEncoder, fit_inverse, heading_error
from simulators import make_maze
from simulators.world import point_segment_distance


@pytest.fixture(scope="module")
def small():
    """3 x 3 maze (side 0.5), q(M) fitted at the true poses of a 1200-step traversal, q(z|x)
    trained with 1000 sleep and 300 ELBO steps; plus the ELBO trace."""
    torch.manual_seed(0)
    maze = make_maze("simple-medium", 3)
    env, _, tr = learned_env(maze, steps=1200, fit_steps=400)
    inv = InversePose(env.model, env.M, env.bounds, max_range=tr.max_range, valid=env.valid)
    hist = inv.fit(tr.observations, steps=300, sleep_steps=1000, seed=0)
    return maze, env, tr, inv, hist


def test_a_fit_is_the_same_after_another_encoder_was_fitted(small):
    """Two encoders fitted one after the other in one process (two mazes of a benchmark
    worker): the second's ELBO phase trains its own parameters, so it ends where a fit of the
    same seed ends whatever ran before."""
    _, env, tr, _, _ = small

    def fitted():
        torch.manual_seed(1)  # the encoder's initial weights (as fit_inverse seeds them)
        inv = InversePose(env.model, env.M, env.bounds, max_range=tr.max_range, valid=env.valid)
        inv.fit(tr.observations, steps=20, sleep_steps=5, seed=1)
        return torch.cat([p.detach().flatten() for p in inv.encoder.parameters()])

    first, second = fitted(), fitted()
    assert torch.equal(first, second)


def test_encoder_shapes_and_heading_range():
    enc = PoseEncoder(20, 0.53, (0.0, 1.0, 0.0, 1.0))
    loc, scale = enc(torch.rand(4, 7, 20) * 0.5)
    assert loc.shape == (4, 7, 3) and scale.shape == (4, 7, 3)
    assert (loc[..., :2] >= 0).all() and (loc[..., :2] <= 1).all()
    assert (loc[..., 2].abs() <= np.pi).all() and (scale > 0).all()


def test_wrong_beam_count_raises_with_shape():
    enc = PoseEncoder(20, 0.53, (0.0, 1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match=r"\[\.\.\., 20\].*\(5, 19\)"):
        enc(torch.rand(5, 19))


def test_infer_shapes_and_bad_input(small):
    _, _, tr, inv, _ = small
    z, ll = inv.infer(tr.observations[:6], n_samples=2, n_restarts=2, refine_steps=3)
    assert z.shape == (6, 3) and ll.shape == (6,)
    assert (z[:, 2] >= -np.pi).all() and (z[:, 2] < np.pi).all()
    z1, ll1 = inv.infer(tr.observations[0], n_samples=2, n_restarts=2, refine_steps=3)
    assert z1.shape == (3,) and ll1.shape == ()
    with pytest.raises(ValueError, match="got shape"):
        inv.infer(tr.observations[:3, :10])


def test_modes_are_distinct_places_best_first(small):
    """The first mode is infer's answer; the others lie farther than the separation from every
    mode before them and score no higher; bad k or separation is refused."""
    _, _, tr, inv, _ = small
    kw = dict(n_samples=8, n_restarts=16, refine_steps=5)
    scans = tr.observations[:5]
    modes = inv.modes(scans, k=3, separation=0.1, **kw)
    best, _ = inv.infer(scans, **kw)
    x = torch.as_tensor(scans, dtype=torch.get_default_dtype())
    assert len(modes) == 5 and any(len(m) > 1 for m in modes)
    for m, b, xi in zip(modes, best, x):
        assert 1 <= len(m) <= 3 and torch.equal(m[0], b)
        d = torch.cdist(m[:, :2], m[:, :2]) + 9 * torch.eye(len(m))
        assert (d > 0.1).all()
        ll = inv.log_likelihood(xi.expand(len(m), -1), m)
        assert (ll[1:] <= ll[0] + 1e-4).all()
    with pytest.raises(ValueError, match="k=0"):
        inv.modes(scans, k=0)


def test_elbo_improves(small):
    *_, hist = small
    assert np.mean(hist[-50:]) > np.mean(hist[:50]) + 1.0


def test_recovers_poses_on_small_maze(small):
    """Scans rendered at 30 random explored free-space poses: median position error of the
    inferred target (mode) < 0.05 (paper success radius) and median heading error < 0.2 rad."""
    maze, env, _, inv, _ = small
    rng = np.random.default_rng(0)
    poses = []
    while len(poses) < 30:
        p = np.array([*rng.uniform(0.03, maze.side - 0.03, 2), rng.uniform(-np.pi, np.pi)])
        if point_segment_distance(p[:2], maze.walls).min() > 0.03 and env.valid(p[None])[0]:
            poses.append(p)
    poses = np.array(poses)
    scans = GroundTruthEnv(maze).scan(poses)  # [30, 20]
    z, _ = inv.infer(scans)
    err = np.hypot(*(z[:, :2].numpy() - poses[:, :2]).T)
    assert np.median(err) < 0.05
    assert np.median(heading_error(z[:, 2].numpy(), poses[:, 2])) < 0.2


def test_fit_inverse_from_env_runs():
    torch.manual_seed(1)
    maze = make_maze("simple-small", 2)
    env, _, tr = learned_env(maze, steps=200, fit_steps=50)
    inv = fit_inverse(env, tr, steps=5, sleep_steps=5)
    assert inv.infer(tr.observations[:2], n_restarts=1, refine_steps=2)[0].shape == (2, 3)


def test_navigate_cli_with_observation_target(tmp_path, capsys):
    import json

    from pyro_slam import cli

    maze = make_maze("simple-small", 2)
    tx, ty = map(float, free_grid(maze)[-1])
    out = tmp_path / "nav.png"
    args = ["navigate", "--maze", "simple-small", "--maze-seed", "2", "--out", str(out)]
    args += ["--traversal-steps", "200", "--fit-steps", "50", "--max-expansions", "50"]
    args += ["--inverse-steps", "5", "--inverse-sleep-steps", "5"]
    args += ["--target-scan-from-pose", str(tx), str(ty), "0.5"]
    rc = cli.main(args)
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rc == (0 if report["found"] else 1)  # (50 expansions may find no plan)
    assert len(report["inferred_goal"]) == 3 and report["inference_error"] >= 0
    assert report["target_lookalikes_exact"] >= 0
    # the agent heads for the inverse model's modes in turn, judging each by its own view
    assert 1 <= report["goals_visited"] == len(report["view_differences"]) <= 3
    assert out.is_file()
    # the ground-truth planner takes the truth's own inverse: the target's place, exactly
    rc = cli.main([*args, "--planner", "ground_truth", "--overwrite"])
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rc == (0 if report["found"] else 1)
    assert report["target_lookalikes_exact"] == 0 and report["inference_error"] < 1e-4
    assert report["goals_visited"] == 1
