"""The DVBF-LM model: Pyro trace structure, bilinear chart, scan rotation, gradients of the
particle ELBO, and inference with Predictive / poutine / SMCFilter."""

from __future__ import annotations

import math

import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro import poutine
from pyro.infer import SVI, Predictive, SMCFilter
from pyro.optim import Adam

from pyro_slam.geometry import interleave
from pyro_slam.inference import (
    ChunkBatch,
    ParticleCache,
    ParticleChunkELBO,
    ParticleFilter,
    Particles,
    ProposalGuide,
    TransitionProposal,
)
from pyro_slam.model import (
    DVBFLM,
    EmissionMLP,
    FilterModel,
    KinematicTransition,
    MapGrid,
    MapGuide,
    rotate_scan,
)
from pyro_slam.model.emissions import RayEmission
from pyro_slam.model.networks import Softsign
from pyro_slam.slam import EmissionConfig, SLAMConfig, build_model
from simulators import simulate_traversal

B = 8  # beams


def tiny_model(n_world=B, cells=(5, 4), dim=3, seed=0):
    torch.manual_seed(seed)
    grid = MapGrid(cells, dim, origin=(-0.5, 1.0), size=(2.0, 1.5))
    emission = EmissionMLP(dim, n_world, hidden=16, layers=2, scale=0.5)
    transition = KinematicTransition((0.01, 0.01, 0.02))
    angles = 2 * math.pi * torch.arange(B) / B
    return DVBFLM(grid, emission, transition, angles, sigma_emission=0.1)


