"""Putting a run together (:mod:`pyro_slam.slam.assemble`): the heading factor's data only with
a heading configuration, the guide's parameters created at once, the objective's cache sized to
the configuration."""

from __future__ import annotations

import pyro
import pytest
from small_slam import SMALL

from pyro_slam.slam import SLAM, with_overrides
from simulators import simulate_traversal


@pytest.fixture(scope="module")
def traversal():
    return simulate_traversal("simple-small", steps=6, seed=0)


def test_assemble_sets_the_run_up_from_its_configuration(traversal):
    plain = SLAM(traversal, SMALL)
    assert plain.heading is None and plain.model.heading is None
    assert plain.inserter is None  # SMALL inserts no scans
    with plain.scope():
        names = set(pyro.get_param_store().keys())
    assert {"map_loc", "map_scale"} <= {n.split(".")[-1] for n in names}  # created at once
    assert plain.cache.z.shape[:2] == (traversal.num_steps, SMALL.training.cache_particles)
    cfg = with_overrides(SMALL, {"heading": {}, "emission": {"insert": {}}})
    full = SLAM(traversal, cfg)
    assert full.heading is not None and full.model.heading is not None
    assert full.inserter is not None
