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


def wall_direction(
    ranges: torch.Tensor,
    angles: torch.Tensor,
    max_range: float,
    mask: torch.Tensor | None = None,
    tol: float = 1e-3,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The direction of a scan's straight walls modulo ``pi / 2``, in the sensor's frame.

    Each pair of neighbouring hits ``h_i, h_{i+1}`` (``h_i = r_i e_i``) spans a segment whose
    direction, modulo ``pi / 2``, is that of the wall both lie on, or an arbitrary one where the
    pair straddles a corner or a depth jump. In a rectilinear (Manhattan) world every wall
    gives the same value, so the value shared by most segments (within ``tol`` rad, modulo
    ``pi / 2``) is taken, with its support, the number of segments that share it. A world
    heading ``phi`` is then consistent with the scan if ``phi + direction`` is a multiple of
    ``pi / 2`` (walls along the world axes).

    Args:
        ranges: ``[..., B]`` readings along ``angles [B]`` (relative to the heading, increasing
            around the full circle, so the first and last beams are neighbours).
        max_range: readings ``>= max_range`` are no hits.
        mask: ``[..., B]`` valid readings (None: all).
        tol: segments whose directions differ by less than this (rad, modulo ``pi / 2``) agree.
    Returns:
        ``(direction [...] in [0, pi / 2), support [...] integer)``; support 0 or 1 means no
        two segments agree and the direction is meaningless.
    """
    e = torch.stack([torch.cos(angles), torch.sin(angles)], -1).to(ranges.dtype)  # [B, 2]
    h = ranges.unsqueeze(-1) * e  # [..., B, 2] hit points relative to the sensor
    hit = ranges < max_range * (1 - 1e-3)  # [..., B]
    if mask is not None:
        hit = hit & mask.bool()
    ok = hit & torch.roll(hit, -1, -1)  # [..., B] segment i -> i + 1 joins two hits
    d = torch.roll(h, -1, -2) - h
    quarter = math.pi / 2
    a = torch.remainder(torch.atan2(d[..., 1], d[..., 0]), quarter)  # [..., B]
    diff = a.unsqueeze(-1) - a.unsqueeze(-2)  # [..., B, B]
    diff = torch.remainder(diff + quarter / 2, quarter) - quarter / 2
    agree = (diff.abs() < tol) & ok.unsqueeze(-1) & ok.unsqueeze(-2)
    support = torch.where(ok, agree.sum(-1), torch.zeros_like(ok, dtype=torch.long))  # [..., B]
    best = support.argmax(-1, keepdim=True)  # [..., 1]
    return a.gather(-1, best)[..., 0], support.gather(-1, best)[..., 0]
