"""Analytic, vectorised ray / line-segment intersection (the reference range sensor).

A ray ``o + t d`` (``|d| = 1``, ``t >= 0``) meets a segment ``p + s e`` (``0 <= s <= 1``) at
``t = (q x e) / (d x e)``, ``s = (q x d) / (d x e)`` with ``q = p - o`` and ``a x b`` the 2-D cross
product. A parallel segment (``d x e = 0``) is hit only if the ray runs along it (collinear,
within a relative ``1e-9``): at its nearer end, or at ``t = 0`` from a point on it -- the wall's
end face, which a thin-segment test would miss (an agent standing on a wall's line saw straight
through the wall).
"""

from __future__ import annotations

import numpy as np

# Upper bound on N * B * W elements processed at once (keeps temporaries ~ tens of MB).
_CHUNK_ELEMENTS = 2_000_000


def raycast(
    walls: np.ndarray,
    origins: np.ndarray,
    angles: np.ndarray,
    max_range: float,
    return_index: bool = False,
):
    """Distance from each origin along each angle to the nearest wall.

    Args:
        walls: segments ``[W, 4]`` ``(x1, y1, x2, y2)``.
        origins: ray origins ``[N, 2]``.
        angles: absolute ray directions ``[N, B]`` (rad).
        max_range: returned where nothing is hit within range.
        return_index: also return the index of the hit segment (``-1`` for no hit).
    Returns:
        ranges ``[N, B]`` float64 (and hit indices ``[N, B]`` int64 if ``return_index``).
    """
    walls = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 2)
    angles = np.asarray(angles, dtype=np.float64)
    if angles.ndim == 1:
        angles = np.broadcast_to(angles, (origins.shape[0], angles.shape[0]))
    n, b = angles.shape
    ranges = np.full((n, b), float(max_range))
    index = np.full((n, b), -1, dtype=np.int64)
    if walls.shape[0] and n:
        step = max(1, _CHUNK_ELEMENTS // max(1, b * walls.shape[0]))
        for lo in range(0, n, step):
            sl = slice(lo, lo + step)
            ranges[sl], index[sl] = _raycast_chunk(walls, origins[sl], angles[sl], max_range)
    return (ranges, index) if return_index else ranges


def _raycast_chunk(walls, origins, angles, max_range):
    """:func:`raycast` for one chunk: ``[n, 2]``, ``[n, B]`` -> ``[n, B]``, ``[n, B]``."""
    dx, dy = np.cos(angles)[..., None], np.sin(angles)[..., None]  # [n, B, 1]
    px, py = walls[:, 0], walls[:, 1]  # [W]
    ex, ey = walls[:, 2] - px, walls[:, 3] - py  # [W]
    qx = (px - origins[:, 0:1])[:, None, :]  # [n, 1, W]
    qy = (py - origins[:, 1:2])[:, None, :]
    denom = dx * ey - dy * ex  # [n, B, W]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (qx * ey - qy * ex) / denom
        s = (qx * dy - qy * dx) / denom
    length = np.hypot(ex, ey)  # [W]
    parallel = np.abs(denom) <= 1e-12 * length
    hit = ~parallel & (t >= 0) & (s >= 0) & (s <= 1) & (t < max_range)
    t = np.where(hit, t, np.inf)
    # collinear: the origin lies on the segment's line (distance below 1e-9 x its length)
    online = np.abs(qx * ey - qy * ex) <= 1e-9 * length**2  # [n, 1, W]
    if (parallel & online).any():
        t0 = qx * dx + qy * dy  # [n, B, W] ray parameter of the segment's first end
        t1 = t0 + ex * dx + ey * dy  # ... and of its second end
        tc = np.where(t0 * t1 <= 0, 0.0, np.minimum(t0, t1))  # from a point on it: 0
        tc = np.where((parallel & online) & (tc >= 0) & (tc < max_range), tc, np.inf)
        t = np.minimum(t, tc)
    idx = np.argmin(t, axis=-1)  # [n, B]
    best = np.take_along_axis(t, idx[..., None], axis=-1)[..., 0]
    found = np.isfinite(best)
    return np.where(found, best, max_range), np.where(found, idx, -1)
