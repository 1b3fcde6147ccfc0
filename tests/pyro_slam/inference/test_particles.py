"""Weighted particle sets (:mod:`pyro_slam.inference.particles`): circular heading moments,
selecting rows of two sets."""

from __future__ import annotations

import math

import torch

from pyro_slam.inference import Particles
from pyro_slam.inference.particles import fitted_variance, pose_moments


def test_heading_moments_are_circular_and_weighted():
    # two particles either side of +-pi: the mean heading is pi (not 0), the std small
    z = torch.tensor([[1.0, 2.0, math.pi - 0.01], [3.0, 2.0, -math.pi + 0.01]])
    p = Particles(z, torch.log(torch.tensor([0.5, 0.5])))
    mean, std = p.mean(), p.std()
    assert abs(abs(float(mean[2])) - math.pi) < 1e-6
    torch.testing.assert_close(mean[:2], torch.tensor([2.0, 2.0]))
    torch.testing.assert_close(std, torch.tensor([1.0, 0.0, 0.01]), atol=1e-5, rtol=0)
    # weights count; None is uniform
    heavy = Particles(z, torch.log(torch.tensor([0.9, 0.1])))
    torch.testing.assert_close(heavy.mean()[0], torch.tensor(1.2))
    torch.testing.assert_close(pose_moments(z)[0], mean)


def test_where_takes_rows_from_either_set():
    a = Particles(torch.zeros(2, 3, 3), torch.full((2, 3), -math.log(3)), None, torch.zeros(2, 3))
    b = Particles(torch.ones(2, 3, 3), torch.full((2, 3), -math.log(3)), None, torch.ones(2, 3))
    c = a.where(torch.tensor([True, False]), b)
    assert torch.equal(c.z[0], a.z[0]) and torch.equal(c.z[1], b.z[1])
    assert torch.equal(c.ancestors, torch.tensor([[0.0] * 3, [1.0] * 3]))


def test_posterior_std_measures_a_narrow_likelihood_behind_a_wide_proposal():
    """64 particles drawn from a wide Gaussian proposal and weighed by a likelihood 8x
    narrower: the weights fall on a few particles, so the weighted std misses the posterior's
    by more than a quarter on some axis, while the Gaussian fit recovers it (the product of the
    two Gaussians) on each axis, the heading's across +-pi. The reported std is the larger of
    the two; flat weights give the proposal's own spread."""
    g = torch.Generator().manual_seed(0)
    sq = torch.tensor([0.08, 0.04, 0.05], dtype=torch.float64)
    sl = sq / 8
    centre = torch.tensor([1.0, -2.0, math.pi - 0.01], dtype=torch.float64)
    truth = (sq**-2 + sl**-2) ** -0.5  # [3] the product's std
    weighted_off = []
    for _ in range(5):
        d = sq * torch.randn(64, 3, generator=g, dtype=torch.float64)
        z = centre + d
        z[:, 2] = torch.remainder(z[:, 2] + math.pi, 2 * math.pi) - math.pi  # wrapped
        logw = -0.5 * ((d / sl) ** 2).sum(-1)
        p = Particles(z, logw - torch.logsumexp(logw, 0))
        assert 1 / p.logw.exp().pow(2).sum() < 8  # the weights have collapsed
        weighted_off.append(float((p.std() / truth - 1).abs().max()))
        torch.testing.assert_close(fitted_variance(p.z, p.logw).sqrt(), truth, rtol=0.05, atol=0)
        assert (p.posterior_std() >= torch.maximum(0.95 * truth, p.std())).all()
        flat = Particles(z, torch.full((64,), -math.log(64), dtype=torch.float64))
        torch.testing.assert_close(flat.posterior_std(), flat.std())
    assert max(weighted_off) > 0.25


def test_posterior_std_of_a_degenerate_cloud_is_the_weighted_one():
    """Particles of zero weight (-inf) or all at one pose leave nothing to fit: the weighted
    std, finite."""
    g = torch.Generator().manual_seed(1)
    z = 0.05 * torch.randn(64, 3, generator=g, dtype=torch.float64)
    logw = torch.full((64,), -math.inf, dtype=torch.float64)
    logw[:5] = -math.log(5)
    p = Particles(z, logw)
    torch.testing.assert_close(p.posterior_std(), p.std())
    same = Particles(torch.zeros(64, 3, dtype=torch.float64), torch.full((64,), -math.log(64)))
    assert torch.equal(same.posterior_std(), torch.zeros(3, dtype=torch.float64))
