"""One model for everything: the training objective is the model's ELBO (or a stated relation
to it), a swapped prior or emission noise reaches the filter, the fitted map and the planner,
and Pyro's own SMCFilter on the same model agrees with our filter, log-evidence included."""

from __future__ import annotations

import functools
import math

import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro import poutine
from pyro.infer import SMCFilter, Trace_ELBO

from pyro_slam.inference import (
    ChunkBatch,
    MapBelief,
    ParticleCache,
    ParticleChunkELBO,
    ParticleFilter,
    Particles,
    Weighting,
)
from pyro_slam.model import (
    DVBFLM,
    BootstrapGuide,
    EmissionMLP,
    FilterModel,
    KinematicTransition,
    MapGrid,
    MapGuide,
    RayEmission,
)
from pyro_slam.planning import LearnedEnv
from pyro_slam.slam import fit_map, presets
from simulators import simulate_traversal

B, T = 8, 5


def toy_model(sigma=0.1, prior=None, noise=None, seed=0):
    """A small DVBF-LM: a 6 x 5 grid of 3 features, a small emission MLP, kinematic moves."""
    torch.manual_seed(seed)
    grid = MapGrid((6, 5), 3, origin=(0.0, 0.0), size=(1.0, 0.8))
    emission = EmissionMLP(3, B, hidden=16, layers=2, scale=0.5)
    transition = KinematicTransition((0.02, 0.02, 0.05))
    angles = 2 * math.pi * torch.arange(B) / B
    return DVBFLM(grid, emission, transition, angles, sigma, prior=prior, noise=noise)


def toy_data(seed=0):
    g = torch.Generator().manual_seed(seed)
    obs = 0.25 + 0.1 * torch.rand(T, B, generator=g)
    ctl = torch.stack([0.2 * torch.randn(T - 1, generator=g), torch.full((T - 1,), 0.06)], -1)
    return obs, ctl, torch.tensor([0.4, 0.4, 0.3])


def toy_guide(model, seed=1):
    """A map guide away from the prior (so that the KL term is not zero)."""
    guide = MapGuide(model.grid.shape)
    loc, scale = guide.params()
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        loc.copy_(0.5 * torch.randn(loc.shape, generator=g))
        pyro.get_param_store()["map_scale"] = 0.3 + 0.2 * torch.rand(loc.shape, generator=g)
    return guide


def bootstrap_pose_guide(model, map_guide):
    """The map guide plus a bootstrap pose guide (each pose from the model's transition): the
    guide under which Trace_ELBO estimates the same bound as a one-particle filter."""

    def guide(observations, controls, init_pose, mask=None):
        map_guide()
        z = pyro.sample("z_0", dist.Normal(init_pose, model.init_scale).to_event(1))
        for t in range(1, controls.shape[0] + 1):
            z = pyro.sample(f"z_{t}", model.transition_dist(z, controls[t - 1]))

    return guide


def mean_and_se(values):
    v = torch.tensor(values, dtype=torch.float64)
    return float(v.mean()), float(v.std() / math.sqrt(len(v)))


def objective_losses(model, map_guide, obs, ctl, init, sigma, n):
    """``n`` draws of the project's training loss (times ``T``, one chunk over the whole
    sequence, one particle) with the chunk filter weighing at ``sigma`` (None: the model's)."""
    g = torch.Generator().manual_seed(3)
    cache = ParticleCache(T, 4000, dtype=obs.dtype)
    z0 = init + model.init_scale * torch.randn(4000, 3, generator=g)  # the pose prior
    cache.store(torch.tensor([0]), Particles(z0[None], torch.full((1, 4000), -math.log(4000))))
    pf = ParticleFilter(model, Weighting(sigma=sigma), generator=g)
    elbo = ParticleChunkELBO(pf, cache, obs, ctl, num_particles=1, refresh=False)
    batch = ChunkBatch(torch.tensor([0]), T)
    return [T * elbo.loss(model.map_model, map_guide, batch) for _ in range(n)]


@pytest.mark.parametrize("preset", list(presets.PRESETS))
def test_elbo_matches_pyro_trace_elbo(preset):
    """At each preset's objective, the training loss equals Pyro's Trace_ELBO on
    ``DVBFLM.model`` (map guide plus bootstrap pose guide) within 4 Monte Carlo standard
    errors. ``"elbo"``: the model's own ELBO. ``"filter-sigma"`` (stated relation): the ELBO of
    the same model with ``sigma_E`` replaced by the filter's std."""
    cfg = presets.get(preset).config
    sigma_e, sigma_f = cfg.emission.sigma, cfg.filter.sigma
    sharpened = cfg.training.objective == "filter-sigma"
    obs, ctl, init = toy_data()
    ours_model = toy_model(sigma=sigma_e)
    guide = toy_guide(ours_model)
    ours = objective_losses(ours_model, guide, obs, ctl, init, sigma_f if sharpened else None, 300)
    pyro_model = toy_model(sigma=sigma_f if sharpened else sigma_e)  # same weights (same seed)
    trace = Trace_ELBO()
    pg = bootstrap_pose_guide(pyro_model, guide)
    theirs = [trace.loss(pyro_model.model, pg, obs, ctl, init) for _ in range(300)]
    (m1, s1), (m2, s2) = mean_and_se(ours), mean_and_se(theirs)
    assert abs(m1 - m2) < 4 * math.hypot(s1, s2), (m1, s1, m2, s2)
    # and the test can tell the two objectives apart: the other sigma is far off
    other = sigma_e if sharpened else sigma_f
    if other is not None and other != (sigma_f if sharpened else sigma_e):
        wrong = toy_model(sigma=other)
        m3, s3 = mean_and_se([trace.loss(wrong.model, pg, obs, ctl, init) for _ in range(100)])
        assert abs(m1 - m3) > 4 * math.hypot(s1, s3)


