"""The geometric LiDAR read-out :class:`~pyro_slam.model.RayEmission`, its per-beam trust and
beam-mixture weights, in the model and in SLAM."""

from __future__ import annotations

import math

import pytest
import torch
from small_slam import ray_slam

from pyro_slam.inference import ParticleFilter
from pyro_slam.metrics import localisation_error
from pyro_slam.model import (
    DVBFLM,
    EmissionMLP,
    KinematicTransition,
    MapBelief,
    MapGrid,
    RayEmission,
)
from pyro_slam.slam import (
    ConfigError,
    EmissionConfig,
    SLAMConfig,
    build_model,
)
from simulators import simulate_traversal


@pytest.fixture(scope="module")
def small_traversal():
    return simulate_traversal("moderate-medium", steps=100, seed=1)


def _wall_grid():
    """A 1 x 1 room on a 41 x 41 grid with one vertical wall at x = 0.6."""
    grid = MapGrid((41, 41), 1, (0.0, 0.0), (1.0, 1.0))
    walls = torch.tensor([[0.6, 0.0, 0.6, 1.0]])
    return grid, walls


def test_range_to_a_known_wall_and_max_range_in_free_space():
    grid, walls = _wall_grid()
    M = RayEmission.wall_map(grid, walls)  # [41, 41, 1]
    em = RayEmission(torch.tensor([0.0, math.pi / 2, math.pi]), max_range=0.5, samples=100)
    z = torch.tensor([[0.3, 0.5, 0.0], [0.45, 0.5, 0.0]])  # [2, 3]
    r = RayEmission.read(em, grid, M, z)  # [2, 3]
    assert r.shape == (2, 3)
    # beam 0 hits the wall 0.3 / 0.15 ahead (the grid smears it by ~half a cell, 0.0125)
    assert r[:, 0].tolist() == pytest.approx([0.3, 0.15], abs=0.02)
    # beams along and away from the wall see nothing within range
    assert r[:, 1:].min() > 0.49


def test_heading_rotates_the_beams():
    grid, walls = _wall_grid()
    M = RayEmission.wall_map(grid, walls)
    em = RayEmission(torch.tensor([0.0, -math.pi / 2]), max_range=0.5, samples=100)
    r = em.read(grid, M, torch.tensor([0.3, 0.5, math.pi / 2]))  # facing +y: beam 1 faces +x
    assert r[0] > 0.49 and r[1] == pytest.approx(0.3, abs=0.02)


def test_oracle_map_reproduces_simulated_scans(small_traversal):
    tr = small_traversal
    cfg = SLAMConfig(emission=EmissionConfig("raycast", resolution=1 / 63))
    model, guide = build_model(tr, cfg)
    assert isinstance(model.emission, RayEmission) and model.grid.dim == 1
    assert guide.shape == (*model.grid.cells, 1)
    M = RayEmission.wall_map(model.grid, tr.walls)
    pred = model.emission_mean(M, torch.as_tensor(tr.poses, dtype=torch.float32))  # [T, B]
    err = (pred - torch.as_tensor(tr.observations, dtype=torch.float32)).abs()
    assert err.shape == tr.observations.shape
    assert err.median() < 0.015 and err.mean() < 0.03


def test_gradients_reach_the_cells_the_beams_cross_and_batched_maps():
    grid, walls = _wall_grid()
    M = RayEmission.wall_map(grid, walls).requires_grad_()
    em = RayEmission(torch.tensor([0.0]), max_range=0.5, samples=50)
    em.read(grid, M, torch.tensor([0.3, 0.5, 0.0])).sum().backward()
    g = M.grad[..., 0].abs()  # [41, 41]
    row = g[:, 20]  # y = 0.5: the beam's row
    assert row[12:25].sum() > 0  # cells between the pose and the wall
    assert g[:, :15].sum() == 0 and g[:, 26:].sum() == 0  # no cell away from the beam
    # a batch of map samples [S, w, h, 1] with poses [S, K, 3] reads [S, K, B]
    Ms = torch.stack([M.detach(), torch.full_like(M, -2.0)])
    r = em.read(grid, Ms, torch.tensor([0.3, 0.5, 0.0]).expand(2, 4, 3))
    assert r.shape == (2, 4, 1)
    assert r[0].squeeze() == pytest.approx(torch.full((4,), 0.3), abs=0.02)
    assert r[1].min() > 0.49  # an empty map: max range


