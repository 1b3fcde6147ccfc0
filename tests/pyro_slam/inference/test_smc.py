"""Pyro's SMCFilter behind our filter's interface (:mod:`pyro_slam.inference.smc`): a cloud
from the initial pose prior, normalised weights, a step that moves it, no filter state."""

from __future__ import annotations

import pytest
import torch
from small_slam import SMALL

from pyro_slam.slam import SLAM
from simulators import simulate_traversal


def test_pyro_smc_filter_starts_at_the_pose_and_follows_the_controls():
    tr = simulate_traversal("simple-small", steps=4, seed=0)
    slam = SLAM(tr, SMALL, smc=True)
    pf = slam.pf
    assert type(pf).__name__ == "PyroSMCFilter"
    K = 256
    M = slam.map_belief()
    z0 = slam.init_pose.expand(K, 3)
    p, ev = pf.init(z0, M, slam.obs[0])
    assert p.z.shape == (K, 3) and torch.isfinite(ev)  # EvidenceSMCFilter keeps it
    torch.testing.assert_close(torch.logsumexp(p.logw, -1), torch.tensor(0.0), atol=1e-5, rtol=0)
    assert float((p.mean()[:2] - slam.init_pose[:2]).norm()) < 0.01
    q, _ = pf.step(p, M, slam.obs[1], slam.ctl[0])
    assert not torch.equal(q.z, p.z)  # each particle drawn from the proposal
    moved = slam.model.transition.mean(p.z, slam.ctl[0]).mean(0)
    assert float((q.mean()[:2] - moved[:2]).norm()) < 0.01
    assert pf.state_dict() == {}
    with pytest.raises(KeyError, match="unexpected filter state"):
        pf.load_state_dict({"x": 1})
