"""A Pyro user's tests: each written with the public API only, as a Pyro user would use the
library -- Pyro's SVI, ELBOs, autoguides, handlers, SMCFilter and Predictive on ``DVBFLM.model``,
with the SLAM run, the planner and the exploration mapper running that same model."""

from __future__ import annotations

import math

import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro import poutine
from pyro.infer import (
    SVI,
    JitTrace_ELBO,
    Predictive,
    Trace_ELBO,
    TraceGraph_ELBO,
    TraceMeanField_ELBO,
)
from pyro.infer.autoguide import (
    AutoDelta,
    AutoGuideList,
    AutoLowRankMultivariateNormal,
    AutoNormal,
)
from pyro.infer.inspect import get_dependencies
from pyro.optim import Adam
from pyro.poutine.messenger import Messenger

from pyro_slam.inference import (
    ChunkBatch,
    EvidenceSMCFilter,
    ParticleFilter,
    Particles,
    ProposalGuide,
    ScanMatchProposal,
    TransitionProposal,
    band_coverage,
    scan_error,
    sequence_guide,
)
from pyro_slam.model import (
    DVBFLM,
    FilterModel,
    KinematicTransition,
    MapBelief,
    MapGrid,
    RayEmission,
    autoguide,
)
from pyro_slam.planning import LearnedEnv, Primitives, learned_env
from pyro_slam.planning.exploration import ExploreConfig, Mapper, mutual_information
from pyro_slam.slam import SLAM, fit_noise, presets
from simulators import make_maze, simulate_traversal


def maze_run(steps=40, preset=None, **kw):
    """A SLAM run on a short traversal of the default maze, not yet run."""
    tr = simulate_traversal("moderate-medium", steps=steps, seed=2)
    return tr, SLAM(tr, preset, seed=1, **kw)


def wall_error(slam) -> float:
    """The map belief's error against the true walls: the ranges its mean predicts at the true
    poses against the noise-free scans there."""
    return scan_error(slam.model, slam.map_belief().loc, slam.tr.poses, slam.obs)


def moving_average(v, n=10):
    return np.convolve(np.asarray(v), np.ones(n) / n, mode="valid")


# ----------------------------------------------------------- SVI on the model trains it
def test_trace_elbo_trains_the_map():
    """``SVI(model.model, slam.sequence_guide(), Adam, Trace_ELBO())`` on the default preset:
    the loss's moving average falls, nothing is NaN, the map belief's error against the true
    walls falls, and only the map's parameters are trained (the shipped transition network is
    not handed to the optimiser)."""
    tr, slam = maze_run(40)
    args = slam.model_inputs()
    with slam.scope():
        before = wall_error(slam)
        svi = SVI(slam.model.model, slam.sequence_guide(), Adam({"lr": 0.05}), Trace_ELBO())
        losses = [svi.step(*args) for _ in range(60)]
        names = set(pyro.get_param_store().keys())
        after = wall_error(slam)
        loc = pyro.param("map_loc")
    assert all(math.isfinite(v) for v in losses) and torch.isfinite(loc).all()
    avg = moving_average(losses)
    assert avg[-1] < 0.8 * avg[0], (avg[0], avg[-1])
    assert after < 0.5 * before, (before, after)  # measured 0.325 -> 0.09
    assert names == {"map_loc", "map_scale"}  # no network: the shipped ones are frozen
    assert not any(p.requires_grad for p in slam.model.transition.parameters())


def test_shipped_networks_learn_only_when_asked():
    """A learned transition is trained by SVI on the model only with ``learn_transition``."""
    tr, slam = maze_run(6)
    m = slam.model
    m.learn_transition = True
    with slam.scope():
        svi = SVI(m.model, slam.sequence_guide(), Adam({"lr": 1e-4}), Trace_ELBO())
        w = next(m.transition.parameters()).detach().clone()
        svi.step(*slam.model_inputs())
        names = list(pyro.get_param_store().keys())
    assert any(n.startswith("transition$$$") for n in names)
    assert not torch.equal(w, next(m.transition.parameters()).detach())