def toy_data(T=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    obs = 0.3 + 0.1 * torch.rand(T, B, generator=g)
    ctl = torch.stack([0.1 * torch.randn(T - 1, generator=g), torch.full((T - 1,), 0.05)], -1)
    return obs, ctl, torch.tensor([0.2, 1.5, 0.3])


# --------------------------------------------------------------------------- trace structure
def test_model_trace_shapes_and_log_density():
    m = tiny_model()
    obs, ctl, init = toy_data()
    T = obs.shape[0]
    tr = poutine.trace(m.model).get_trace(obs, ctl, init)
    site = tr.nodes["map"]
    assert site["value"].shape == (5, 4, 3)
    assert site["fn"].batch_shape == (5, 4) and site["fn"].event_shape == (3,)
    frames = {f.name: (f.dim, f.size) for f in site["cond_indep_stack"]}
    assert frames == {"map_x": (-2, 5), "map_y": (-1, 4)}
    assert [n for n in tr.nodes if n.startswith("z_")] == [f"z_{t}" for t in range(T)]
    for t in range(T):
        z, x = tr.nodes[f"z_{t}"], tr.nodes[f"x_{t}"]
        assert z["value"].shape == (3,) and not z["is_observed"] and z["cond_indep_stack"] == ()
        assert x["is_observed"] and x["fn"].event_shape == (B,) and x["fn"].batch_shape == ()
        assert torch.equal(x["value"], obs[t])
    poses = tr.nodes["_RETURN"]["value"]
    assert poses.shape == (T, 3)
    assert torch.equal(poses, torch.stack([tr.nodes[f"z_{t}"]["value"] for t in range(T)]))
    # the trace density is the sum of the factors written out by hand
    M = site["value"]
    expected = dist.Normal(0.0, 1.0).log_prob(M).sum()
    expected += dist.Normal(init, m.init_scale).log_prob(poses[0]).sum()
    for t in range(T):
        if t:
            prev = poses[t - 1]
            loc = m.transition.mean(prev, ctl[t - 1], m.emission_mean(M, prev))
            expected += dist.Normal(loc, m.transition.sigma).log_prob(poses[t]).sum()
        expected += m.emission_log_prob(obs[t], m.emission_mean(M, poses[t]))
    torch.testing.assert_close(tr.log_prob_sum(), expected)


def test_model_samples_observations_and_respects_mask():
    m = tiny_model()
    obs, ctl, init = toy_data()
    tr = poutine.trace(m.model).get_trace(None, ctl, init)
    assert all(tr.nodes[f"x_{t}"]["value"].shape == (B,) for t in range(5))
    assert not any(tr.nodes[f"x_{t}"]["is_observed"] for t in range(5))
    mask = torch.ones(5, B, dtype=torch.bool)
    mask[2, :3] = False
    tr = poutine.trace(m.model).get_trace(obs, ctl, init, mask)
    x2 = tr.nodes["x_2"]
    mean = m.emission_mean(tr.nodes["map"]["value"], tr.nodes["z_2"]["value"])
    full = dist.Normal(mean, 0.1).log_prob(obs[2])
    torch.testing.assert_close(x2["fn"].log_prob(obs[2]), full[3:].sum())
    torch.testing.assert_close(m.emission_log_prob(obs[2], mean, mask[2]), full[3:].sum())


def test_time_loop_is_first_order_markov():
    m = tiny_model()
    obs, ctl, init = toy_data(T=4)
    tr = poutine.trace(m.model).get_trace(obs, ctl, init)
    # the global map is sampled before the time loop; the initial pose opens it, seeing nothing
    assert "_markov_scope" not in tr.nodes["map"]["infer"]
    assert set(tr.nodes["z_0"]["infer"]["_markov_scope"]) == set()
    assert set(tr.nodes["x_0"]["infer"]["_markov_scope"]) == {"z_0", "scan_0"}
    for t in range(1, 4):
        z, x = tr.nodes[f"z_{t}"]["infer"], tr.nodes[f"x_{t}"]["infer"]
        # (scan_t: the deterministic site of the predicted observation mu_E at z_t)
        prev = {f"x_{t - 1}", f"scan_{t - 1}", f"z_{t - 1}"}
        assert set(z["_markov_scope"]) == prev  # z_t sees step t-1 only
        assert set(x["_markov_scope"]) == prev | {f"z_{t}", f"scan_{t}"}
        assert z["_markov_depth"] == x["_markov_depth"] == 1  # one loop, not nested


# ------------------------------------------------------------------------------ chart
def bilinear_map(grid, coef):
    """``M[i, j] = c0 + c1 x_i + c2 y_j + c3 x_i y_j`` at the grid's node positions."""
    w, h = grid.cells
    xs = grid.origin[0] + torch.arange(w, dtype=torch.float64) * grid.size[0] / (w - 1)
    ys = grid.origin[1] + torch.arange(h, dtype=torch.float64) * grid.size[1] / (h - 1)
    X, Y = xs[:, None, None], ys[None, :, None]
    return coef[0] + coef[1] * X + coef[2] * Y + coef[3] * X * Y


def test_attend_is_exact_bilinear_interpolation():
    grid = MapGrid((5, 4), 2, origin=(-0.5, 1.0), size=(2.0, 1.5))
    coef = torch.tensor([[0.3, -1.0], [2.0, 0.5], [-1.5, 1.0], [0.7, -2.0]], dtype=torch.float64)
    M = bilinear_map(grid, coef)  # [5, 4, 2]
    g = torch.Generator().manual_seed(0)
    xy = torch.stack(
        [-0.5 + 2.0 * torch.rand(50, generator=g), 1.0 + 1.5 * torch.rand(50, generator=g)], -1
    ).double()

    def f(p):
        x, y = p[..., :1], p[..., 1:]
        return coef[0] + coef[1] * x + coef[2] * y + coef[3] * x * y

    torch.testing.assert_close(grid.attend(M, xy), f(xy))
    # grid nodes read their own cell; the far corner (clamped index) too
    torch.testing.assert_close(grid.attend(M, torch.tensor([[0.0, 1.5]]).double()), M[1:2, 1])
    torch.testing.assert_close(grid.attend(M, torch.tensor([[1.5, 2.5]]).double()), M[4:5, 3])
    # outside the extent: the border (clamped position)
    out = torch.tensor([[-3.0, 1.2], [0.3, 9.0], [5.0, -5.0]], dtype=torch.float64)
    lo, hi = torch.tensor([-0.5, 1.0]), torch.tensor([1.5, 2.5])
    torch.testing.assert_close(grid.attend(M, out), f(torch.maximum(torch.minimum(out, hi), lo)))
    # gradient w.r.t. the position is the bilinear function's
    p = xy[:5].clone().requires_grad_()
    grid.attend(M, p)[:, 0].sum().backward()
    dfdx = coef[1, 0] + coef[3, 0] * xy[:5, 1]
    dfdy = coef[2, 0] + coef[3, 0] * xy[:5, 0]
    torch.testing.assert_close(p.grad, torch.stack([dfdx, dfdy], -1))
    # a batch of S maps with positions [S, N, 2] reads each map at its own positions
    Ms = torch.stack([M, 2 * M + 1, -M])
    xs = xy[:12].reshape(3, 4, 2)
    want = torch.stack([f(xs[0]), 2 * f(xs[1]) + 1, -f(xs[2])])
    torch.testing.assert_close(grid.attend(Ms, xs), want)
    # power=2: squared weights; at a cell centre each of the 4 weights is 1/4
    centre = torch.tensor([[-0.25, 1.25]], dtype=torch.float64)
    ones = torch.ones(5, 4, 1, dtype=torch.float64)
    assert grid.attend(ones, centre, power=2).item() == pytest.approx(0.25)
    assert grid.attend(ones, centre).item() == pytest.approx(1.0)


def test_relative_variance_is_the_squared_weights_read():
    """The shifted single read equals sum a_i^2 s_i^2 / sum a_i^2 over the four cells, inside the
    grid, on its nodes and edges and clamped outside it, in both dtypes."""
    grid = MapGrid((7, 5), 1, origin=(-1.0, 0.5), size=(3.0, 2.0))
    g = torch.Generator().manual_seed(3)
    for dtype in (torch.float32, torch.float64):
        scale = torch.rand(7, 5, 1, generator=g).to(dtype) + 0.1
        xy = torch.rand(200, 2, generator=g).to(dtype) * torch.tensor([5.0, 4.0]).to(dtype)
        xy = xy + torch.tensor([-2.0, -0.5]).to(dtype)  # a band beyond every edge
        xy[:3] = torch.tensor([[-1.0, 0.5], [2.0, 2.5], [0.5, 1.0]]).to(dtype)  # nodes
        want = grid.attend(scale**2, xy, power=2) / grid.attend(torch.ones_like(scale), xy, 2)
        got = grid.relative_variance(scale, xy)
        torch.testing.assert_close(got, want)
        assert torch.equal(grid.read_variance(scale, xy[:, 0], xy[:, 1]), got)
        torch.testing.assert_close(grid.read(scale, xy[:, 0], xy[:, 1]), grid.attend(scale, xy))


def test_interleave_is_a_last_axis_stack():
    x, y = torch.randn(4, 3, 5), torch.randn(4, 3, 5)
    assert torch.equal(interleave(x, y), torch.stack([x, y], -1))
    out = interleave(x.double(), y > 0, torch.float32)
    assert out.dtype == torch.float32
    assert torch.equal(out, torch.stack([x.double(), (y > 0).double()], -1).float())


def test_ray_march_reads_the_variance_where_the_points_are():
    """``read_moments`` is the march of ``stops`` with the variance read at its points."""
    grid = MapGrid.covering(-2.0, -2.0, 2.0, 2.0, 0.1, 1)
    em = RayEmission(torch.linspace(-1.5, 1.5, 7), 3.0, samples=30)
    g = torch.Generator().manual_seed(1)
    loc = torch.randn(*grid.shape, generator=g) * 2
    scale = torch.rand(*grid.shape, generator=g)
    z = torch.randn(5, 3, generator=g) * 0.5
    pts, stop, passes = em.stops(grid, loc, z)  # [5, 7, 30, 2], [5, 7, 30], [5, 7]
    var = grid.relative_variance(scale, pts)[..., 0]
    rng, unknown = em.read_moments(grid, loc, scale, z)
    assert torch.equal(rng, em.expected_range(grid, loc, z))
    torch.testing.assert_close(unknown, (stop * var).sum(-1) + passes * var[..., -1])
    torch.testing.assert_close(stop.sum(-1) + passes, torch.ones(5, 7))


def test_grid_covering_unit_maze():
    g = MapGrid.covering(0.0, 0.0, 1.0, 1.0, 1 / 31, 10)
    assert g.cells == (32, 32) and g.shape == (32, 32, 10) and g.size == (1.0, 1.0)
    g = MapGrid.covering(0.0, 0.0, 1.0, 0.5, 0.1, 4, margin=0.05)
    assert g.cells == (12, 7) and g.origin == (-0.05, -0.05)
    assert g.size == pytest.approx((1.1, 0.6))


# ------------------------------------------------------------------------- emission
@pytest.mark.parametrize("n_world", [B, 2 * B])
def test_rotating_by_one_beam_spacing_shifts_scan_by_one_beam(n_world):
    m = tiny_model(n_world=n_world)
    M = torch.randn(5, 4, 3, generator=torch.Generator().manual_seed(1))
    z = torch.tensor([[0.1, 1.4, 0.3], [0.9, 2.0, -2.0]])
    turned = z + torch.tensor([0.0, 0.0, 2 * math.pi / B])
    a, b = m.emission_mean(M, z), m.emission_mean(M, turned)
    assert a.shape == (2, B)
    # beam i now looks where beam i+1 looked
    torch.testing.assert_close(b, torch.roll(a, -1, dims=-1), atol=1e-5, rtol=0)
    full_turn = z + torch.tensor([0.0, 0.0, 2 * math.pi])
    torch.testing.assert_close(m.emission_mean(M, full_turn), a, atol=1e-5, rtol=0)
    # the world-frame profile itself does not depend on the heading
    world = m.emission(m.chart(M, z))
    torch.testing.assert_close(m.emission(m.chart(M, turned)), world)


def test_rotate_scan_interpolates_world_profile():
    world = torch.tensor([1.0, 2.0, 3.0, 4.0])  # at 0, pi/2, pi, 3pi/2
    angles = torch.tensor([0.0, math.pi / 2])
    torch.testing.assert_close(rotate_scan(world, torch.tensor(0.0), angles), world[:2])
    torch.testing.assert_close(
        rotate_scan(world, torch.tensor(math.pi / 4), angles), torch.tensor([1.5, 2.5])
    )
    # wraps around: heading 7pi/4 reads between 4 and 1
    torch.testing.assert_close(
        rotate_scan(world, torch.tensor(-math.pi / 4), angles), torch.tensor([2.5, 1.5])
    )


# ------------------------------------------------------------------------- gradients
CFG = SLAMConfig(emission=EmissionConfig(resolution=0.25 / 6))
MAP_DIM, HIDDEN, LAYERS = 3, 16, 2  # a small emission MLP


def small_model(tr):
    """The DVBF-LM SLAM builds for ``tr`` with a small emission MLP (weights from torch's
    global random stream)."""
    emission = EmissionMLP(MAP_DIM, max(tr.num_beams, 20), HIDDEN, LAYERS, scale=tr.max_range)
    return build_model(tr, CFG, emission=emission)


@pytest.fixture(scope="module")
def small_traversal():
    return simulate_traversal("simple-small", steps=16, seed=0)


def elbo_setup(tr, dtype=torch.float32, ess_threshold=0.5, seed=0):
    torch.manual_seed(seed)
    model, guide = small_model(tr)
    model.to(dtype)
    obs = torch.as_tensor(tr.observations, dtype=dtype)
    ctl = torch.as_tensor(tr.controls, dtype=dtype)
    g = torch.Generator().manual_seed(seed)
    pf = ParticleFilter(model, ess_threshold=ess_threshold, generator=g)
    cache = ParticleCache(obs.shape[0], 8, dtype=dtype)
    poses = torch.as_tensor(tr.poses, dtype=dtype)
    z = poses[:, None] + 1e-3 * torch.randn(obs.shape[0], 8, 3, generator=g, dtype=dtype)
    cache.store(
        torch.arange(obs.shape[0]), Particles(z, torch.full((obs.shape[0], 8), -math.log(8)))
    )
    elbo = ParticleChunkELBO(pf, cache, obs, ctl, num_particles=16)
    return model, guide, elbo, poses


def test_gradients_flow_into_map_and_emission(small_traversal):
    model, guide, elbo, poses = elbo_setup(small_traversal)
    batch = ChunkBatch(torch.tensor([0, 6]), 4)
    loss = elbo.loss_and_grads(model.model, guide, batch)
    assert math.isfinite(loss)
    store = pyro.get_param_store()
    loc, scale = store["map_loc"], store.get_param("map_scale").unconstrained()
    for name, p in [("map_loc", loc), ("map_scale", scale)]:
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name
    emission_params = {n: p for n, p in store.named_parameters() if n.startswith("emission$$$")}
    assert len(emission_params) == 2 * (LAYERS + 1)
    module = dict(model.emission.named_parameters())
    for name, p in emission_params.items():
        assert p is module[name.split("$$$")[1]]  # the store holds the module's own tensors
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    # the likelihood only reaches cells near the chunks (loc = 0, so the KL adds nothing):
    # cells more than 2 cells from every pose of both chunks get exactly zero gradient
    grid = model.grid
    used = torch.cat([poses[0:4], poses[6:10]])[:, :2]
    axes = [torch.arange(c, dtype=torch.float32) for c in grid.cells]
    node = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)
    spacing = torch.tensor(grid.size) / (torch.tensor(grid.cells) - 1)
    pos = (used - torch.tensor(grid.origin)) / spacing  # grid coordinates
    far = (node[:, :, None] - pos).abs().amax(-1).amin(-1) > 2.5
    assert far.any() and (~far).any()
    assert (loc.grad[far] == 0).all() and (loc.grad[~far] != 0).any()


