"""One model for everything: the training objective is the model's ELBO, a swapped prior or
emission noise reaches the filter, the fitted map and the planner, and Pyro's own SMCFilter on
the same model agrees with our filter, log-evidence included."""

from __future__ import annotations

import copy
import dataclasses
import functools
import math

import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro import poutine
from pyro.infer import Trace_ELBO
from pyro.infer.autoguide import AutoNormal
from synthetic_logs import room_log

from pyro_slam.inference import (
    ChunkBatch,
    EvidenceSMCFilter,
    ParticleFilter,
    Particles,
    ProposalGuide,
    TransitionProposal,
)
from pyro_slam.io import odometry_poses
from pyro_slam.model import (
    DVBFLM,
    EmissionMLP,
    FilterModel,
    KinematicTransition,
    MapBelief,
    MapGrid,
    MapGuide,
    RayEmission,
    WrappedMixture,
)
from pyro_slam.model.guide import MapLeaves, autoguide
from pyro_slam.planning import LearnedEnv, learned_env, plan
from pyro_slam.planning.exploration import ExploreConfig, Mapper, mutual_information
from pyro_slam.slam import SLAM, fit_map, presets, with_overrides
from simulators import make_maze, simulate_traversal

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


def slam_objective(slam, n: int, seed: int = 3) -> list[float]:
    """``n`` draws of SLAM's own training loss (``slam.elbo``, the one SLAM builds) times ``T``,
    on one chunk over the whole traversal with one particle, the start particles from the pose
    prior."""
    elbo, T = slam.elbo, slam.T
    g = torch.Generator().manual_seed(seed)
    N = slam.cache.num_particles
    z0 = slam.init_pose + slam.model.init_scale * torch.randn(N, 3, generator=g)
    elbo.K, elbo.refresh = 1, False
    batch = ChunkBatch(torch.tensor([0]), T)
    out = []
    with slam.scope():
        for _ in range(n):
            slam.cache.store(
                torch.tensor([0]), Particles(z0[None], torch.full((1, N), -math.log(N)))
            )
            out.append(T * elbo.loss(slam.model.model, slam.guide, batch))
    return out


def preset_traversal(preset: str, steps: int = 6):
    """A short traversal for ``preset``: camera frames for the visual ones, a metric log (a
    room) for ``real``."""
    if preset == "real":
        return room_log(T=steps)[0]
    image = presets.get(preset).config.emission.observation == "image"
    return simulate_traversal("moderate-medium", steps=steps, seed=2, images=image)


@pytest.mark.parametrize("preset", list(presets.PRESETS))
def test_default_objective_is_trace_elbo(preset):
    """At each preset's defaults, SLAM's own objective (``slam.elbo``, one particle) equals
    Pyro's ``Trace_ELBO`` on ``DVBFLM.model`` with the SLAM guide (map guide, frame guide with
    the heading factor, and the filter's proposal for the poses) within 4 Monte Carlo standard
    errors; and the test tells a model with another emission noise apart."""
    tr = preset_traversal(preset)
    slam = SLAM(tr, presets.get(preset).for_traversal(tr), seed=1)
    if slam.heading is not None:  # the heading factor takes part: a frame and seen walls
        assert not math.isnan(slam.heading.frame.mean)
        assert bool(slam.heading.ok[1:].any())
    if slam.inserter is not None:  # the map SLAM's objective sees: the scans inserted, at the
        true = slam.tr.poses if slam.tr.poses is not None else odometry_poses(slam.tr)  # truth
        poses = torch.as_tensor(np.asarray(true), dtype=slam.obs.dtype)
        with torch.no_grad(), slam.scope():
            for t in range(slam.T):
                slam.inserter.insert(slam.obs[t], slam.valid(t), poses[t], 0.0)
    n = 200
    ours = slam_objective(slam, n)
    theirs = trace_elbo_draws(slam, n)
    (m1, s1), (m2, s2) = mean_and_se(ours), mean_and_se(theirs)
    assert abs(m1 - m2) < 4 * math.hypot(s1, s2), (m1, s1, m2, s2)
    # another emission noise (twice sigma_E) is told apart, on the same random numbers
    slam.model.sigma_emission *= 2
    other = trace_elbo_draws(slam, n)
    m3, s3 = mean_and_se([b - a for a, b in zip(theirs, other)])
    assert abs(m3) > 4 * s3, (m3, s3)


