"""Small pose-geometry helpers shared by the model, filters, planners and metrics (torch)."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from slamdata.angles import wrap_angle  # noqa: F401 (the one angle helper, re-exported)


def interleave(x: torch.Tensor, y: torch.Tensor, dtype=None) -> torch.Tensor:
    """``torch.stack([x, y], -1).to(dtype)`` for ``x, y [...]``: ``[..., 2]``, written into one
    buffer (a last-axis ``stack`` of large tensors runs several times slower on CPU). Tensor
    subclasses (Pyro's provenance tracking, :func:`pyro.infer.inspect.get_dependencies`) go
    through ``torch.stack``, which they follow; item assignment into a new buffer they cannot."""
    if type(x) is not torch.Tensor or type(y) is not torch.Tensor:
        return torch.stack(torch.broadcast_tensors(x, y), -1).to(dtype or x.dtype)
    out = torch.empty(*x.shape, 2, dtype=dtype or x.dtype, device=x.device)
    out[..., 0] = x
    out[..., 1] = y
    return out


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


class WallDirection(NamedTuple):
    """A scan's wall direction (:func:`wall_direction`), each ``[...]``: ``direction`` in
    ``[0, pi / 2)``; ``support``, the number of agreeing segments; ``length2``, their summed
    squared lengths; ``scatter``, the direction's standard error from their spread."""

    direction: torch.Tensor
    support: torch.Tensor
    length2: torch.Tensor
    scatter: torch.Tensor


def wall_direction(
    ranges: torch.Tensor,
    angles: torch.Tensor,
    max_range: float,
    mask: torch.Tensor | None = None,
    tol: float = 1e-3,
) -> WallDirection:
    """The direction of a scan's straight walls modulo ``pi / 2``, in the sensor's frame.

    Each pair of neighbouring hits ``h_i, h_{i+1}`` (``h_i = r_i e_i``) spans a segment whose
    direction, modulo ``pi / 2``, is that of the wall both lie on, or an arbitrary one where the
    pair straddles a corner or a depth jump. In a rectilinear (Manhattan) world every wall
    gives the same value, so the value shared by most segments (within ``tol`` rad, modulo
    ``pi / 2``) is taken -- the mean of the agreeing segments, weighted by their squared
    lengths (a segment's direction error falls with its length) -- with its support, the number
    of segments that share it. Only segments with an agreeing neighbour count (three hits on
    one straight wall): a segment across a corner or a depth jump rarely has one, and chords
    of a curved wall never agree with their neighbours, so a round room gives no support. A
    world heading ``phi`` is consistent with the scan if ``phi + direction`` is the walls' own
    direction (a multiple of ``pi / 2`` for walls along the world axes).

    Args:
        ranges: ``[..., B]`` readings along ``angles [B]`` (relative to the heading, increasing
            around the full circle, so the first and last beams are neighbours).
        max_range: readings ``>= max_range`` are no hits.
        mask: ``[..., B]`` valid readings (None: all).
        tol: segments whose directions differ by less than this (rad, modulo ``pi / 2``) agree.
    Returns:
        a :class:`WallDirection` of ``[...]`` tensors; support 0 or 1 means no straight wall and
        the direction is meaningless.
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
    diff = wrap_angle(diff, quarter)
    agree = (diff.abs() < tol) & ok.unsqueeze(-1) & ok.unsqueeze(-2)  # [..., B, B]
    support = torch.where(ok, agree.sum(-1), torch.zeros_like(ok, dtype=torch.long))  # [..., B]
    best = support.argmax(-1, keepdim=True)  # [..., 1]
    members = agree.gather(-2, best.unsqueeze(-1).expand(*best.shape, agree.shape[-1]))[..., 0, :]
    # only segments with an agreeing neighbour (three hits on one straight wall) count
    members = members & (torch.roll(members, 1, -1) | torch.roll(members, -1, -1))
    l2 = (d * d).sum(-1) * members  # [..., B] squared lengths of the agreeing segments
    rel = torch.gather(diff, -2, best.unsqueeze(-1).expand(*best.shape, diff.shape[-1]))[..., 0, :]
    centre = a.gather(-1, best)[..., 0]  # [...] the best segment's direction
    shift = (l2 * rel).sum(-1) / l2.sum(-1).clamp_min(1e-30)  # weighted mean offset from it
    direction = torch.remainder(centre - shift, quarter)
    support = members.sum(-1)  # [...]
    # the weighted mean's standard error from the agreeing segments' own scatter
    res = (rel - shift.unsqueeze(-1)) * members
    n = members.sum(-1).to(l2.dtype)
    scatter = (l2**2 * res**2).sum(-1).sqrt() / l2.sum(-1).clamp_min(1e-30)
    scatter = scatter * (n / (n - 1).clamp_min(1)).sqrt()
    return WallDirection(direction, support, l2.sum(-1), scatter)


def range_noise(
    ranges: torch.Tensor, angles: torch.Tensor, max_range: float, mask=None, max_turn: float = 0.3
) -> float:
    """A robust estimate of a range sensor's noise std from its scans ``[..., B]``: the distance
    of each hit from the line through its two neighbouring hits, over the triples on one
    straight wall (turn below ``max_turn`` rad), as ``1.4826 median / sqrt(1.5)`` (the middle
    point's own noise plus half of each neighbour's). ``0.0`` for noise-free straight walls."""
    e = torch.stack([torch.cos(angles), torch.sin(angles)], -1).to(ranges.dtype)  # [B, 2]
    h = ranges.unsqueeze(-1) * e  # [..., B, 2]
    hit = ranges < max_range * (1 - 1e-3)
    if mask is not None:
        hit = hit & mask.bool()
    prev, nxt = torch.roll(h, 1, -2), torch.roll(h, -1, -2)
    ok = hit & torch.roll(hit, 1, -1) & torch.roll(hit, -1, -1)
    chord = nxt - prev
    n = chord.norm(dim=-1).clamp_min(1e-12)
    dist = ((h - prev)[..., 0] * chord[..., 1] - (h - prev)[..., 1] * chord[..., 0]).abs() / n
    a, b = h - prev, nxt - h
    turn = torch.atan2(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0], (a * b).sum(-1)).abs()
    dist = dist[ok & (turn < max_turn)]
    return float(1.4826 * dist.median() / math.sqrt(1.5)) if dist.numel() else 0.0


def _halves(H: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Row indices of the upper and lower half, outwards from the horizon ``[H/2]`` each."""
    return torch.arange(H // 2 - 1, -1, -1), torch.arange(H // 2, H)


def _wall_runs(images: torch.Tensor, tol: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The wall's brightness at the horizon ``[..., W]`` and, per half, how many rows from the
    horizon outwards keep it ``[..., 2, W]`` (0 where the two horizon rows differ)."""
    H = images.shape[-2]
    wall = images[..., H // 2 - 1, :]  # [..., W]
    at_horizon = (images[..., H // 2, :] - wall).abs() < tol
    runs = []
    for half in _halves(H):
        full = (images[..., half, :] - wall.unsqueeze(-2)).abs() < tol  # [..., H/2, W]
        runs.append(torch.cumprod(full.long(), -2).sum(-2) * at_horizon)
    return wall, torch.stack(runs, -2)


def _row_at(x: torch.Tensor, i: torch.Tensor, shape) -> torch.Tensor:
    """``x [..., R, W]`` (broadcast to ``shape``) at row ``i [..., W]`` of each column."""
    return torch.gather(x.expand(*shape), -2, i.unsqueeze(-2))[..., 0, :]


def image_background(images: torch.Tensor, tol: float = 1e-4) -> torch.Tensor:
    """The floor / ceiling brightness of each image row, from the frames alone (no poses).

    In a column whose wall ends ``k`` rows from the horizon (:func:`image_wall_extents`), the
    rows ``k + 2`` and more from it see only floor or ceiling, whose brightness depends on the
    row alone: a row's background is the median of those pixels over all frames and columns.

    Args:
        images: ``[N, H, W]`` frames.
        tol: as in :func:`image_wall_extents`.
    Returns:
        ``[H]`` background brightness per row (nan: never seen, e.g. at the horizon).
    """
    H = images.shape[-2]
    _, runs = _wall_runs(images, tol)  # [N, 2, W]
    out = torch.full((H,), math.nan, dtype=images.dtype)
    for side, half in enumerate(_halves(H)):
        for j, row in enumerate(half.tolist()):
            free = runs[:, side, :] <= j - 2  # [N, W]
            if free.any():
                out[row] = images[:, row, :][free].median()
    return out  # [H]


def image_wall_extents(
    images: torch.Tensor, background: torch.Tensor, min_contrast: float = 0.05, tol: float = 1e-4
) -> torch.Tensor:
    """How far the wall seen in each column reaches above and below the horizon, in rows.

    The camera draws a wall at perpendicular (z-) depth ``d`` from ``horizon - f a / d`` to
    ``horizon + f b / d`` and blends a partly covered row as ``c wall + (1 - c) background``
    (:class:`simulators.camera.Camera`). The wall fills the two rows at the horizon with one
    brightness; counting the rows that keep it, outwards, and reading the coverage ``c`` of the
    first row that does not (from ``background``) gives each edge's distance from the horizon,
    ``f a / d`` and ``f b / d``: both proportional to the inverse depth, without knowing ``f``,
    ``a`` or ``b``.

    Args:
        images: ``[..., H, W]`` frames (``H`` even, horizon between rows ``H/2 - 1`` and ``H/2``).
        background: ``[H]`` per-row floor / ceiling brightness (:func:`image_background`).
        min_contrast: an edge is measured only where wall and background differ by this much
            (in the edge row and the row inside it).
        tol: rows within this of the horizon's brightness are fully covered.
    Returns:
        ``[..., 2, W]`` the top and bottom extents (rows); nan where not measurable (no wall
        at the horizon, a wall filling the image to its border, too little contrast, unknown
        background).
    """
    H = images.shape[-2]
    if H % 2 or background.shape != (H,):
        raise ValueError(
            f"images [..., H, W] need an even H and background [H]; got {tuple(images.shape)} "
            f"and {tuple(background.shape)}"
        )
    h0 = H // 2
    wall, runs = _wall_runs(images, tol)  # [..., W], [..., 2, W]
    extents = []
    for side, half in enumerate(_halves(H)):
        img, bg = images[..., half, :], background[half].unsqueeze(-1)  # [..., h0, W], [h0, 1]
        k = runs[..., side, :]  # [..., W] fully covered rows from the horizon
        edge, inner = k.clamp(max=h0 - 1), (k - 1).clamp(min=0)
        b_edge, b_inner = _row_at(bg, edge, img.shape), _row_at(bg, inner, img.shape)
        contrast = torch.minimum((wall - b_edge).abs(), (wall - b_inner).abs())
        ok = (k > 0) & (k < h0) & (contrast > min_contrast)  # nan contrast: False
        c = (_row_at(img, edge, img.shape) - b_edge) / torch.where(
            ok, wall - b_edge, torch.ones_like(wall)
        )
        ok = ok & (c > -tol) & (c < 1 + tol)
        extents.append(torch.where(ok, k + c.clamp(0, 1), torch.full_like(c, math.nan)))
    return torch.stack(extents, -2)  # [..., 2, W]


def image_wall_direction(
    images: torch.Tensor,
    angles: torch.Tensor,
    background: torch.Tensor,
    tol: float = 1e-3,
    min_contrast: float = 0.05,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`wall_direction` for a first-person camera: the walls' direction modulo ``pi / 2``.

    Each edge of the walls (:func:`image_wall_extents`) gives the inverse depth of every column
    up to one scale, i.e. the wall points ``(1, tan(angle)) / extent`` in the camera's frame up
    to a scale, which leaves their directions unchanged; the top and bottom edges are two such
    partial scans whose segments vote together.

    Args:
        images: ``[..., H, W]`` frames.
        angles: ``[W]`` each column's bearing relative to the heading.
        background: ``[H]`` (:func:`image_background`).
        tol, min_contrast: as in :func:`wall_direction` and :func:`image_wall_extents`.
    Returns:
        ``(direction [...] in [0, pi / 2), support [...])`` as :func:`wall_direction`.
    """
    ext = image_wall_extents(images, background, min_contrast)  # [..., 2, W]
    ranges = 1.0 / (ext * torch.cos(angles).to(ext.dtype))  # [..., 2, W] up to a scale
    gap = torch.full_like(ranges[..., :1], math.inf)
    ranges = torch.cat([ranges, gap], -1).flatten(-2)  # [..., 2 (W + 1)] a no-hit between scans
    a = torch.cat([angles, angles[:1]]).repeat(2)
    hit = torch.isfinite(ranges)
    out = wall_direction(torch.where(hit, ranges, torch.zeros_like(ranges)), a, math.inf, hit, tol)
    return out[0], out[1]
