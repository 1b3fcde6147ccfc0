"""A run is its components, its state and its data (:mod:`pyro_slam.slam.parts`,
:mod:`pyro_slam.slam.state`): the components are frozen, the run's names read through to them,
and a checkpoint round trip restores the state exactly."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from slam_runs import RAYCAST, STEPS, make_slam

from pyro_slam.slam import SLAMState, checkpoint
from pyro_slam.slam.parts import Components, RunData
from simulators import simulate_traversal


@pytest.fixture(scope="module")
def traversal():
    return simulate_traversal("simple-small", steps=STEPS, seed=0)


def test_components_are_frozen_and_the_run_reads_through(traversal):
    slam = make_slam(traversal)
    c = slam.components
    assert isinstance(c, Components) and isinstance(slam.data, RunData)
    assert isinstance(slam.state, SLAMState) and slam.state.mode is None
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.model = None
    with pytest.raises(dataclasses.FrozenInstanceError):
        slam.data.obs = None
    with pytest.raises(AttributeError):
        slam.model = None  # the run's names are read-only
    assert slam.model is c.model and slam.pf is c.pf and slam.elbo is c.elbo
    assert slam.cache is slam.state.cache and slam.history is slam.state.history
    assert slam.obs is slam.data.obs and slam.T == STEPS == slam.data.T
    # the filters and the objective draw from the state's generator and fill its cache
    assert c.pf.generator is slam.state.gen and c.elbo.pf.generator is slam.state.gen
    assert c.elbo.cache is slam.state.cache


def _state_tensors(st: SLAMState) -> dict:
    """The state's particles, cache, history and generator state."""
    out = {f"cache.{k}": v for k, v in st.cache.state_dict().items()}
    out |= {f"history.{k}": v for k, v in st.history.state_dict().items()}
    out |= {"z": st.particles.z, "logw": st.particles.logw, "gen": st.gen.get_state()}
    return out


def test_checkpoint_round_trip_restores_the_state_exactly(traversal, tmp_path):
    ckpt = tmp_path / "ckpt.pt"
    slam = make_slam(traversal, RAYCAST, checkpoint=ckpt, checkpoint_every=100)
    slam.run("online", progress=False)
    saved = _state_tensors(slam.state)
    # (not the wall time, which the run adds to after its final checkpoint)
    counters = {f.name: getattr(slam.state, f.name) for f in dataclasses.fields(SLAMState)[3:-2]}
    rng = torch.get_rng_state()
    assert set(checkpoint.read(ckpt)) == {"format", "fingerprint", "state", "components"}

    torch.manual_seed(123)  # torch's global random state comes back too
    resumed = make_slam(traversal, RAYCAST, checkpoint=ckpt).resume(ckpt)
    got = _state_tensors(resumed.state)
    for k, v in saved.items():
        assert torch.equal(got[k], v), k
    for k, v in counters.items():
        assert getattr(resumed.state, k) == v, k
    assert torch.equal(torch.get_rng_state(), rng)
    assert torch.equal(resumed.inserter.inserted, slam.inserter.inserted)
    assert resumed.components.inserter is not None and resumed.elbo.num_steps_seen == STEPS