def chunk_evidence_draws(slam, M, frame, n: int, seed: int = 3) -> list[float]:
    """``n`` draws of the log-evidence SLAM's training objective estimates for a chunk of the
    whole (short) traversal under the map ``M`` and the frame ``frame``, at SLAM's own particle
    count, the chunk's start particles from the cache filled from the pose prior."""
    elbo, T = slam.elbo, slam.T
    g = torch.Generator().manual_seed(seed)
    N = slam.cache.num_particles
    z0 = slam.init_pose + slam.model.init_scale * torch.randn(N, 3, generator=g)
    prior = Particles(z0[None], torch.full((1, N), -math.log(N)))
    batch = ChunkBatch(torch.zeros(n, dtype=torch.long), T)  # n chunks, each the traversal
    with slam.scope(), torch.no_grad():
        slam.cache.store(torch.tensor([0]), prior)
        return elbo.chunk_log_evidence(M, batch, frame).tolist()


def iwae_draws(slam, M, frame, n: int, K: int, seed: int = 5) -> list[float]:
    """``n`` draws of Pyro's importance-weighted bound with ``K`` particles on ``DVBFLM.model``
    with the SLAM guide, both conditioned on the map ``M`` and the frame ``frame``: ``log
    mean_k p(x, z_k | M, phi) / q(z_k)`` from Pyro's traces of the model's own sites."""
    fixed = {"map": M} if frame is None else {"map": M, "frame": frame}
    model = poutine.condition(slam.model.model, fixed)
    guide = poutine.condition(slam.sequence_guide(), fixed)
    args = slam.model_inputs()
    pyro.set_rng_seed(seed)

    def local(tr):  # the poses, scans and wall directions: not the fixed globals
        tr.compute_log_prob()
        return sum(
            s["log_prob"].sum()
            for k, s in tr.nodes.items()
            if s["type"] == "sample" and k not in fixed
        )

    out = []
    with slam.scope(), torch.no_grad():
        for _ in range(n):
            logw = []
            for _ in range(K):
                g = poutine.trace(guide).get_trace(*args)
                m = poutine.trace(poutine.replay(model, trace=g)).get_trace(*args)
                logw.append(local(m) - local(g))
            out.append(float(torch.logsumexp(torch.stack(logw), 0) - math.log(K)))
    return out


def test_objective_detects_tempering():
    """At SLAM's own configuration (the default preset's particles per chunk, a chunk of its
    length), the log-evidence SLAM's training objective estimates under a map drawn from
    ``q(M)`` agrees with Pyro's importance-weighted bound with as many particles on
    ``DVBFLM.model`` (the model's own sites, traced by Pyro) within Monte Carlo error plus the
    two bounds' gap (2 nats; measured 170.0 against 170.2); the filter's likelihood tempered
    x0.8, or its sigma_E raised x1.25, moves SLAM's figure by tens of nats (measured 139.2 and
    154.5)."""
    cfg = presets.get("manhattan").config
    tr = simulate_traversal("moderate-medium", steps=cfg.training.chunk_length, seed=2)
    slam = SLAM(tr, cfg, seed=1)
    slam.run("online", progress=False)  # scans inserted: a map with walls
    with slam.scope(), torch.no_grad():
        M, frame = slam.guide()
    n, K = 40, cfg.training.particles
    (m1, s1) = mean_and_se(chunk_evidence_draws(slam, M, frame, n))
    (m2, s2) = mean_and_se(iwae_draws(slam, M, frame, n, K))
    assert abs(m1 - m2) < 2.0 + 4 * math.hypot(s1, s2), (m1, s1, m2, s2)


def trace_elbo_draws(slam, n: int, seed: int = 5) -> list[float]:
    """``n`` draws of Pyro's ``Trace_ELBO`` loss of ``DVBFLM.model`` with the SLAM guide, from
    the random seed ``seed``."""
    trace, args = Trace_ELBO(), slam.model_inputs()
    pyro.set_rng_seed(seed)
    with slam.scope():
        return [trace.loss(slam.model.model, slam.sequence_guide(), *args) for _ in range(n)]


