"""The likelihood-field LiDAR emission :class:`~pyro_slam.model.EndPointEmission`: the distance
its ramp reads at each reading's end point, in the model, the filter and SLAM."""

from __future__ import annotations

import math
from dataclasses import replace

import pyro
import pyro.distributions as dist
import pytest
import torch
from small_slam import SMALL

from pyro_slam.inference import ParticleFilter
from pyro_slam.model import (
    DVBFLM,
    EndPointEmission,
    KinematicTransition,
    LearnedTransition,
    MapBelief,
    MapGrid,
    TransitionMLP,
    WallRamp,
)
from pyro_slam.slam import SLAM, ConfigError, EmissionConfig, ScanInsertionConfig
from simulators import simulate_traversal

SPACING = 0.025
RAMP = WallRamp(wall=2.2, free=-1.1, half_width=1.5, shift=0.25)


def wall_map():
    """A 1 x 1 room on a 41 x 41 grid (spacing 0.025) with a wall at x = 0.6 facing west: the
    ramp at each grid point's signed distance to it, ``[41, 41, 1]``."""
    grid = MapGrid((41, 41), 1, (0.0, 0.0), (1.0, 1.0))
    xs = torch.arange(41, dtype=torch.float32) * SPACING
    d = ((xs - 0.6) / SPACING)[:, None].expand(41, 41)  # [w, h] positive behind the wall
    return grid, RAMP.loc(d).unsqueeze(-1)


def model_with(em, outlier_prob=0.0):
    """The model of ``em`` on the room's grid: sigma_E 0.01, outliers over a range of 0.5."""
    noise = {"sigma_emission": 0.01, "outlier_prob": outlier_prob, "outlier_range": 0.5}
    return DVBFLM(wall_map()[0], em, KinematicTransition((1e-3, 1e-3, 1e-3)), **noise)


def test_the_ramp_reads_back_the_distance_it_writes():
    d = torch.linspace(-1.75, 1.25, 13)  # inside the ramp, less its shift
    torch.testing.assert_close(RAMP.distance(RAMP.loc(d)), d)
    # beyond the ramp the map says only "free" or "wall": the distance is clamped
    far = RAMP.distance(RAMP.loc(torch.tensor([-9.0, 9.0])))
    torch.testing.assert_close(far, torch.tensor([-1.75, 1.25]))


def test_the_mean_given_a_reading_is_the_reading_less_the_distance_at_its_end_point():
    """Beam 0 looks east at the wall 0.3 ahead: a reading of 0.32 ends 0.02 behind the wall,
    so its mean is 0.30 and the model scores N(0.02; 0, sigma_E); one of 0.45 ends beyond the
    ramp and is charged the clamped distance; a miss (at the range) is its own mean."""
    grid, M = wall_map()
    em = EndPointEmission(torch.tensor([0.0, math.pi]), max_range=0.5, ramp=RAMP)
    z = torch.tensor([0.3, 0.5, 0.0])
    x = torch.tensor([[0.32, 0.5], [0.30, 0.5], [0.45, 0.5], [0.2, 0.5]])  # [4, B]
    mean = em.read(grid, M, z.expand(4, 3), x)
    expect = torch.tensor([0.30, 0.30, 0.45 - 1.25 * SPACING, 0.2 + 1.75 * SPACING])
    torch.testing.assert_close(mean[:, 0], expect, atol=1e-5, rtol=0)
    torch.testing.assert_close(mean[:, 1], torch.full((4,), 0.5))  # west: a miss
    model = model_with(em)
    lp = model.emission_log_prob(x, mean)
    d = torch.tensor([0.02, 0.0, 1.25 * SPACING, -1.75 * SPACING])
    torch.testing.assert_close(lp, dist.Normal(0.0, 0.01).log_prob(d) + lp.new_tensor(3.6862316))
    # without a reading: the ray march's expected range (the wall, to within the grid)
    assert float(em.read(grid, M, z[None])[0, 0]) == pytest.approx(0.3, abs=0.02)


