"""The particle cache (:mod:`pyro_slam.inference.cache`): storing clouds, their moments
(circular in the heading) and proposals from them."""

from __future__ import annotations

import math

import pytest
import torch
from linear_gaussian import LinearGaussian

from pyro_slam.inference import ParticleCache, ParticleFilter, Particles


def test_particle_cache_store_and_propose():
    g = torch.Generator().manual_seed(0)
    cache = ParticleCache(10, num_particles=400)
    z = torch.tensor([1.0, 2.0, 0.5]) + torch.tensor([0.1, 0.2, 0.05]) * torch.randn(
        2, 800, 3, generator=g
    )
    cache.store(torch.tensor([3, 4]), Particles(z, torch.full((2, 800), -math.log(800))), g)
    assert cache.filled.tolist() == [False] * 3 + [True] * 2 + [False] * 5
    loc, scale = cache.moments(torch.tensor([3, 4]))
    torch.testing.assert_close(loc, torch.tensor([[1.0, 2.0, 0.5]] * 2), atol=0.03, rtol=0)
    torch.testing.assert_close(scale, torch.tensor([[0.1, 0.2, 0.05]] * 2), rtol=0.15, atol=0)
    for kind in ("gaussian", "categorical"):
        prop = cache.propose(torch.tensor([3, 4, 3]), 7, kind, generator=g)
        assert prop.shape == (3, 7, 3) and torch.isfinite(prop).all()
    # a cloud facing west straddles +-pi: its heading moments are circular (mean ~pi, std
    # 0.01), not the raw values' (mean ~0, std ~pi), and the proposal stays near +-pi
    west = torch.tensor([0.5, 0.5, math.pi]) + torch.tensor([0.0, 0.0, 0.01]) * torch.randn(
        1, 800, 3, generator=g
    )
    west[..., 2] = torch.remainder(west[..., 2] + math.pi, 2 * math.pi) - math.pi
    cache.store(torch.tensor([6]), Particles(west, torch.full((1, 800), -math.log(800))), g)
    loc, scale = cache.moments(torch.tensor([6]))
    assert abs(abs(float(loc[0, 2])) - math.pi) < 0.003 and float(scale[0, 2]) < 0.012
    prop = cache.propose(torch.tensor([6]), 100, generator=g)[..., 2]  # [1, 100]
    assert float(prop.abs().min()) > math.pi - 0.05 and float(prop.abs().max()) <= math.pi
    p = Particles(west[0], torch.full((800,), -math.log(800)))
    assert float(p.std()[2]) < 0.012 and abs(abs(float(p.mean()[2])) - math.pi) < 0.003
    with pytest.raises(ValueError, match=r"no particles at steps \[5\]"):
        cache.propose(torch.tensor([4, 5]), 7)
    with pytest.raises(ValueError, match="unknown proposal"):
        cache.propose(torch.tensor([4]), 7, "nope")
    with pytest.raises(ValueError, match="unknown resampling scheme"):
        ParticleFilter(LinearGaussian(torch.float32), scheme="stratified")