def test_swapped_prior_reaches_filter_and_planner():
    """A map prior N(0, 2^2): the filter's marginal emission compares the belief's variance
    with 4, not 1; a fitted map stays at the prior where no scan reaches; the planner counts a
    cell as explored by its std relative to the prior's."""
    wide = dist.Normal(torch.zeros(3), 2.0 * torch.ones(3)).to_event(1)
    std_model, wide_model = toy_model(), toy_model(prior=wide)
    loc = torch.zeros(std_model.grid.shape)
    scale = torch.full(std_model.grid.shape, 1.0)
    z = torch.tensor([[0.5, 0.4, 0.0]])
    belief = MapBelief(loc, scale)
    # theory: the reading is unknown with probability var(q) / var(prior) at a chart whose four
    # cells have std 1 (the model's outlier probability is 0 here)
    assert torch.allclose(std_model.marginal_emission(belief, z)[1], torch.tensor([[1.0]]))
    assert torch.allclose(wide_model.marginal_emission(belief, z)[1], torch.tensor([[1 / 4]]))
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
    model.sigma_emission = 0.07
    pf = ParticleFilter(model)
    p, inc = pf.init(z0, M, x)
    scan = model.emission_mean(M, z0)
    expected = dist.StudentT(3.0, scan, 0.07).log_prob(x).sum(-1)  # [64]
    torch.testing.assert_close(p.logw, expected - torch.logsumexp(expected, 0), atol=1e-5, rtol=0)
    torch.testing.assert_close(inc, torch.logsumexp(expected, 0) - math.log(64))
    gauss = dist.Normal(scan, 0.07).log_prob(x).sum(-1)
    assert (p.logw - (gauss - torch.logsumexp(gauss, 0))).abs().max() > 0.1  # not Gaussian


def smc_run(model, M, obs, ctl, init, K, resample=True):
    """Pyro's SMCFilter (:class:`EvidenceSMCFilter`) on ``FilterModel``: weighted means
    ``[T, 3]`` and the log-evidence."""
    guide = ProposalGuide(model, TransitionProposal())
    smc = EvidenceSMCFilter(
        FilterModel(model, M),
        guide,
        K,
        max_plate_nesting=0,
        ess_threshold=0.5 if resample else 1e-12,
    )
    means = []
    with torch.no_grad():
        for t in range(obs.shape[0]):
            if t == 0:
                smc.init(init_pose=init, x=obs[0])
            else:
                smc.step(t, obs[t], ctl[t - 1])
            means.append(smc.get_empirical()["z"].mean)
    return torch.stack(means), smc.log_evidence


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
    ours_model = copy.copy(model)
    if ignore_scans:
        ours_model.sigma_emission = 1e6
    pf = ParticleFilter(ours_model, generator=torch.Generator().manual_seed(0))
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


def _read_marginal(model, belief, z, x=None):
    """The stated marginalisation, written out: the reading at the belief's mean (given the
    scan ``x`` where the emission reads it) and its chance of being unknown, ``1 - (1 - eps)(1
    - v)``."""
    rel = belief.scale / model.prior_std()
    mean, v = model.emission.read_moments(model.grid, belief.loc, rel, z, x=x)
    return mean, 1 - (1 - model.outlier_prob) * (1 - v.clamp(0, 1))


