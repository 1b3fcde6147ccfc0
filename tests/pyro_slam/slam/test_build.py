"""The model builder (:mod:`pyro_slam.slam.build`): the transition scaled on a copy, dead
reckoning."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from slam_runs import (
    STEPS,
    make_slam,
)

from pyro_slam.inference import Particles
from pyro_slam.model import KinematicTransition
from pyro_slam.slam import ConfigError, TransitionConfig, path_integration
from simulators import simulate_traversal


@pytest.fixture(scope="module")
def traversal():
    return simulate_traversal("simple-small", steps=STEPS, seed=0)


def test_transition_scale_scales_a_copy_of_sigma_t(traversal):
    tran = KinematicTransition((5e-4, 5e-4, 8e-3))
    slam = make_slam(traversal, {"transition": {"scale": [3.0, 3.0, 0.2]}}, transition=tran)
    torch.testing.assert_close(slam.model.transition.sigma, torch.tensor([1.5e-3, 1.5e-3, 1.6e-3]))
    torch.testing.assert_close(tran.sigma, torch.tensor([5e-4, 5e-4, 8e-3]))  # not changed
    # the filter's particles spread by the scaled sigma: heading spread shrinks 5x
    z = torch.zeros(4000, 3)
    p = slam.pf.propagate(Particles(z, torch.zeros(4000)), torch.zeros(2))
    spread = p - slam.model.transition.mean(z, torch.zeros(1, 2))
    np.testing.assert_allclose(spread.std(0).numpy(), [1.5e-3, 1.5e-3, 1.6e-3], rtol=0.06)
    same = make_slam(traversal, transition=tran)
    assert same.model.transition is tran  # factors of 1: the transition as given
    for bad in [(1.0, 1.0), (1.0, 0.0, 1.0)]:
        with pytest.raises(ConfigError, match="transition.scale must be 3 positive numbers"):
            TransitionConfig(scale=bad)


def test_path_integration_reproduces_noiseless_motion():
    tr = simulate_traversal("simple-small", steps=40, seed=3, noise=0)
    assert tr.metadata["collisions"] == 0
    poses = path_integration(tr, KinematicTransition((1e-3, 1e-3, 1e-3)))
    assert poses.shape == (40, 3) and poses.dtype == np.float64
    np.testing.assert_allclose(poses[:, :2], tr.poses[:, :2], atol=1e-5)
    np.testing.assert_allclose(np.angle(np.exp(1j * (poses[:, 2] - tr.poses[:, 2]))), 0, atol=1e-5)
    assert (poses[:, 2] >= -np.pi).all() and (poses[:, 2] < np.pi).all()
