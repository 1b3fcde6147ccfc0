"""How well can a scan at a new position be predicted from the view just behind it?

Diagnostic for online DVBF-LM SLAM (docs/benchmarks.md, "Where the feedback starts"): at the
frontier of the map the chart is essentially the chart of positions already visited, so the
emission predicts the new scan from a view a few steps behind. This script measures the best
case of two read-outs of that older view, with *exact* (ray-cast, noise-free) world-frame range
profiles instead of a learned map, so it bounds what any emission of that kind can do:

* ``copy``: the profile of pose ``t - k`` read at pose ``t``'s beam directions (what a chart
  without geometry does: the view is translated with the agent);
* ``reproject``: the profile's end points form a polygon around pose ``t - k``; the scan at
  pose ``t`` is the distance along each beam to that polygon (the geometry a chart could encode;
  segments between two max-range end points are open).

Prints JSON: RMS and median per-scan RMS error (world units) for each ``n_world`` and lag ``k``.

    python benchmarks/frontier_ceiling.py                 # maze 1001, 3000 steps, ~2 s
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def read_profile(profile: np.ndarray, heading: np.ndarray, beam_angles: np.ndarray) -> np.ndarray:
    """World-frame ``profile [N, n]`` (angles ``2 pi j / n``) read at ``heading [N] + beams``.

    Circular linear interpolation, as :func:`pyro_slam.networks.rotate_scan`: ``[N, B]``.
    """
    n = profile.shape[-1]
    f = np.remainder(heading[:, None] + beam_angles, 2 * np.pi) * (n / (2 * np.pi))
    i0 = np.floor(f).astype(int) % n
    a = f - np.floor(f)
    lo = np.take_along_axis(profile, i0, 1)
    hi = np.take_along_axis(profile, (i0 + 1) % n, 1)
    return lo * (1 - a) + hi * a


def reproject(
    profile: np.ndarray,
    centre: np.ndarray,
    pose: np.ndarray,
    beam_angles: np.ndarray,
    max_range: float,
) -> np.ndarray:
    """Scan at ``pose [N, 3]`` from the polygon of ``profile [N, n]`` seen from ``centre [N, 2]``.

    Returns ``[N, B]``: the nearest intersection of each beam with the closed polygon of the
    profile's end points, ``max_range`` where there is none (open segments are skipped).
    """
    n = profile.shape[-1]
    th = 2 * np.pi * np.arange(n) / n
    ends = centre[:, None, :] + profile[..., None] * np.stack([np.cos(th), np.sin(th)], -1)
    nxt = np.roll(ends, -1, 1)  # [N, n, 2]
    far = profile >= max_range - 1e-9
    open_ = far & np.roll(far, -1, 1)  # [N, n]
    phi = pose[:, 2:3] + beam_angles  # [N, B]
    d = np.stack([np.cos(phi), np.sin(phi)], -1)[:, :, None, :]  # [N, B, 1, 2]
    e = (nxt - ends)[:, None]  # [N, 1, n, 2]
    w = (ends - pose[:, None, :2])[:, None]  # [N, 1, n, 2]
    den = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    den = np.where(np.abs(den) < 1e-12, 1e-12, den)
    s = (w[..., 0] * e[..., 1] - w[..., 1] * e[..., 0]) / den  # distance along the beam
    u = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / den  # position on the segment
    hit = (s > 0) & (u >= 0) & (u <= 1) & ~open_[:, None, :]
    return np.minimum(np.where(hit, s, np.inf).min(-1), max_range)


def ceiling(traversal, n_worlds=(20, 60), lags=(2, 4, 8, 16)) -> dict:
    """Errors of ``copy`` and ``reproject`` against the noise-free scans of ``traversal``."""
    from simulators import raycast

    P, B, R = traversal.poses, traversal.beam_angles, float(traversal.max_range)
    scan = raycast(traversal.walls, P[:, :2], P[:, 2:3] + B, R)  # [T, B], noise-free
    out = {}
    for nw in n_worlds:
        prof = raycast(traversal.walls, P[:, :2], 2 * np.pi * np.arange(nw) / nw, R)  # [T, nw]
        rows = {"self": _stats(read_profile(prof, P[:, 2], B) - scan)}
        for k in lags:
            t = np.arange(k, len(P))
            src = t - k
            rows[f"lag{k}"] = {
                "distance_mean": float(np.linalg.norm(P[t, :2] - P[src, :2], axis=1).mean()),
                "copy": _stats(read_profile(prof[src], P[t, 2], B) - scan[t]),
                "reproject": _stats(reproject(prof[src], P[src, :2], P[t], B, R) - scan[t]),
            }
        out[f"n_world={nw}"] = rows
    return out


def _stats(residual: np.ndarray) -> dict:
    per_scan = np.sqrt((residual**2).mean(-1))
    return {"rms": float(np.sqrt((per_scan**2).mean())), "median": float(np.median(per_scan))}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--maze-seed", type=int, default=1001)
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--seed", type=int, default=1, help="driver seed of the traversal")
    args = p.parse_args(argv)
    from simulators import make_maze, simulate_traversal

    tr = simulate_traversal(make_maze("moderate-medium", args.maze_seed), args.steps, args.seed)
    out = {"maze_seed": args.maze_seed, "steps": args.steps, **ceiling(tr)}
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