@pytest.mark.parametrize("elbo", [TraceGraph_ELBO, TraceMeanField_ELBO])
def test_other_pyro_elbos_train_the_map(elbo):
    """``TraceGraph_ELBO`` and ``TraceMeanField_ELBO`` (analytic KL for the map) train it too:
    every guide site is reparameterised and the proposals carry no gradient."""
    tr, slam = maze_run(30, "raycast")
    with slam.scope():
        before = wall_error(slam)
        svi = SVI(slam.model.model, slam.sequence_guide(), Adam({"lr": 0.05}), elbo())
        losses = [svi.step(*slam.model_inputs()) for _ in range(40)]
        after = wall_error(slam)
    assert all(math.isfinite(v) for v in losses)
    assert after < 0.6 * before, (before, after)  # measured 0.325 -> 0.15


def test_jit_trace_elbo_on_fixed_arguments():
    """``JitTrace_ELBO`` compiles the model and the SLAM guide for fixed tensor arguments
    where the guide has no data-dependent branch (the paper's bootstrap proposal; the scan
    match's fallback is a branch a trace cannot follow): its loss is Trace_ELBO's on the same
    random numbers, and its SVI steps train."""
    tr, slam = maze_run(8, "paper")
    obs, ctl, init, _, _ = slam.model_inputs()
    guide = slam.sequence_guide()
    with slam.scope():
        pyro.set_rng_seed(3)
        want = Trace_ELBO().loss(slam.model.model, guide, obs, ctl, init)
        pyro.set_rng_seed(3)
        got = JitTrace_ELBO().loss(slam.model.model, guide, obs, ctl, init)
        svi = SVI(slam.model.model, guide, Adam({"lr": 0.05}), JitTrace_ELBO())
        steps = [svi.step(obs, ctl, init) for _ in range(100)]
    assert got == pytest.approx(want, rel=1e-5)
    assert all(math.isfinite(v) for v in steps)
    assert np.mean(steps[-10:]) < 0.6 * np.mean(steps[:10])  # measured 488 -> 160


def test_slam_objective_is_trace_mean_field_elbo_on_the_same_trace():
    """SLAM's own objective (``slam.elbo``, an ELBO subclass) with one particle and one chunk
    over the whole traversal: its value and its gradient (times ``T``) are Pyro's
    ``TraceMeanField_ELBO``'s on the same trace (the same map, frame and poses replayed into the
    SLAM guide)."""
    tr, slam = maze_run(8)
    T, elbo, args = slam.T, slam.elbo, slam.model_inputs()
    elbo.K, elbo.refresh = 1, False
    with slam.scope():
        z0 = slam.init_pose + slam.model.init_scale * torch.randn(1, 1, 3)
        elbo.cache.store(torch.tensor([0]), Particles(z0, torch.zeros(1, 1)))
        recorder = poutine.trace(slam.guide)
        ours = T * elbo.differentiable_loss(
            slam.model.model, recorder, ChunkBatch(torch.tensor([0]), T)
        )
        loc = pyro.param("map_loc").unconstrained()
        (g_ours,) = torch.autograd.grad(ours, loc)
        draws = poutine.trace(slam.sequence_guide()).get_trace(*args)  # a trace to overwrite
        for name in ("map", "frame"):
            draws.nodes[name]["value"] = recorder.trace.nodes[name]["value"]
        for t in range(T):  # the objective's own poses (the cache holds the chunk's particle)
            draws.nodes[f"z_{t}"]["value"] = elbo.cache.z[t, 0]
        guide = poutine.replay(slam.sequence_guide(), trace=draws)
        theirs = TraceMeanField_ELBO().differentiable_loss(slam.model.model, guide, *args)
        (g_theirs,) = torch.autograd.grad(theirs, loc)
    assert float(ours) == pytest.approx(float(theirs), rel=1e-5, abs=1e-3)
    torch.testing.assert_close(g_ours, g_theirs, rtol=1e-4, atol=1e-5)


# ------------------------------------------------------------------- guides over the map
def map_only(cls, **kw):
    """A guide factory: Pyro's autoguide ``cls`` over ``poutine.block(model.model,
    expose=["map"])``, as a Pyro user writes it."""
    return lambda model: cls(poutine.block(model.model, expose=["map"]), **kw)