@pytest.mark.parametrize("ess_threshold", [2.0, 0.0], ids=["resample-always", "never"])
def test_particle_elbo_gradient_matches_finite_differences(small_traversal, ess_threshold):
    """For fixed random numbers the estimator is a smooth function of the map and emission
    parameters (resampling at every step, or never -- then the carried weights depend on the
    map too): autograd equals central differences."""
    model, guide, elbo, _ = elbo_setup(small_traversal, torch.float64, ess_threshold=ess_threshold)
    store = pyro.get_param_store()
    with torch.no_grad():  # float64 map parameters, away from the prior
        g = torch.Generator().manual_seed(5)
        store["map_loc"] = 0.3 * torch.randn(model.grid.shape, generator=g, dtype=torch.float64)
        store["map_scale"] = torch.full(model.grid.shape, 0.5, dtype=torch.float64)
    snapshot, gen_state = elbo.cache.state_dict(), elbo.pf.generator.get_state()
    batch = ChunkBatch(torch.tensor([2, 9]), 4)

    def loss():
        elbo.cache.load_state_dict(snapshot)
        elbo.pf.generator.set_state(gen_state)
        torch.manual_seed(11)  # the map sample
        return elbo.differentiable_loss(model.model, guide, batch)

    loc = store["map_loc"]
    scale = store.get_param("map_scale").unconstrained()
    w = model.emission.net.net[0].weight
    value = loss()
    # the value: -(T / (C L)) sum log p^ + KL, per time step, with the analytic Normal KL
    T, C, L = 16, 2, 4
    kl = loc.numel() * (math.log(1 / 0.5) + 0.25 / 2 - 0.5) + (loc**2).sum().item() / 2
    ev = elbo.last_log_evidence.sum().item()
    assert value.item() * T == pytest.approx(-(T / (C * L)) * ev + kl, rel=1e-12)
    grads = torch.autograd.grad(value, [loc, scale, w])
    for p, grad in zip([loc, scale, w], grads):
        flat = grad.flatten()
        for i in flat.abs().argsort(descending=True)[:3].tolist():
            eps = 1e-6
            with torch.no_grad():
                p.view(-1)[i] += eps
                up = loss().item()
                p.view(-1)[i] -= 2 * eps
                down = loss().item()
                p.view(-1)[i] += eps
            fd = (up - down) / (2 * eps)
            assert fd == pytest.approx(flat[i].item(), rel=1e-4, abs=1e-8)


