"""Can a pose graph over SLAM's own revisits undo its error? (a diagnostic of the map's warp)

Reads the runs a ``slam_accuracy.py`` call exported (``OUT/runs/<mode>_m*_t*_T*.npz``) and
re-estimates each trajectory as a pose graph, the way graph SLAM would use our filter as its
front end:

- odometry factors: the body-frame increments of the path-integration poses, with the
  transition's per-step residual std ``--sigma-odometry`` (x, y, heading);
- loop closures: whenever the SLAM estimate at step t comes within ``--radius`` of where it was
  at least ``--gap`` steps earlier (the earliest such step s), the pose difference z_t - z_s
  should equal the estimate's, with std ``--sigma-loop`` (position, heading). A filter that
  relocalises on a revisit places z_t relative to the map written at s, so that difference is
  the relative measurement it provides.

The graph is solved for all poses at once (the start pose fixed) by L-BFGS over the odometry
corrections. Prints JSON: mean final and time-averaged position error of the SLAM estimate, of
the pose graph and of path integration, and the number of loop closures per run.

    python benchmarks/slam_pose_graph.py out/s13_shtt_24 --mode online   # 24 runs, ~8 min
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slam_error_sources import load_runs  # noqa: E402  (a sibling script: the runs' loader)

from pyro_slam.metrics import localisation_error  # noqa: E402


def _wrap(a: torch.Tensor) -> torch.Tensor:
    return torch.atan2(torch.sin(a), torch.cos(a))


def _integrate(z0: torch.Tensor, d_body: torch.Tensor, d_heading: torch.Tensor) -> torch.Tensor:
    """Poses ``[T, 3]`` from ``z0 [3]``, body-frame steps ``[T-1, 2]`` and turns ``[T-1]``."""
    h = z0[2] + torch.cat([d_heading.new_zeros(1), torch.cumsum(d_heading, 0)])  # [T]
    c, s = torch.cos(h[:-1]), torch.sin(h[:-1])
    dx = c * d_body[:, 0] - s * d_body[:, 1]  # [T-1]
    dy = s * d_body[:, 0] + c * d_body[:, 1]
    xy = z0[:2] + torch.cat([z0.new_zeros(1, 2), torch.cumsum(torch.stack([dx, dy], -1), 0)])
    return torch.cat([xy, h.unsqueeze(-1)], -1)


def loop_closures(estimate: np.ndarray, radius: float, gap: int) -> np.ndarray:
    """``[L, 2]`` pairs (s, t): the earliest s <= t - gap with |z_s - z_t| < radius"""
    xy = estimate[:, :2]
    pairs = []
    for t in range(gap, len(xy)):
        near = np.nonzero(np.linalg.norm(xy[: t - gap + 1] - xy[t], axis=1) < radius)[0]
        if len(near):
            pairs.append((near[0], t))
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2)


def pose_graph(
    estimate: np.ndarray,
    odometry: np.ndarray,
    radius: float = 0.02,
    gap: int = 300,
    sigma_odometry=(1.3e-4, 1.3e-4, 0.006),
    sigma_loop=(0.01, 0.03),
    iters: int = 300,
) -> tuple[np.ndarray, int]:
    """Poses ``[T, 3]`` from odometry ``[T, 3]`` and the estimate's ``[T, 3]`` loop closures.

    Returns the solved poses and the number of loop closures (0: the odometry as it is).
    """
    if estimate.shape != odometry.shape or estimate.ndim != 2 or estimate.shape[1] != 3:
        raise ValueError(f"estimate {estimate.shape} and odometry {odometry.shape}: want [T, 3]")
    e = torch.as_tensor(estimate, dtype=torch.float64)  # [T, 3]
    o = torch.as_tensor(odometry, dtype=torch.float64)
    d = o[1:, :2] - o[:-1, :2]  # [T-1, 2]
    c, s = torch.cos(o[:-1, 2]), torch.sin(o[:-1, 2])
    d_body = torch.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)
    d_heading = _wrap(o[1:, 2] - o[:-1, 2])  # [T-1]
    pairs = torch.as_tensor(loop_closures(estimate, radius, gap))  # [L, 2]
    z0 = e[0]
    if len(pairs) == 0:
        return _integrate(z0, d_body, d_heading).numpy(), 0
    i, j = pairs[:, 0], pairs[:, 1]
    rel_xy = e[j, :2] - e[i, :2]  # [L, 2]
    rel_h = _wrap(e[j, 2] - e[i, 2])  # [L]
    so = torch.tensor(sigma_odometry, dtype=torch.float64)
    delta = torch.zeros(len(d_body), 3, dtype=torch.float64, requires_grad=True)  # whitened

    def poses():
        return _integrate(z0, d_body + delta[:, :2] * so[:2], d_heading + delta[:, 2] * so[2])

    opt = torch.optim.LBFGS([delta], max_iter=iters, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-9, tolerance_change=1e-12)  # fmt: skip

    def closure():
        opt.zero_grad()
        z = poses()
        r_xy = (z[j, :2] - z[i, :2] - rel_xy) / sigma_loop[0]
        r_h = _wrap(z[j, 2] - z[i, 2] - rel_h) / sigma_loop[1]
        loss = 0.5 * (delta.pow(2).sum() + r_xy.pow(2).sum() + r_h.pow(2).sum())
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        z = poses()
    z[:, 2] = _wrap(z[:, 2])
    return z.numpy(), len(pairs)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("out", type=Path, help="a slam_accuracy.py --out directory")
    p.add_argument("--mode", default="online", help="online | offline (the runs' file prefix)")
    p.add_argument("--radius", type=float, default=0.02)
    p.add_argument("--gap", type=int, default=300)
    p.add_argument("--sigma-odometry", default="1.3e-4,1.3e-4,0.006")
    p.add_argument("--sigma-loop", default="0.01,0.03")
    args = p.parse_args(argv)
    runs = load_runs(p, args.out, args.mode)
    so = tuple(map(float, args.sigma_odometry.split(",")))
    sl = tuple(map(float, args.sigma_loop.split(",")))
    rows = []
    for z in runs:
        truth, est, pi = z["truth"], z["estimate"], z["pi_poses"]
        graph, n = pose_graph(est, pi, args.radius, args.gap, so, sl)
        errs = [localisation_error(x, truth) for x in (est, graph, pi)]  # 3 x [T]
        rows.append([e[-1] for e in errs] + [e.mean() for e in errs] + [n])
    r = np.asarray(rows)  # [runs, 7]
    out = {"runs": len(runs), "mode": args.mode}
    for k, name in enumerate(("slam", "pose_graph", "pi")):
        out[f"{name}_final_mean"] = round(float(r[:, k].mean()), 4)
        out[f"{name}_final_std"] = round(float(r[:, k].std()), 4)
        out[f"{name}_time_avg_mean"] = round(float(r[:, 3 + k].mean()), 4)
    out["pose_graph_better_final"] = int((r[:, 1] < r[:, 0]).sum())
    out["loop_closures_mean"] = round(float(r[:, 6].mean()), 1)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