def test_autonormal_block_idiom():
    """``AutoNormal(poutine.block(model.model, expose=["map"]))``: SLAM runs with it as its map
    guide (scan insertion writes into its locs and scales), and Trace_ELBO on the model with
    the SLAM guide around it trains it."""
    tr, slam = maze_run(40, "raycast", guide=map_only(AutoNormal, init_scale=1.0))
    assert type(slam.map_guide).__name__ == "AutoNormal" and slam.inserter is not None
    res = slam.run("online", progress=False)
    err = np.hypot(*(res["mean"][:, :2] - tr.poses[:, :2]).T)
    assert err.max() < 0.02  # measured 0.004
    with slam.scope():
        assert float(pyro.param("AutoNormal.locs.map").max()) > 1.0  # the inserted walls
    # a fresh one, trained by Pyro's SVI with the SLAM guide around it
    m = slam.model
    auto = AutoNormal(poutine.block(m.model, expose=["map"]), init_scale=1.0)
    with pyro.get_param_store().scope():
        guide = sequence_guide(m, slam.proposal, auto)
        svi = SVI(m.model, guide, Adam({"lr": 0.05}), Trace_ELBO())
        losses = [svi.step(*slam.model_inputs()) for _ in range(40)]
        after = scan_error(m, auto.median(*slam.model_inputs())["map"], tr.poses, slam.obs)
    assert np.mean(losses[-10:]) < np.mean(losses[:10])
    assert after < 0.6 * scan_error(m, torch.zeros(m.grid.shape), tr.poses, slam.obs)


@pytest.mark.parametrize(
    "factory",
    [
        map_only(AutoLowRankMultivariateNormal, init_scale=1.0, rank=4),
        autoguide(AutoNormal, init_scale=1.0),
    ],
    ids=["low-rank", "library-autoguide"],
)
def test_other_map_autoguides_run_slam(factory):
    """A low-rank multivariate normal over the blocked model and the library's ``autoguide``
    factory: SLAM runs with scan insertion into them and tracks the path."""
    tr, slam = maze_run(30, "raycast", guide=factory)
    assert slam.inserter is not None
    res = slam.run("online", progress=False)
    assert np.hypot(*(res["mean"][-1, :2] - tr.poses[-1, :2])) < 0.02


def test_autoguide_list_runs_slam_with_svi_only():
    """``AutoGuideList`` of an ``AutoNormal`` over the blocked model: a guide whose marginal
    SLAM can read (its quantiles) but not write, so SLAM runs with SVI alone, insertion off,
    with the documented warning."""

    def factory(model):
        guide = AutoGuideList(model.model)
        guide.append(AutoNormal(poutine.block(model.model, expose=["map"]), init_scale=1.0))
        return guide

    with pytest.warns(UserWarning, match="scan insertion is off"):
        tr, slam = maze_run(12, "raycast", guide=factory)
    assert slam.inserter is None
    res = slam.run("online", progress=False)
    assert np.isfinite(res["mean"]).all() and len(res["losses"]) > 0


def test_autodelta_map_guide():
    """``autoguide(AutoDelta)``: a point estimate of the map. SLAM runs with SVI alone (no
    marginal std to insert into: insertion off, with the warning); the filter's belief is the
    estimate with zero std, and SVI moves it."""
    with pytest.warns(UserWarning, match="scan insertion is off"):
        tr, slam = maze_run(30, "raycast", guide=autoguide(AutoDelta))
    assert slam.inserter is None
    res = slam.run("online", progress=False)
    belief = slam.map_belief()
    assert torch.equal(belief.scale, torch.zeros_like(belief.scale))
    assert float(belief.loc.abs().max()) > 0  # SVI moved it from its start
    assert np.isfinite(res["mean"]).all() and len(res["losses"]) > 0


# ------------------------------------------------------------------------------ tooling
def test_render_model_has_pose_to_scan_edges():
    """``get_dependencies`` and ``pyro.render_model`` show ``z_t -> x_t`` for every emission
    kind (every simulated preset), and ``z_{t-1} -> z_t``."""
    for name in presets.PRESETS:
        obs = presets.get(name).config.emission.observation
        if name == "real":  # a metric log's end-point emission: tested on a room below
            continue
        tr = simulate_traversal("moderate-medium", steps=4, seed=2, images=obs == "image")
        slam = SLAM(tr, name, seed=1)
        with slam.scope():
            deps = get_dependencies(slam.model.model, slam.model_inputs())["prior_dependencies"]
            graph = pyro.render_model(slam.model.model, model_args=slam.model_inputs())
        for t in range(4):
            assert f"z_{t}" in deps[f"x_{t}"], (name, t, deps[f"x_{t}"])
        assert "z_2" in deps["z_3"]
        assert "z_2 -> x_2" in graph.source, name