def test_bad_emission_kind_is_rejected():
    with pytest.raises(ConfigError, match="emission.kind must be one of .*'nerf'"):
        EmissionConfig(kind="nerf")


def test_marginal_emission_knows_beams_that_end_on_mapped_walls():
    """Under a map belief each beam's reading is known where the ray stops on a wall the map
    knows, even at a new pose, and unknown (uniform over the range) where it runs into cells
    still at the prior: the marginal emission's outlier probability is the model's on the
    first, 1 on the second; a chart emission has one per particle."""
    grid, walls = _wall_grid()
    em = RayEmission(torch.tensor([0.0, math.pi]), max_range=0.5, samples=100)
    model = DVBFLM(
        grid, em, KinematicTransition((1e-3, 1e-3, 1e-3)), outlier_prob=0.1, outlier_range=0.5
    )
    loc = RayEmission.wall_map(grid, walls)
    scale = torch.full_like(loc, 1.0)
    scale[12:30] = 0.05  # mapped: x in [0.3, 0.725], the wall at x = 0.6 included
    belief = MapBelief(loc, scale)
    z = torch.tensor([[0.4, 0.5, 0.0], [0.45, 0.5, 0.0]])  # [K=2, 3]
    mean, eps = model.marginal_emission(belief, z)  # [2, B=2] each
    assert mean.shape == eps.shape == (2, 2)
    assert mean[:, 0] == pytest.approx(torch.tensor([0.2, 0.15]), abs=0.02)
    assert eps[:, 0].max() < 0.11  # east: stops on the mapped wall (the model's 0.1)
    assert eps[:, 1].min() > 0.99  # west: runs out of range in unmapped cells
    # under the belief the weights are the model's emission with that outlier probability
    x = torch.tensor([0.2, 0.3])
    pf = ParticleFilter(model)
    ll, _ = pf.log_likelihood(z, belief, x)
    expect = model.emission_dist(mean, outlier_prob=eps).log_prob(x)
    torch.testing.assert_close(ll, expect)
    # a chart emission: one value per particle, from the chart at the pose
    mlp = DVBFLM(MapGrid((5, 5), 2), EmissionMLP(2, 20), KinematicTransition(1e-3), [0.0])
    v = mlp.marginal_emission(MapBelief(torch.zeros(5, 5, 2), torch.ones(5, 5, 2)), z)[1]
    assert v.shape == (2, 1) and torch.allclose(v, torch.ones(2, 1))


def test_online_slam_with_the_ray_emission_tracks_and_maps(small_traversal):
    """A short online run with the ray-cast emission: the pose estimate stays on the path, and
    the learned map, ray-cast at the true poses, predicts the observed scans far better than the
    prior map (nearly free space, every beam at max range) does."""
    tr = small_traversal
    slam = ray_slam(tr)
    assert slam.inserter is None
    res = slam.run("online", progress=False)
    assert res["map_loc"].shape == (*slam.model.grid.cells, 1)
    err = localisation_error(res["mean"], tr.poses)  # [T]
    # the estimate stays in the corridor (~0.06 wide): measured 0.016-0.039 over SLAM seeds 0-3
    # (dead reckoning: 0.011 over these 100 steps; the map is this test's claim)
    assert err.max() < 0.05
    em, grid = slam.model.emission, slam.model.grid
    M = torch.as_tensor(res["map_loc"])  # [w, h, 1]
    z = torch.as_tensor(tr.poses, dtype=M.dtype)  # [T, 3]
    learned = (em.read(grid, M, z) - slam.obs).abs().mean()
    prior = (em.read(grid, torch.zeros_like(M), z) - slam.obs).abs().mean()
    assert prior > 0.25 and learned < 0.4 * prior  # measured 0.34 and 0.092


