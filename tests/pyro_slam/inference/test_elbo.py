"""The training objective (:mod:`pyro_slam.inference.elbo`): its chunk filter weighs with the
model's emission."""

from __future__ import annotations

import pyro.distributions as dist
import pytest
import torch
from slam_runs import (
    STEPS,
    make_slam,
)

from pyro_slam.inference import ChunkBatch
from simulators import simulate_traversal


@pytest.fixture(scope="module")
def traversal():
    return simulate_traversal("simple-small", steps=STEPS, seed=0)


def test_elbo_chunk_filter_weighs_with_the_models_emission(traversal):
    # the training objective's chunk filter weighs with the model's emission: its sigma_E and
    # its beam mixture, as the filter does
    slam = make_slam(traversal, {"emission": {"sigma": 0.02, "outlier_prob": 0.2}})
    t = 5
    true = torch.as_tensor(traversal.poses, dtype=slam.cache.z.dtype)
    slam.cache.z[:] = true.unsqueeze(1)  # every cached particle at the true pose
    slam.cache.filled[:] = True
    M = 0.5 * torch.randn(slam.model.grid.shape, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        ev = slam.elbo.chunk_log_evidence(M, ChunkBatch(torch.tensor([t]), 1))
        scan = slam.model.emission_mean(M, true[t])
        gauss = dist.Normal(scan, 0.02).log_prob(slam.obs[t]).exp()
        expected = torch.log(0.8 * gauss + 0.2 / slam.model.outlier_range).sum()
    assert slam.model.sigma_emission == 0.02 and slam.model.outlier_prob == 0.2
    torch.testing.assert_close(ev[0], expected, rtol=1e-3, atol=1e-2)
