"""The Manhattan-world heading observation (not the paper's model).

Where the walls run along two perpendicular world axes, each scan's straight walls give its
heading modulo a quarter turn: from LiDAR ranges (:func:`~pyro_slam.geometry.wall_direction`)
or from a camera frame's wall edges (:func:`~pyro_slam.geometry.image_wall_direction`). The
filter then samples the heading conditioned on it
(:func:`~pyro_slam.inference.proposals.heading_conditioned`).
"""

from __future__ import annotations

import math

import torch

from ..data import Traversal
from ..geometry import image_background, image_wall_direction, wall_direction
from ..inference import HeadingObservation
from .config import HeadingConfig


def heading_observations(
    traversal: Traversal, obs: torch.Tensor, mask, config: HeadingConfig, image: bool
) -> HeadingObservation:
    """The heading observation of every step of a prepared traversal (``obs [T, N]``,
    ``mask [T, N]`` or None): ``value [T]`` (nan where fewer than ``config.support`` wall
    segments agree within ``config.sigma`` rad)."""
    angles = torch.as_tensor(traversal.beam_angles, dtype=obs.dtype)
    tol = config.sigma
    if image:  # the walls' edges in each frame
        frames = obs.reshape(obs.shape[0], *traversal.metadata["image_shape"])  # [T, H, W]
        columns = angles.reshape(frames.shape[1:])[0]  # [W] column bearings
        direction, support = image_wall_direction(frames, columns, image_background(frames), tol)
    else:
        direction, support = wall_direction(obs, angles, float(traversal.max_range), mask, tol)
    ok = support >= config.support
    value = torch.where(ok, -direction, torch.full_like(direction, math.nan))  # [T]
    return HeadingObservation(value, config.sigma)