@pytest.mark.parametrize("proposal", ["transition", "scan-match"])
def test_filter_weights_are_model_likelihood(proposal):
    """On fixed particles and a fixed map belief, the filter's incremental log-weights equal
    the model's log p(x_t | z_t, M) under the stated marginalisation over q(M), plus the heading
    factor's log-density, plus the proposal's correction log p(z_t | z_t-1) - log q(z_t); under
    a map (no belief) the scan's part is exactly the model's emission."""
    tr = simulate_traversal("moderate-medium", steps=40, seed=2)
    cfg = presets.get("manhattan").config
    slam = SLAM(tr, with_overrides(cfg, {"filter": {"proposal": proposal}}), seed=1)
    slam.run("online", progress=False)
    model, pf, belief = slam.model, slam.pf, slam.map_belief()
    pf.ess_threshold = 0.0  # no resampling: the increments are the weights' changes
    t = 39
    g = torch.Generator().manual_seed(0)
    K = 64
    z_prev = torch.as_tensor(tr.poses[t - 1], dtype=torch.float32) + 0.005 * torch.randn(
        K, 3, generator=g
    )
    logw = torch.log_softmax(torch.randn(K, generator=g), 0)
    scan_prev = model.emission_mean(belief.loc, z_prev)
    p = Particles(z_prev, logw, scan_prev)
    x, u, h = slam.obs[t], slam.ctl[t - 1], slam.heading.evidence().at(t)
    assert bool(h.seen()), "the step must carry heading evidence"
    pf.generator.manual_seed(5)
    new, inc = pf.step(p, belief, x, u, step=t, heading=h)
    got = new.logw + inc - logw  # [K] the incremental log-weights
    z = new.z
    mean, eps = _read_marginal(model, belief, z)
    scan_ll = model.emission_dist(mean, outlier_prob=eps).log_prob(x)  # [K]
    frame, std = h.frame, math.sqrt(float(h.sigma) ** 2 + h.frame_var)
    head_ll = WrappedMixture(
        frame - z[:, 2], std, math.pi / 2, model.heading.outlier_prob
    ).log_prob(h.direction)
    q = slam.proposal.dist(
        model, z_prev, scan_prev, u.unsqueeze(-2), x=x, M=belief, heading=h.per_particle()
    )
    trans = model.transition_dist(z_prev, u.unsqueeze(-2), scan_prev)
    correction = trans.log_prob(z) - q.log_prob(z)
    torch.testing.assert_close(got, scan_ll + head_ll + correction, atol=2e-3, rtol=1e-4)
    assert correction.abs().max() > 0.1  # the proposal is not the transition
    # under a map, the scan's part is the model's emission exactly
    M = belief.loc
    ll, scan = pf.log_likelihood(z, M, x)
    torch.testing.assert_close(ll, model.emission_dist(model.emission_mean(M, z)).log_prob(x))


def test_two_slam_objects_keep_their_maps():
    """Each SLAM run keeps its parameters in a store of its own: building and running a second
    one leaves the first one's map belief as it was, bit for bit, and the caller's own Pyro
    parameters survive both."""
    pyro.clear_param_store()
    mine = pyro.param("users_own", torch.tensor(3.0))
    tr1 = simulate_traversal("simple-small", steps=30, seed=0)
    tr2 = simulate_traversal("simple-small", steps=30, seed=1)
    a = SLAM(tr1, presets.get("raycast").config, seed=1)
    a.run("online", progress=False)
    before = a.map_belief()
    b = SLAM(tr2, presets.get("raycast").config, seed=2)
    b.run("online", progress=False)
    after = a.map_belief()
    assert torch.equal(before.loc, after.loc) and torch.equal(before.scale, after.scale)
    assert not torch.equal(b.map_belief().loc, after.loc)
    assert list(pyro.get_param_store().keys()) == ["users_own"]
    assert pyro.param("users_own") is mine


def _expected_increments(slam, prev: Particles, z, M, t):
    """The model's log-likelihood of step ``t`` at poses ``z [K, 3]`` under the map ``M`` or
    the belief ``M`` (the stated marginalisation), plus the heading factor's, plus the
    proposal's correction from the parents ``prev``: ``[K]``."""
    model, x, u = slam.model, slam.obs[t], slam.ctl[t - 1]
    mask = None if slam.mask is None else slam.mask[t]
    if isinstance(M, MapBelief):
        mean, eps = _read_marginal(model, M, z, x)
        ll = model.emission_dist(mean, mask, outlier_prob=eps).log_prob(x)
    else:
        ll = model.emission_dist(model.emission_mean(M, z, x), mask).log_prob(x)
    h = None if slam.heading is None else slam.heading.evidence().at(t)
    if h is not None:
        ll = ll + model.heading_log_prob(z[:, 2], h)
    q = slam.proposal.dist(
        model,
        prev.z,
        prev.scan,
        u.unsqueeze(-2),
        x=x,
        mask=mask,
        M=M,
        heading=None if h is None else h.per_particle(),
    )
    trans = model.transition_dist(prev.z, u.unsqueeze(-2), prev.scan)
    return ll + trans.log_prob(z) - q.log_prob(z)