def test_beam_mixture_weights_bound_one_wild_beam():
    """The model's beam mixture (``outlier_prob``): each beam scores ``log((1 - eps) N(x; mu,
    sigma) + eps / outlier_range)``, so one beam the map cannot explain costs at most
    ``log(eps / range)`` relative to a match instead of ``r^2 / 2 sigma^2``; the filter weighs
    with exactly that."""
    eps, rng, s = 0.1, 0.5, 0.02
    x = torch.tensor([0.3, 0.2])  # [B]
    scan = torch.tensor([[0.3, 0.2], [0.3, 0.45], [0.31, 0.2]])  # [K=3, B]

    class Fixed(RayEmission):  # an emission that predicts these scans
        def read(self, grid, M, z, x=None):
            return scan

    model = DVBFLM(
        MapGrid((5, 5), 1),
        Fixed([0.0, 1.0], rng),
        KinematicTransition(1e-3),
        sigma_emission=s,
        outlier_prob=eps,
        outlier_range=rng,
    )
    lp, _ = ParticleFilter(model).log_likelihood(torch.zeros(3, 3), torch.zeros(5, 5, 1), x)
    gauss = -0.5 * ((x - scan) / s) ** 2 - math.log(s) - 0.5 * math.log(2 * math.pi)
    expect = torch.log((1 - eps) * gauss.exp() + eps / rng).sum(-1)
    assert torch.allclose(lp, expect, atol=1e-5)
    # the wild beam (0.25 off, 12.5 sigma): the plain Gaussian would cost 78 nats
    assert float(lp[0] - lp[1]) < 7.0
    # a near miss still ranks below a match: the mixture keeps the Gaussian's sharpness
    assert lp[0] > lp[2] > lp[1]
    with pytest.raises(ValueError, match="outlier_prob"):
        DVBFLM(
            MapGrid((5, 5), 1), RayEmission([0.0], 1.0), KinematicTransition(1e-3), outlier_prob=1.0
        )


def test_early_stopped_march_matches_the_full_march():
    """Dropping a beam once its transmittance is below the tolerance changes its range by less
    than ``tolerance * max_range`` and its variance by less than ``tolerance``; beams that
    reach the end of the range (an open side of the room) keep their passing term. Checked
    across several blocks (walls 0.2-0.9 from the poses, 4 points per block), with gradients,
    and with the map's variance passed in as a caller keeps it."""
    grid = MapGrid((41, 41), 1, (0.0, 0.0), (1.0, 1.0))
    walls = torch.tensor([[0.1, 0.05, 0.1, 0.95], [0.1, 0.05, 0.95, 0.05], [0.7, 0.4, 0.7, 0.6]])
    loc = RayEmission.wall_map(grid, walls, width=1.5).double()
    scale = torch.rand(41, 41, 1, generator=torch.Generator().manual_seed(0)).double()
    angles = torch.linspace(-math.pi, math.pi, 24)[:-1]
    full = RayEmission(angles, max_range=0.8, samples=60).double()
    early = RayEmission(angles, max_range=0.8, samples=60, tolerance=1e-6).double()
    early.block = 4
    z = torch.tensor([[0.3, 0.5, 0.1], [0.5, 0.3, -2.0], [0.45, 0.7, 3.0]], dtype=torch.float64)
    z.requires_grad_()
    r0, v0 = full.read_moments(grid, loc, scale, z)  # [3, 23] each
    r1, v1 = early.read_moments(grid, loc, scale, z)
    assert r1.shape == v1.shape == (3, 23)
    kept = early.read_moments(grid, loc, scale, z, scale**2)  # the variance as a caller keeps it
    assert torch.equal(kept[0], r1) and torch.equal(kept[1], v1)
    passing = full._range(grid, loc, z)[1]  # [3, 23]
    assert (passing > 0.5).any() and (passing < 1e-6).sum() > 30  # both kinds of beam
    assert (r0 - r1).abs().max() < 1e-6 * 0.8 + 1e-9
    assert (v0 - v1).abs().max() < 1e-6
    g0, g1 = (torch.autograd.grad(r.sum(), z)[0] for r in (r0, r1))
    torch.testing.assert_close(g1, g0, atol=1e-4, rtol=1e-4)