def test_swapped_prior_reaches_filter_and_planner():
    """A map prior N(0, 2^2): the filter's trust compares the belief's variance with 4, not 1;
    a fitted map stays at the prior where no scan reaches; the planner counts a cell as explored
    by its std relative to the prior's."""
    wide = dist.Normal(torch.zeros(3), 2.0 * torch.ones(3)).to_event(1)
    std_model, wide_model = toy_model(), toy_model(prior=wide)
    loc = torch.zeros(std_model.grid.shape)
    scale = torch.full(std_model.grid.shape, 1.0)
    z = torch.tensor([[0.5, 0.4, 0.0]])
    belief = MapBelief(loc, scale)
    w = Weighting()
    # theory: trust = 1 - var(q) / var(prior) at a chart whose four cells have std 1
    assert torch.allclose(w.trust(std_model, z, belief), torch.tensor([[0.01]]))  # (floor)
    assert torch.allclose(w.trust(wide_model, z, belief), torch.tensor([[1 - 1 / 4]]))
    # fitting: cells no scan reaches keep the prior (std 2, not 1); the emission is frozen
    tr = simulate_traversal("simple-small", steps=6, seed=0)
    grid = MapGrid((12, 12), 3, origin=(-2.0, -2.0), size=(6.0, 6.0))  # beyond the maze
    fits = {}
    for name, prior in (("std", None), ("wide", wide)):
        em = EmissionMLP(3, 20, 16, 2, scale=tr.max_range)
        m = DVBFLM(grid, em, KinematicTransition(1e-3), tr.beam_angles, prior=prior)
        fits[name] = fit_map(tr, m, steps=300, lr=0.05)
    far = (slice(0, 2), slice(0, 2))  # cells 2 units from the maze: no scan reaches them
    assert torch.allclose(fits["std"][1][far], torch.ones(()), atol=0.02)
    assert torch.allclose(fits["wide"][1][far], torch.full((), 2.0), atol=0.04)
    # planning: q(M) std 1.0 everywhere is unexplored under N(0, 1), explored under N(0, 4)
    env_std = LearnedEnv(std_model, loc, scale=scale, max_std=0.6)
    env_wide = LearnedEnv(wide_model, loc, scale=scale, max_std=0.6)
    assert not env_std.valid(z.numpy())[0] and env_wide.valid(z.numpy())[0]
    torch.testing.assert_close(env_wide.std(z[:, :2].numpy()), 0.5 * env_std.std(z[:, :2].numpy()))


def test_swapped_emission_noise_reaches_filter():
    """A Student-t emission noise: the filter's weights are the Student-t log-density of the
    scan around the predicted one (here under a fixed map, so no trust inflation)."""
    noise = functools.partial(dist.StudentT, 3.0)
    model = toy_model(noise=noise)
    g = torch.Generator().manual_seed(0)
    M = torch.randn(model.grid.shape, generator=g)
    z0 = torch.tensor([0.5, 0.4, 0.2]) + 0.05 * torch.randn(64, 3, generator=g)
    x = 0.3 + 0.05 * torch.rand(B, generator=g)
    pf = ParticleFilter(model, Weighting(sigma=0.07))
    p, inc = pf.init(z0, M, x)
    scan = model.emission_mean(M, z0)
    expected = dist.StudentT(3.0, scan, 0.07).log_prob(x).sum(-1)  # [64]
    torch.testing.assert_close(p.logw, expected - torch.logsumexp(expected, 0), atol=1e-5, rtol=0)
    torch.testing.assert_close(inc, torch.logsumexp(expected, 0) - math.log(64))
    gauss = dist.Normal(scan, 0.07).log_prob(x).sum(-1)
    assert (p.logw - (gauss - torch.logsumexp(gauss, 0))).abs().max() > 0.1  # not Gaussian


