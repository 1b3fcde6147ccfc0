"""Resampling schemes (:mod:`pyro_slam.inference.resampling`): shapes, following the weights,
systematic counts within one of their expectation."""

from __future__ import annotations

import math

import pytest
import torch

from pyro_slam.inference import Particles, resampling


@pytest.mark.parametrize("scheme", ["systematic", "multinomial"])
def test_resampling_keeps_shapes_and_follows_weights(scheme):
    g = torch.Generator().manual_seed(0)
    K = 8
    logw = torch.randn(2, 3, K, generator=g) * 2
    z = torch.randn(2, 3, K, 3, generator=g)
    p = Particles(z, resampling.normalize(logw), torch.randn(2, 3, K, 5, generator=g))
    state = g.get_state()
    idx = resampling.SCHEMES[scheme](logw, g)
    assert idx.shape == (2, 3, K) and idx.dtype == torch.long
    assert idx.min() >= 0 and idx.max() < K
    g.set_state(state)  # the same draw again, inside Particles.resample
    r = p.resample(g, scheme)
    assert r.z.shape == z.shape and r.scan.shape == (2, 3, K, 5) and r.logw.shape == (2, 3, K)
    torch.testing.assert_close(r.logw, torch.full_like(logw, -math.log(K)))
    # every resampled particle is one of the old ones, with its scan
    for i in range(2):
        for j in range(3):
            torch.testing.assert_close(r.z[i, j], z[i, j, idx[i, j]])
            torch.testing.assert_close(r.scan[i, j], p.scan[i, j, idx[i, j]])


def test_systematic_counts_are_within_one_of_expectation():
    g = torch.Generator().manual_seed(1)
    K = 50
    logw = torch.randn(20, K, generator=g) * 1.5
    idx = resampling.systematic(logw, g)
    counts = torch.zeros(20, K).scatter_add_(1, idx, torch.ones(20, K))
    expected = K * torch.softmax(logw, -1)
    assert ((counts - expected).abs() < 1 + 1e-5).all()
    # multinomial resampling is unbiased: average counts over many draws approach K w
    many = torch.stack([resampling.multinomial(logw[:1], g) for _ in range(400)])
    freq = torch.zeros(K).scatter_add_(0, many.flatten(), torch.ones(many.numel())) / 400
    assert (freq - expected[0]).abs().max() < 0.5
