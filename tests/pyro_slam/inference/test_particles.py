"""Weighted particle sets (:mod:`pyro_slam.inference.particles`): circular heading moments,
selecting rows of two sets."""

from __future__ import annotations

import math

import torch

from pyro_slam.inference import Particles
from pyro_slam.inference.particles import pose_moments


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
