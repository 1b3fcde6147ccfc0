"""Small pose-geometry helpers shared by the model, filters, planners and metrics (torch)."""

from __future__ import annotations

import math

import torch


def wrap_angle(a: torch.Tensor) -> torch.Tensor:
    """Wrap angles to ``[-pi, pi)``."""
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


def rotate_forward(z: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Kinematics of the maze agent: rotate by ``u[..., 0]``, then move ``u[..., 1]`` ahead.

    Args:
        z: poses ``[..., 3]`` (x, y, heading).
        u: controls ``[..., 2]`` (rotation rad, forward offset).
    Returns:
        next poses ``[..., 3]``, heading wrapped.
    """
    h = z[..., 2] + u[..., 0]
    x = z[..., 0] + u[..., 1] * torch.cos(h)
    y = z[..., 1] + u[..., 1] * torch.sin(h)
    return torch.stack([x, y, wrap_angle(h)], dim=-1)


def odometry_delta(z: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Apply a robot-frame odometry increment ``u = (dx, dy, dtheta)`` ``[..., 3]`` to ``z``."""
    c, s = torch.cos(z[..., 2]), torch.sin(z[..., 2])
    x = z[..., 0] + c * u[..., 0] - s * u[..., 1]
    y = z[..., 1] + s * u[..., 0] + c * u[..., 1]
    return torch.stack([x, y, wrap_angle(z[..., 2] + u[..., 2])], dim=-1)