def smc_run(model, M, obs, ctl, init, K, resample=True):
    """Pyro's SMCFilter on ``FilterModel``: weighted means ``[T, 3]`` and (without resampling)
    the log-evidence from the particles' log-likelihoods and weights."""
    smc = SMCFilter(FilterModel(model, M), BootstrapGuide(model), K, max_plate_nesting=0,
                    ess_threshold=0.5 if resample else 1e-12)  # fmt: skip
    log_ev = 0.0
    means = []
    with torch.no_grad():
        for t in range(obs.shape[0]):
            # (a copy: SMCFilter updates its weights in place)
            prev = smc.get_empirical()["z"].log_weights.clone() if t else None
            if t == 0:
                smc.init(init_pose=init, x=obs[0])
                prev = torch.full((K,), -math.log(K))
            else:
                smc.step(obs[t], ctl[t - 1])
            prev = prev - torch.logsumexp(prev, 0)
            log_ev += float(torch.logsumexp(prev + smc.state["log_lik"], 0))
            means.append(smc.get_empirical()["z"].mean)
    return torch.stack(means), log_ev


@pytest.mark.parametrize("ignore_scans", [False, True], ids=["ours", "scans-ignored"])
def test_smcfilter_and_ours_agree(ignore_scans):
    """Same model, same map, both bootstrap: the weighted means and the log-evidence agree
    within Monte Carlo error; a filter that ignores the scans (sigma 1e6) fails the check."""
    tr = simulate_traversal("simple-small", steps=12, seed=0)
    torch.manual_seed(0)
    grid = MapGrid((9, 9), 1, origin=(0.0, 0.0), size=(0.25, 0.25))
    emission = RayEmission(tr.beam_angles, tr.max_range)
    model = DVBFLM(grid, emission, KinematicTransition((3e-3, 3e-3, 0.02)), sigma_emission=0.05)
    M = RayEmission.wall_map(grid, tr.walls)
    obs = torch.as_tensor(tr.observations)
    ctl = torch.as_tensor(tr.controls, dtype=obs.dtype)
    init = torch.as_tensor(tr.poses[0], dtype=obs.dtype)
    K = 2000
    torch.manual_seed(1)
    smc_means, _ = smc_run(model, M, obs, ctl, init, K)
    sigma = 1e6 if ignore_scans else None
    pf = ParticleFilter(model, Weighting(sigma=sigma), generator=torch.Generator().manual_seed(0))
    ours = pf.run(M, obs, ctl, init, K)
    # the log-evidence of the first 5 steps, where SMCFilter without resampling (sequential
    # importance sampling) still has thousands of effective particles: a sharp reference
    torch.manual_seed(2)
    _, smc_ev = smc_run(model, M, obs[:5], ctl[:4], init, 2 * K, resample=False)
    ours_ev = pf.run(M, obs[:5], ctl[:4], init, 2 * K)["log_evidence"]
    close_means = bool(((smc_means[:, :2] - ours["mean"][:, :2]).norm(dim=-1) < 0.01).all())
    close_ev = abs(smc_ev - ours_ev) < 1.0
    if ignore_scans:
        assert not (close_means and close_ev)
        assert abs(smc_ev - ours_ev) > 100  # the evidence tells at once
    else:
        assert close_means and close_ev, (smc_ev, ours_ev)


def test_predictive_rollouts_of_the_model_under_planned_controls():
    """``DVBFLM.model`` takes a batch of control sequences: one rollout per planned sequence,
    from the same start, through pyro.infer.Predictive."""
    model = toy_model()
    M = torch.randn(model.grid.shape)
    controls = torch.stack([torch.tensor([[0.0, 0.05]] * 3), torch.tensor([[0.5, 0.05]] * 3)])
    init = torch.tensor([0.4, 0.4, 0.0])
    tr = poutine.trace(poutine.condition(model.model, {"map": M})).get_trace(None, controls, init)
    assert tr.nodes["z_3"]["value"].shape == (2, 3) and tr.nodes["x_3"]["value"].shape == (2, B)
    turned = tr.nodes["z_1"]["value"][:, 2] - init[2]
    assert abs(float(turned[1] - turned[0]) - 0.5) < 0.3  # the second sequence turned


def test_slam_runs_with_pyro_smcfilter_as_its_filter():
    """``SLAM(..., smc=True)``: Pyro's SMCFilter filters the SLAM loop on the same model (our
    filter still trains the map) and tracks the pose as ours does; weights it cannot compute
    per particle are refused."""
    from pyro_slam.metrics import localisation_error
    from pyro_slam.slam import SLAM, ConfigError, with_overrides

    tr = simulate_traversal("simple-small", steps=30, seed=0)
    cfg = with_overrides(presets.get("raycast").config, {"filter": {"weighting": "marginal"}})
    errs = {}
    for smc in (False, True):
        slam = SLAM(tr, cfg, seed=1, smc=smc)
        res = slam.run("online", progress=False)
        errs[smc] = float(localisation_error(res["mean"], tr.poses).max())
    assert type(slam.pf).__name__ == "PyroSMCFilter"
    assert errs[True] < 0.03 and errs[False] < 0.03  # corridors are 1/12 wide here
    with pytest.raises(ValueError, match="shared"):
        SLAM(tr, presets.get("raycast").config, smc=True)
    with pytest.raises(ConfigError, match="heading"):
        SLAM(tr, with_overrides(cfg, {"heading": {"sigma": 1e-3}}), smc=True)
