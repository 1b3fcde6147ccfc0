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


def reproject_scan(
    ranges: torch.Tensor,
    angles: torch.Tensor,
    offsets: torch.Tensor,
    max_range: float,
    mask: torch.Tensor | None = None,
    max_turn: float = 0.6,
    min_incidence: float = 0.35,
    wrap: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The scan a LiDAR would read from slightly shifted positions, from one scan's hit points.

    Each beam's wall is taken as the line through its hit point ``h_i = r_i e_i`` along the
    polyline of the neighbouring hits, tangent ``t_i = h_{i+1} - h_{i-1}``; a ray from ``delta``
    along the same world direction ``e_i`` meets it at ``s_i = r_i - (delta x t_i) / (e_i x t_i)``
    (``x`` the 2-D cross product). Exact for straight walls that stay visible; a beam is marked
    invalid where that picture does not hold: a max-range or masked reading (or a masked
    neighbour), a corner or depth jump (the two polyline segments at the hit turn by more than
    ``max_turn`` rad), a grazing ray (``|sin|`` of the incidence angle below ``min_incidence``),
    or ``s`` outside ``(0, max_range)``. (``benchmarks/frontier_ceiling.py`` instead intersects
    each beam with the whole polygon of a world-frame profile: exact for larger shifts, but with
    no test of where that picture fails, so it suits a diagnostic bound, not training targets.)

    Args:
        ranges: ``[..., B]`` readings along the world angles ``angles [..., B]`` (heading plus
            beam angle), in increasing order around the sensor.
        offsets: ``[..., A, 2]`` world-frame shifts of the sensor position.
        max_range: readings ``>= max_range`` are no hits.
        mask: ``[..., B]`` valid readings (None: all).
        wrap: the beams cover the full circle, so the first and last are neighbours.
    Returns:
        ``(ranges [..., A, B], valid [..., A, B])``; invalid entries hold the original reading.
    """
    e = torch.stack([torch.cos(angles), torch.sin(angles)], -1)  # [..., B, 2]
    h = ranges.unsqueeze(-1) * e  # [..., B, 2] hit points relative to the sensor
    hit = ranges < max_range
    if mask is not None:
        hit = hit & mask.bool()
    nxt, prv = torch.roll(h, -1, -2), torch.roll(h, 1, -2)
    ok = hit & torch.roll(hit, -1, -1) & torch.roll(hit, 1, -1)  # [..., B]
    if not wrap:
        ok[..., 0] = False
        ok[..., -1] = False
    a, b = nxt - h, h - prv  # [..., B, 2] the two polyline segments at each hit

    def cross(u, v):
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    turn = torch.atan2(cross(b, a), (a * b).sum(-1)).abs()  # [..., B]
    t = nxt - prv  # [..., B, 2] tangent
    tn = t.norm(dim=-1).clamp_min(1e-12)
    et = cross(e, t)  # [..., B]
    ok = ok & (turn < max_turn) & ((et / tn).abs() > min_incidence)
    d = offsets.unsqueeze(-2)  # [..., A, 1, 2]
    safe = torch.where(ok, et, torch.ones_like(et)).unsqueeze(-2)  # [..., 1, B]
    s = ranges.unsqueeze(-2) - cross(d, t.unsqueeze(-3)) / safe  # [..., A, B]
    valid = ok.unsqueeze(-2) & (s > 0) & (s < max_range)
    return torch.where(valid, s, ranges.unsqueeze(-2).expand_as(s)), valid