@pytest.mark.parametrize("preset", list(presets.PRESETS))
def test_pyro_smcfilter_runs_every_preset(preset):
    """Pyro's SMCFilter drop-in (``SLAM(..., smc=True)``) runs every preset with its proposal:
    over a short run its posterior means agree with our filter's; and one of its steps weighs
    each particle by the model's likelihood of the scan (and heading) -- under the map belief
    through the stated marginalisation, under a map exactly -- plus the proposal's correction,
    as our filter does (up to the normaliser)."""
    tr = preset_traversal(preset, steps=24)
    cfg = presets.get(preset).for_traversal(tr)
    means = {}
    for smc in (False, True):
        slam = SLAM(tr, cfg, seed=1, smc=smc)
        means[smc] = slam.run("online", progress=False)["mean"]
    assert type(slam.pf).__name__ == "PyroSMCFilter"
    gap = np.hypot(*(means[True][:, :2] - means[False][:, :2]).T).max()
    scale = 1.0 if preset == "real" else 0.01  # metres, maze units
    assert gap < scale, gap  # measured <= 0.004 (mazes)
    pf, t = slam.pf, slam.T - 1
    belief = slam.map_belief()
    pf.smc.ess_threshold = 1e-9  # one more step without resampling
    for M in (belief, belief.loc):
        prev = pf._particles()
        h = None if slam.heading is None else slam.heading.evidence().at(t)
        with torch.no_grad():
            m = None if slam.mask is None else slam.mask[t]
            new, _ = pf.step(prev, M, slam.obs[t], slam.ctl[t - 1], m, heading=h)
            want = _expected_increments(slam, prev, new.z, M, t)
        diff = new.logw - prev.logw - want
        assert float((diff - diff.mean()).abs().max()) < 2e-3
    assert float(want.std()) > 0.1  # under the map, the scan counts


def test_swaps_reach_navigation_and_mi():
    """A map prior of variance 4 and a Student-t emission noise change what navigation and
    exploration compute, as theory says: under the wider prior the fitted map shrinks less
    towards the prior mean (larger |loc|, so other predicted scans) and the MI of a path into
    unexplored space is larger (the maps it may reveal vary more); under Student-t noise the
    fitted map resists corrupted scans (robust regression) and the MI is lower (noisier
    readings carry less about the map). The infogain reads the model's prior."""
    maze = make_maze("simple-medium", 3)
    tr = simulate_traversal(maze, steps=400, seed=1)
    wide = dist.Normal(torch.zeros(10), 2.0 * torch.ones(10)).to_event(1)
    student = functools.partial(dist.StudentT, 2.0)
    _, (loc1, _), _ = learned_env(maze, tr, fit_steps=300)
    env4, (loc4, _), _ = learned_env(maze, tr, fit_steps=300, prior=wide)
    assert float(loc4.abs().mean()) > 1.5 * float(loc1.abs().mean())  # measured 2.0x
    z = torch.as_tensor(tr.poses[::20], dtype=torch.float32)
    assert float((env4.scan(z) - LearnedEnv(env4.model, loc1).scan(z)).abs().mean()) > 0.005
    g = np.random.default_rng(0)
    bad = tr.observations.copy()
    hit = g.random(bad.shape) < 0.2
    bad[hit] = g.uniform(0, tr.max_range, hit.sum())
    corrupted = dataclasses.replace(tr, observations=bad)
    Z, clean = (torch.as_tensor(a, dtype=torch.float32) for a in (tr.poses, tr.observations))
    errs = {}
    for name, noise in (("normal", None), ("student", student)):
        env, _, _ = learned_env(maze, corrupted, fit_steps=300, noise=noise)
        errs[name] = float((env.scan(Z) - clean).abs().mean())
    assert errs["student"] < 0.92 * errs["normal"]  # measured 0.036 against 0.041
    # exploration: the MI of a path east into unexplored space, three mapper seeds each
    cfg = ExploreConfig.smoke(
        mi={"L": 30, "M": 8, "K": 30, "obs_stride": 5},
        plan={"horizon": 30},
        mapping={"sigma_E": 0.05},
    )
    grid = MapGrid((8, 8), cfg.mapping.map_dim, (0.0, 0.0), (1.0, 1.0))
    beams = 2 * np.pi * np.arange(20) / 20
    east = torch.tensor([[0.0, 0.02]] * 29)
    mi = {}
    for name, kw in (("std", {}), ("wide", {"prior": wide}), ("student", {"noise": student})):
        runs = []
        for seed in range(3):
            m = Mapper.new(grid, beams, 0.53, dataclasses.replace(cfg, seed=seed), **kw)
            runs.append(mutual_information(m, east, [0.25, 0.5, 0.0], cfg))
        mi[name] = runs
    assert min(mi["wide"]) > max(mi["std"]) + 5  # measured ~91 against ~77 nats
    assert max(mi["student"]) < min(mi["std"]) - 20  # measured ~29
    # infogain = KL(q(M) || p(M)) against the model's prior: 0 at the prior, whatever it is;
    # q = N(0, 1) everywhere against N(0, 4): log 2 + 1/8 - 1/2 per entry
    m = Mapper.new(grid, beams, 0.53, cfg, prior=wide)
    assert m.infogain() == pytest.approx(0.0, abs=1e-6)
    with m.scope():
        leaves = MapLeaves.of(m.guide, grid.shape)
    with torch.no_grad():
        leaves.raw.fill_(float(leaves.transform.inv(torch.tensor(1.0))))
    per_entry = math.log(2.0) + 1 / 8 - 1 / 2
    assert m.infogain() == pytest.approx(per_entry * grid.cells[0] * grid.cells[1] * 10, rel=1e-4)