# --------------------------------------------------------------- Predictive / poutine
def test_predictive_with_fixed_map_samples_the_emission_noise():
    m = tiny_model()
    obs, ctl, init = toy_data(T=2)
    M = torch.randn(5, 4, 3, generator=torch.Generator().manual_seed(2))
    N = 300
    samples = {"map": M.expand(N, 5, 4, 3)}
    pred = Predictive(m.model, posterior_samples=samples, return_sites=["x_0", "z_1", "map"])
    with torch.no_grad():
        s = pred(None, ctl, init)
    # Predictive pads sites outside the two map plates to max_plate_nesting = 2
    assert s["x_0"].shape == (N, 1, 1, B) and s["z_1"].shape == (N, 1, 1, 3)
    s = {k: v.reshape(N, -1) for k, v in s.items() if k != "map"} | {"map": s["map"]}
    assert torch.equal(s["map"][7], M)
    with torch.no_grad():
        mean0 = m.emission_mean(M, init)
    x0 = s["x_0"]
    assert ((x0.mean(0) - mean0).abs() < 4 * 0.1 / math.sqrt(N) + 2e-3).all()  # z_0 ~ init
    assert x0.std(0).mean().item() == pytest.approx(0.1, rel=0.1)
    z1 = m.transition.mean(init, ctl[0]).detach()
    assert ((s["z_1"].mean(0) - z1).abs() < 4 * 0.02 / math.sqrt(N) + 1e-3).all()