def test_moments_know_readings_that_end_on_mapped_walls_and_not_misses():
    grid, M = wall_map()
    em = EndPointEmission(torch.tensor([0.0, math.pi]), max_range=0.5, ramp=RAMP)
    scale = torch.ones_like(M)
    scale[20:30] = 0.1  # mapped: x in [0.5, 0.725]
    z = torch.tensor([[0.3, 0.5, 0.0], [0.1, 0.5, 0.0], [0.1, 0.5, 0.0]])
    x = torch.tensor([[0.3, 0.5], [0.3, 0.5], [0.5, 0.5]])  # [K, B]: east, then a miss west
    mean, v = em.read_moments(grid, M, scale, z, x=x)
    assert mean.shape == v.shape == (3, 2)
    assert float(v[0, 0]) == pytest.approx(0.01, abs=1e-6)  # ends at x = 0.6: mapped
    assert float(v[1, 0]) == pytest.approx(1.0)  # ends at x = 0.4: at the prior
    # misses are unknown, even one whose end point (x = 0.6) is mapped
    assert v[2].tolist() == [1.0, 1.0] and v[:, 1].tolist() == [1.0, 1.0, 1.0]


def test_filter_and_model_weigh_with_the_same_end_point_factor():
    """The particle filter's log-likelihood under a map is the model's own site ``x_t`` (its
    mean given the observation), and under a belief the marginal emission's at the same end
    points; it peaks at the true pose."""
    grid, M = wall_map()
    em = EndPointEmission(torch.tensor([0.0, 0.3, -0.3]), max_range=0.5, ramp=RAMP)
    model = model_with(em, outlier_prob=0.1)
    true = torch.tensor([0.3, 0.5, 0.0])
    x = 0.3 / torch.cos(em.beam_angles)  # [B] the scan at the true pose
    z = true + torch.tensor([[0.0, 0, 0], [-0.02, 0, 0], [0.02, 0, 0], [0.0, 0, 0.3]])  # [K, 3]
    pf = ParticleFilter(model)
    ll, _ = pf.log_likelihood(z, M, x)
    assert int(ll.argmax()) == 0 and float(ll[0] - ll[1:].max()) > 1.0
    at = pyro.poutine.condition(model.model, {"map": M, "z_0": z[1]})
    trace = pyro.poutine.trace(at).get_trace(x[None], torch.zeros(0, 3), z[1])
    torch.testing.assert_close(trace.nodes["x_0"]["fn"].log_prob(x), ll[1])
    belief = MapBelief(M, torch.full_like(M, 1e-3))
    llb, _ = pf.log_likelihood(z, belief, x)
    torch.testing.assert_close(llb, ll, atol=1e-3, rtol=0)


def test_end_point_slam_needs_fusion_insertion_and_shares_its_ramp():
    """The kind is configured with fusion insertion only; the inserter writes the emission's
    own ramp; a transition that reads the predicted scan is refused (the end-point mean
    depends on the reading); a short run tracks its path."""
    with pytest.raises(ConfigError, match="'endpoint' .* needs emission.insert.kind = 'fusion'"):
        EmissionConfig("endpoint", insert=ScanInsertionConfig(kind="occupancy"))
    with pytest.raises(ConfigError, match="needs emission.insert.kind"):
        EmissionConfig("endpoint")
    tr = simulate_traversal("moderate-medium", steps=60, seed=1)
    insert = ScanInsertionConfig(kind="fusion")
    cfg = replace(SMALL, emission=EmissionConfig("endpoint", 1 / 63, insert=insert))
    slam = SLAM(tr, cfg)
    assert isinstance(slam.model.emission, EndPointEmission)
    assert slam.inserter.ramp is slam.model.emission.ramp
    assert 0 < abs(slam.model.emission.ramp.shift) < 1
    with pytest.raises(ValueError, match="no predicted scan for LearnedTransition"):
        DVBFLM(slam.model.grid, slam.model.emission, LearnedTransition(TransitionMLP(2, 3), 0.01))
