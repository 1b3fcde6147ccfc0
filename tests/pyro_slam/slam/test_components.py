"""Emission kinds are registrations: a new emission needs one ``register_emission`` call, and
the configuration, the model builder, the memory check and the SLAM runner read its facts."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pyro_slam.model import Emission
from pyro_slam.slam import SLAM, ConfigError, EmissionConfig, SLAMConfig, build_model
from pyro_slam.slam.components import EMISSIONS, EmissionKind, register_emission
from simulators import simulate_traversal


class WallAhead(Emission):
    """A toy LiDAR emission: every beam reads the occupancy of the chart at the pose, squashed
    to the sensor's range (``sigmoid(m) * range``)."""

    map_dim = 1

    def __init__(self, beam_angles, reading_range: float):
        super().__init__()
        self.event_shape = (len(beam_angles),)
        self.reading_range = float(reading_range)

    def mean(self, m, z):
        return (torch.sigmoid(m) * self.reading_range).expand(*m.shape[:-1], self.event_size)


@pytest.fixture
def toy_kind():
    kind = register_emission(
        EmissionKind(
            "wall-ahead", lambda tr, cfg, reach: WallAhead(tr.beam_angles, reach), learned=False
        )
    )
    yield kind
    EMISSIONS.pop("wall-ahead")


def test_an_emission_is_one_registration(toy_kind):
    tr = simulate_traversal("simple-small", steps=20, seed=0)
    cfg = SLAMConfig(emission=EmissionConfig("wall-ahead"))
    assert cfg.emission.observation == "lidar"
    model, guide = build_model(tr, cfg)
    assert isinstance(model.emission, WallAhead) and model.grid.dim == 1
    slam = SLAM(tr, cfg, seed=0)
    assert not slam.model.learn_emission  # the kind says there is nothing to learn
    res = slam.run("online", progress=False)
    assert res["mean"].shape == (20, 3) and np.isfinite(res["mean"]).all()
    with pytest.raises(ConfigError, match="emission.insert .* ray-cast"):
        EmissionConfig("wall-ahead", insert={})  # it does not read the map along rays


def test_an_unregistered_kind_is_refused_naming_the_registered_ones():
    with pytest.raises(ConfigError, match="emission.kind must be one of .*'raycast'"):
        EmissionConfig("wall-ahead")
    with pytest.raises(ValueError, match="observation must be 'lidar' or 'image'"):
        register_emission(EmissionKind("sonar", lambda tr, cfg, reach: None, observation="sonar"))