def test_predictive_pose_samples():
    """``Predictive`` of the model: the pose sequence (its return value) ``[N, T, 3]``; each
    step's site is Pyro's, padded to the map's two plates ``[N, 1, 1, 3]``."""
    tr, slam = maze_run(5)
    _, ctl, init, _, _ = slam.model_inputs()
    with slam.scope():
        pred = Predictive(
            slam.model.model, guide=slam.guide, num_samples=7, return_sites=["_RETURN", "z_3"]
        )
        s = pred(None, ctl, init)
    assert s["_RETURN"].shape == (7, 5, 3)
    assert s["z_3"].shape == (7, 1, 1, 3)
    torch.testing.assert_close(s["_RETURN"][:, 3], s["z_3"].reshape(7, 3))


def tiny_model(noise=None, sigma=0.05):
    """A ray-cast DVBF-LM on a 9 x 9 grid over a small maze's corner."""
    tr = simulate_traversal("simple-small", steps=12, seed=0)
    grid = MapGrid((9, 9), 1, origin=(0.0, 0.0), size=(0.25, 0.25))
    emission = RayEmission(tr.beam_angles, tr.max_range)
    model = DVBFLM(
        grid, emission, KinematicTransition((3e-3, 3e-3, 0.02)), sigma_emission=sigma, noise=noise
    )
    return tr, model, RayEmission.wall_map(grid, tr.walls)


def test_smcfilter_evidence_with_resampling():
    """``EvidenceSMCFilter`` (Pyro's SMCFilter with the log-evidence) on ``FilterModel``, with
    resampling: over 8 seeds its log-evidence agrees with our filter's within Monte Carlo
    error; the likelihood read at ``state`` after each step (which SMCFilter has resampled) is
    tens of nats off."""
    tr, model, M = tiny_model()
    obs = torch.as_tensor(tr.observations)
    ctl = torch.as_tensor(tr.controls, dtype=obs.dtype)
    init = torch.as_tensor(tr.poses[0], dtype=obs.dtype)
    K, T = 200, obs.shape[0]
    smc, ours, naive = [], [], []
    for seed in range(8):
        pyro.set_rng_seed(seed)
        f = EvidenceSMCFilter(
            FilterModel(model, M),
            ProposalGuide(model, TransitionProposal()),
            K,
            max_plate_nesting=0,
            ess_threshold=0.5,
        )
        after = 0.0
        with torch.no_grad():
            f.init(init_pose=init, x=obs[0])
            for t in range(1, T):
                prev = f.get_empirical()["z"].log_weights.clone()
                f.step(t, obs[t], ctl[t - 1])
                state = f.state["z"]  # the recipe: the step's own likelihood at the state
                ll = model.emission_dist(model.emission_mean(M, state)).log_prob(obs[t])
                after += float(torch.logsumexp(prev - prev.logsumexp(0) + ll, 0))
        smc.append(f.log_evidence)
        naive.append(after)
        pf = ParticleFilter(model, generator=torch.Generator().manual_seed(seed))
        ours.append(pf.run(M, obs, ctl, init, K)["log_evidence"])
    (a, sa), (b, sb) = (np.mean(smc), np.std(smc) / 8**0.5), (np.mean(ours), np.std(ours) / 8**0.5)
    assert abs(a - b) < 4 * math.hypot(sa, sb) + 0.5, (a, sa, b, sb)
    assert abs(np.mean(naive) - np.mean(smc)) > 5  # measured 26 nats


# ------------------------------------------------------------- one model for everything
class WideScans(Messenger):
    """A user's emission written as a handler: the scans' noise a Gaussian of std 0.2 about the
    predicted scan (read from the step's ``scan_t`` site)."""

    def _pyro_post_sample(self, msg):
        if msg["name"].startswith("scan_"):
            self.scan = msg["value"]

    def _pyro_sample(self, msg):
        if msg["name"].startswith("x_"):
            msg["fn"] = dist.Normal(self.scan, 0.2).to_event(1)


