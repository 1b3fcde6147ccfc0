"""The online sweep and the offline rounds (:mod:`pyro_slam.slam.loop`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from slam_runs import (
    CHUNK_LENGTH,
    STEPS,
    config,
    make_slam,
)

from pyro_slam.metrics import localisation_error
from pyro_slam.slam import ConfigError, loop
from simulators import simulate_traversal


@pytest.fixture(scope="module")
def traversal():
    return simulate_traversal("simple-small", steps=STEPS, seed=0)


def test_offline_estimate_cache_filters_chunks_from_the_cached_particles(traversal, monkeypatch):
    """``offline.estimate="cache"`` (paper B-I): each chunk restarts from the cache, so a pose
    the cache holds far from the truth shows up at that chunk's steps and nowhere else."""
    L = CHUNK_LENGTH
    slam = make_slam(traversal, {"offline": {"rounds": 0, "estimate": "cache"}})
    run_ = loop.cache_pass
    shift = torch.tensor([0.03, 0.0, 0.0])

    def shifted_cache_pass(c, st, data, progress, desc):  # the cache at step 2L moved in x
        st.cache.z[2 * L] += shift
        before.append(st.cache.z.clone())
        return run_(c, st, data, progress, desc)

    before = []

    monkeypatch.setattr(loop, "cache_pass", shifted_cache_pass)
    res = slam.run("offline", progress=False)
    T = traversal.num_steps
    assert res["mean"].shape == res["std"].shape == (T, 3)
    err = localisation_error(res["mean"], traversal.poses)
    chunk = slice(2 * L, 3 * L)
    assert err[chunk].min() > 0.015 and np.delete(err, np.arange(2 * L, 3 * L)).max() < 0.01
    # chunk starts sit on the cache's means, which the pass leaves as they were
    starts = slam.cache.z[::L].mean(1).numpy()
    np.testing.assert_allclose(res["mean"][::L, :2], starts[:, :2], atol=5e-3)
    assert torch.equal(slam.cache.z, before[0])
    # with SVI rounds, only their chunks refresh the cache: no whole-traversal filter pass
    slam = make_slam(traversal, {"offline": {"estimate": "cache"}})
    monkeypatch.setattr(loop, "cache_pass", run_)
    monkeypatch.setattr(loop, "filter_pass", None)  # would raise if called
    res = slam.run("offline", progress=False)
    assert slam.state.round == 2 and localisation_error(res["mean"], traversal.poses).max() < 0.03
    msg = r"offline.estimate must be one of \['forward', 'cache'\], got 'smooth'"
    with pytest.raises(ConfigError, match=msg):
        config({"offline": {"estimate": "smooth"}})