def test_guide_and_model_replay_under_poutine():
    m = tiny_model()
    obs, ctl, init = toy_data()
    guide = MapGuide(m.grid.shape)
    g_tr = poutine.trace(guide).get_trace()
    m_tr = poutine.trace(poutine.replay(m.model, trace=g_tr)).get_trace(obs, ctl, init)
    assert torch.equal(m_tr.nodes["map"]["value"], g_tr.nodes["map"]["value"])
    assert [f.name for f in g_tr.nodes["map"]["cond_indep_stack"]] == ["map_x", "map_y"]
    assert torch.isfinite(m_tr.log_prob_sum()) and torch.isfinite(g_tr.log_prob_sum())
    # Predictive with the guide: map from q(M), the rest from the model
    s = Predictive(m.model, guide=guide, num_samples=3, return_sites=["map", "x_4"])(
        None, ctl, init
    )
    assert s["map"].shape == (3, 5, 4, 3) and s["x_4"].shape == (3, 1, 1, B)
    assert not torch.equal(s["map"][0], s["map"][1])  # independent draws from q(M)
    # at init, q(M) is the prior: KL = 0
    kl = torch.distributions.kl_divergence(guide.distribution(), m.map_prior()).sum()
    assert kl.item() == 0.0


# ------------------------------------------------------------------ SMCFilter on a map
def test_smcfilter_on_learned_map_agrees_with_particle_filter(small_traversal):
    tr = small_traversal
    model, guide, elbo, poses = elbo_setup(tr)
    svi = SVI(model.model, guide, Adam({"lr": 0.05}), loss=elbo)
    g = torch.Generator().manual_seed(0)
    losses = [svi.step(ChunkBatch(torch.randint(0, 13, (4,), generator=g), 4)) for _ in range(60)]
    assert all(math.isfinite(v) for v in losses)
    assert sum(losses[-10:]) < sum(losses[:10])  # it learned something
    M = guide.mean()
    obs = torch.as_tensor(tr.observations)
    ctl = torch.as_tensor(tr.controls, dtype=torch.float32)
    init = poses[0]
    K = 400
    torch.manual_seed(0)
    smc = SMCFilter(
        FilterModel(model, M), ProposalGuide(model, TransitionProposal()), K, max_plate_nesting=0
    )
    with torch.no_grad():
        smc.init(init_pose=init, x=obs[0])
        smc_means = [smc.get_empirical()["z"].mean]
        for t in range(1, len(obs)):
            smc.step(t, obs[t], ctl[t - 1])
            smc_means.append(smc.get_empirical()["z"].mean)
    smc_means = torch.stack(smc_means)
    assert smc_means.shape == (16, 3) and torch.isfinite(smc_means).all()
    pf = ParticleFilter(model, generator=torch.Generator().manual_seed(0))
    ours = pf.run(M, obs, ctl, init, K)
    assert torch.isfinite(ours["mean"]).all() and math.isfinite(ours["log_evidence"])
    # same model, same map, both bootstrap: estimates agree within MC error
    tol = 5 * ours["std"][:, :2] / math.sqrt(K / 4) + 1e-4
    assert ((smc_means[:, :2] - ours["mean"][:, :2]).abs() < tol).all()
    # and both track the true path (corridor width 1/12)
    assert (smc_means[:, :2] - poses[:, :2]).norm(dim=-1).max() < 0.03


def test_bf16_filtering_matches_fp32_and_softsign_in_place_matches(small_traversal):
    x = torch.randn(7, 5)
    with torch.no_grad():
        torch.testing.assert_close(Softsign()(x.clone()), torch.nn.functional.softsign(x))
    tr = small_traversal
    model, guide, _, poses = elbo_setup(tr)
    M = torch.randn(model.grid.shape, generator=torch.Generator().manual_seed(1))
    obs = torch.as_tensor(tr.observations, dtype=torch.float32)
    ctl = torch.as_tensor(tr.controls, dtype=torch.float32)
    model.sigma_emission = 0.2
    out = {}
    for name, dt in (("fp32", None), ("bf16", torch.bfloat16)):
        gen = torch.Generator().manual_seed(0)
        pf = ParticleFilter(model, generator=gen, autocast_dtype=dt)
        out[name] = pf.run(M, obs, ctl, poses[0], 200)
    # same random stream, emission differs by bf16 rounding only: estimates agree closely
    diff = (out["fp32"]["mean"][:, :2] - out["bf16"]["mean"][:, :2]).abs().max()
    assert diff < 5e-3
    assert out["bf16"]["mean"].dtype == torch.float32