def test_an_autonormal_map_guide_runs_through_slam_navigation_and_mi():
    """Pyro's ``AutoNormal`` over the map site, with the default preset: SLAM runs with it (scan
    insertion writes into its ``locs``/``scales``), navigation plans in the map it fitted, and
    the exploration mapper trains it and estimates MI."""
    maze = make_maze("simple-medium", 3)
    tr = simulate_traversal(maze, steps=400, seed=1)
    guide = autoguide(AutoNormal, init_scale=1.0)
    slam = SLAM(tr, guide=guide, seed=1)
    assert type(slam.map_guide).__name__ == "AutoNormal" and slam.inserter is not None
    res = slam.run("online", progress=False)
    err = np.hypot(*(res["mean"][:, :2] - tr.poses[:, :2]).T)
    assert err.max() < 0.05 and err.mean() < 0.03  # measured 0.032 and 0.016
    with slam.scope():
        written = dict(pyro.get_param_store().named_parameters())["AutoNormal.locs.map"]
    assert float(written.detach().max()) > 1.0  # the inserted walls
    env, (loc, scale), _ = learned_env(maze, slam=slam)
    torch.testing.assert_close(loc, slam.map_belief().loc)
    for a, b in ((10, 200), (100, 300)):
        r = plan(env, np.array([*tr.poses[a, :2], 0.0]), tr.poses[b, :2], max_expansions=2000)
        assert r.success
    env2, _, _ = learned_env(maze, tr, fit_steps=50, guide=guide)
    assert env2.scan(torch.as_tensor(tr.poses[:3], dtype=torch.float32)).shape == (3, 20)
    cfg = ExploreConfig.smoke(mi={"L": 10, "M": 4, "K": 10, "obs_stride": 5}, plan={"horizon": 10})
    grid = MapGrid((8, 8), cfg.mapping.map_dim, (0.0, 0.0), (1.0, 1.0))
    m = Mapper.new(grid, 2 * np.pi * np.arange(20) / 20, 0.53, cfg, guide=guide)
    m.add(tr.poses[:50] / 0.5, tr.observations[:50])
    losses = m.train(5)
    assert all(math.isfinite(v) for v in losses) and math.isfinite(m.infogain())
    assert math.isfinite(
        mutual_information(m, torch.tensor([[0.0, 0.02]] * 9), [0.5, 0.5, 0.0], cfg)
    )