def test_handler_reaches_filter_planner_and_mi():
    """Handlers around the model reach everything that runs it: a user's emission handler the
    filter's weights, the planner's rollouts and the MI; ``poutine.scale`` the weights and scan
    insertion; ``poutine.condition`` on the map the filter (it localises on the given map) and
    insertion (nothing to write)."""
    maze = make_maze("moderate-medium", 1)
    tr = simulate_traversal(maze, steps=40, seed=2)
    slam = SLAM(tr, "raycast", seed=1)
    slam.run("online", progress=False)
    pf, p, t = slam.pf, slam.particles, slam.T - 1
    belief = slam.map_belief()

    def weights(handler):
        slam.model.handler = handler
        pf.generator.manual_seed(5)
        pf.ess_threshold = 0.0
        with torch.no_grad():
            new, inc = pf.step(p, belief, slam.obs[t], slam.ctl[t - 1], step=t)
        slam.model.handler = None
        return new.logw + inc - p.logw, new.z, pf.last_trace

    plain, z, trace = weights(None)
    half, z_half, _ = weights(poutine.scale(scale=0.5))
    model_part = sum(  # [K] the model's log-densities of the step (the proposal's is not scaled)
        trace.nodes[n]["log_prob"] for n in (f"z_{t}", f"x_{t}", f"h_{t}") if n in trace.nodes
    )
    assert torch.equal(z, z_half)  # the same proposals ...
    torch.testing.assert_close(half, plain - 0.5 * model_part, rtol=1e-4, atol=1e-3)  # ... halved
    rest = plain - trace.nodes[f"x_{t}"]["log_prob"]  # [K] the step's weight but its emission
    wide, _, trace = weights(WideScans())
    scan = trace.nodes[f"scan_{t}"]["value"]
    want = dist.Normal(scan, 0.2).log_prob(slam.obs[t]).sum(-1)  # [K] the handler's emission
    torch.testing.assert_close(wide, rest + want, rtol=1e-4, atol=1e-3)
    # the planner's rollouts and the MI sample the handled model
    env, _, _ = learned_env(maze, slam=slam)
    start = np.array([[*tr.poses[10, :2], 0.0]])
    prims = Primitives().padded()
    plain_scans = env._rollout(start, prims)[2]
    slam.model.handler = WideScans()
    wide_scans = env._rollout(start, prims)[2]
    assert float(wide_scans.std(2).mean()) > 2 * float(plain_scans.std(2).mean())
    cfg = ExploreConfig.smoke(mi={"L": 16, "M": 4, "K": 16, "obs_stride": 5})
    east = torch.tensor([[0.0, 0.02]] * 9)
    pyro.set_rng_seed(0)
    mi_wide = mutual_information(Mapper.from_slam(slam, cfg), east, tr.poses[20], cfg)
    slam.model.handler = None
    pyro.set_rng_seed(0)
    mi_plain = mutual_information(Mapper.from_slam(slam, cfg), east, tr.poses[20], cfg)
    assert mi_wide < mi_plain - 1.0


def test_handlers_reach_scan_insertion():
    """A SLAM run under ``poutine.scale(scale=0.5)`` inserts each reading with half its
    precision (a wider map belief where scans were written); under ``poutine.condition`` on the
    map (the true walls) it localises on that map and writes nothing into the guide."""
    tr = simulate_traversal("moderate-medium", steps=30, seed=2)
    cfg = presets.get("raycast").config
    runs = {}
    for name, handler in (("plain", None), ("half", poutine.scale(scale=0.5))):
        slam = SLAM(tr, cfg, seed=1, handler=handler)
        slam.run("online", progress=False)
        runs[name] = slam
    written = runs["plain"].inserter.inserted
    s_plain = runs["plain"].map_belief().scale[..., 0][written]
    s_half = runs["half"].map_belief().scale[..., 0][written]
    assert float(s_half.median()) > 1.2 * float(s_plain.median())
    walls = RayEmission.wall_map(runs["plain"].model.grid, tr.walls)
    known = SLAM(tr, cfg, seed=1, handler=poutine.condition(data={"map": walls}))
    res = known.run("online", progress=False)
    assert torch.equal(known.map_belief().loc, torch.zeros_like(walls))  # nothing written
    assert np.hypot(*(res["mean"][:, :2] - tr.poses[:, :2]).T).max() < 0.01


