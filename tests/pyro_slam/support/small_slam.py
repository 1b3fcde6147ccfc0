"""A small online SLAM configuration of the ray-cast emission, shared by the tests of the model's
ray emission, scan insertion and the heading factor."""

from __future__ import annotations

from pyro_slam.model import RayEmission
from pyro_slam.slam import (
    SLAM,
    EmissionConfig,
    FilterConfig,
    SLAMConfig,
    TrainingConfig,
    TransitionConfig,
)

SMALL = SLAMConfig(
    emission=EmissionConfig("raycast", resolution=1 / 31, sigma=0.1, outlier_prob=0.0),
    transition=TransitionConfig("kinematic", scale=(1.0, 1.0, 1.0)),
    filter=FilterConfig(particles=64, proposal="transition"),
    training=TrainingConfig(particles=8, chunk_length=4, chunks=4, every=1),
    heading=None,
)


def ray_slam(tr, config: SLAMConfig = SMALL, samples: int = 24) -> SLAM:
    """SLAM with the ray-cast emission, ``samples`` points per beam."""
    return SLAM(tr, config, emission=RayEmission(tr.beam_angles, tr.max_range, samples))