def test_planner_uses_model_transition():
    """The planner's rollouts are draws of the model's own transition with its noise: a
    transition twice as noisy spreads the draws twice as wide, and one that moves half as far
    forward halves the successors' travel."""
    maze = make_maze("simple-medium", 3)
    env, _, _ = learned_env(maze, steps=300, fit_steps=50)
    prims = Primitives().padded()
    start = np.array([[0.25, 0.25, 0.0]])
    model = env.model

    def spread_and_travel():
        env._memos.clear()
        _, travel, _, _ = env.rollout(start, prims)
        L = prims.shape[1]
        init = torch.as_tensor(start, dtype=prims.dtype)[:, None]
        with torch.no_grad(), pyro.plate("draws", 64, dim=-3):
            tr = poutine.trace(poutine.condition(model.model, {"map": env.M})).get_trace(
                None, prims, init
            )
        return float(tr.nodes[f"z_{L}"]["value"][..., :2].std(0).mean()), float(travel.mean())

    s1, d1 = spread_and_travel()
    model.transition.sigma.mul_(2.0)
    s2, _ = spread_and_travel()
    model.transition.sigma.div_(2.0)
    assert 1.6 < s2 / s1 < 2.4
    env_half = LearnedEnv(model, env.M, samples=env.samples)
    base = model.transition.mean
    model.transition.mean = lambda z, u, scan=None: base(z, u * torch.tensor([1.0, 0.5]), scan)
    _, travel, _, _ = env_half.rollout(start, prims)
    model.transition.mean = base
    assert float(travel.mean()) == pytest.approx(0.5 * d1, rel=0.15)


def test_mi_uses_slam_model():
    """MI on a SLAM run (``Mapper.from_slam``) is the run's own predictive: its map belief's
    draws and its emission noise; the same controls carry less information under a noisier
    emission, and the mapper's maps are the run's guide's."""
    maze = make_maze("moderate-medium", 1)
    tr = simulate_traversal(maze, steps=30, seed=2)
    slam = SLAM(tr, "raycast", seed=1)
    slam.run("online", progress=False)
    cfg = ExploreConfig.smoke(mi={"L": 16, "M": 4, "K": 16, "obs_stride": 5})
    mapper = Mapper.from_slam(slam, cfg)
    assert mapper.model is slam.model and mapper.guide is slam.map_guide
    torch.testing.assert_close(mapper.marginals()[0], slam.map_belief().loc)
    east = torch.tensor([[0.0, 0.02]] * 9)
    pyro.set_rng_seed(0)
    mi = mutual_information(mapper, east, tr.poses[20], cfg)
    slam.model.sigma_emission *= 4
    pyro.set_rng_seed(0)
    noisy = mutual_information(mapper, east, tr.poses[20], cfg)
    assert noisy < mi - 0.1, (mi, noisy)


def test_predictive_band_coverage():
    """The model's predictive band is calibrated once its noise is fitted to the traversal by
    the ELBO (``fit_noise``, at the SLAM run's poses and its map belief's mean): the 10-90 %
    band of ``Predictive``'s scans covers 70-90 % of the observed beams; with the preset's
    sigma_E of 0.05 and 10 % outliers it covers nearly all of them."""
    tr = simulate_traversal("moderate-medium", steps=100, seed=2)
    slam = SLAM(tr, seed=1)
    res = slam.run("online", progress=False)
    M = slam.map_belief().loc
    m = slam.model
    wide = band_coverage(m, M, res["mean"], slam.obs, slam.ctl, slam.mask)
    sigma, eps = fit_noise(slam.tr, m, M, res["mean"])
    fitted = band_coverage(m, M, res["mean"], slam.obs, slam.ctl, slam.mask)
    assert sigma < 0.05 and 0.7 <= fitted <= 0.9, (sigma, eps, fitted)
    assert wide > 0.95


def test_scan_match_scores_with_the_model_noise_family():
    """The scan-matching proposal's match weighs each reading by the model's own noise family:
    with Student-t noise its proposal differs from the Gaussian model's (a far reading weighs
    less), with the same transition."""
    tr, gauss, M = tiny_model()
    _, student, _ = tiny_model(noise=lambda loc, scale: dist.StudentT(2.0, loc, scale))
    z = torch.as_tensor(tr.poses[4], dtype=torch.float32).expand(16, 3)
    x = torch.as_tensor(tr.observations[5], dtype=torch.float32).clone()
    x[0] = 0.01  # one wild reading
    u = torch.as_tensor(tr.controls[4], dtype=torch.float32)
    qs = [
        ScanMatchProposal().dist(m, z, None, u, x=x, M=MapBelief(M, torch.full_like(M, 0.1)))
        for m in (gauss, student)
    ]
    assert float((qs[0].mu - qs[1].mu).abs().max()) > 1e-5
