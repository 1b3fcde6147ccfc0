"""How well the ray-cast LiDAR map fits the scans after a short online SLAM run (docs/benchmarks.md,
"Session 24").

Runs online SLAM with the ray-cast emission (``SHIPPED_FILTER`` plus ``lidar_emission="raycast"``
on a 64 x 64 map, and ``--set`` overrides) for ``--steps`` steps of traversal 1 of each maze, with
the map learned at the filter's poses or, ``--map-poses true``, at the true poses. Then it reads
the final map's mean at the true poses and at the estimates of every step and compares with the
scans, on the beams that hit a wall (reading below 0.5): the RMS residual, and the mean residual
of the three beams ahead and behind (positive: the map predicts too long a range, i.e. walls too
thin). Prints one JSON line per maze, then a summary line.

    python benchmarks/ray_map_fit.py --maze-seeds 991,992,993 --steps 300
    python benchmarks/ray_map_fit.py --maze-seeds 991,992,993 --steps 300 --map-poses true
    python benchmarks/ray_map_fit.py --maze-seeds 991,992,993 --steps 300 --set lr_map=0.1
    python benchmarks/ray_map_fit.py --oracle --maze-seeds 991    # the wall map, no SLAM
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from _common import parse_maze_seeds
from slam_accuracy import MAZE_SEEDS, TUNING_SEEDS, _traversal
from slam_trace import parse_overrides

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

RAYCAST = {"lidar_emission": "raycast", "map_resolution": 1 / 63}
HIT = 0.5  # readings below this hit a wall (the sensor's range is 0.53)


def residual_stats(pred: np.ndarray, obs: np.ndarray) -> dict:
    """Residuals ``pred - obs [T, B]`` on the hits: RMS, median absolute, mean ahead / behind
    (beams ``0, 1, B-1`` and ``B/2 - 1 .. B/2 + 1``)."""
    r, hit = pred - obs, obs < HIT
    B = obs.shape[1]
    ahead, behind = [0, 1, B - 1], [B // 2 - 1, B // 2, B // 2 + 1]
    return {
        "rms": float(np.sqrt(np.mean(r[hit] ** 2))),
        "median_abs": float(np.median(np.abs(r[hit]))),
        "mean": float(r[hit].mean()),
        "mean_ahead": float(r[:, ahead][hit[:, ahead]].mean()),
        "mean_behind": float(r[:, behind][hit[:, behind]].mean()),
    }


def run_maze(maze_seed: int, steps: int, over: dict, map_poses: str, oracle: bool) -> dict:
    import torch

    from pyro_slam import metrics
    from pyro_slam.cli import SHIPPED_FILTER, shipped_slam
    from pyro_slam.networks import RayEmission
    from pyro_slam.slam import path_integration

    tr = _traversal(maze_seed, 1, steps, True)
    t0 = time.perf_counter()
    cfg = {"learn_emission": False, **SHIPPED_FILTER, **RAYCAST, **over, "seed": 1}
    slam = shipped_slam(tr, "learned", **cfg)
    out = {"maze": maze_seed, "steps": steps, "map_poses": map_poses, "set": over}
    obs = np.asarray(tr.observations)
    true = torch.as_tensor(tr.poses, dtype=torch.get_default_dtype())
    if oracle:
        M = RayEmission.wall_map(slam.model.grid, tr.walls)
        with torch.no_grad():
            out["at_true"] = residual_stats(slam.model.emission_mean(M, true).numpy(), obs)
        return out
    pi = path_integration(tr, slam.model.transition)
    if map_poses != "filter":
        slam.pin_cache(tr.poses if map_poses == "true" else pi, seed=1)
    res = slam.run("online", progress=False)
    est = np.asarray(res["mean"])
    loc = slam.guide.params()[0].detach()
    with torch.no_grad():
        at_true = slam.model.emission_mean(loc, true).numpy()
        at_est = slam.model.emission_mean(loc, torch.as_tensor(est, dtype=loc.dtype)).numpy()
    out["at_true"] = residual_stats(at_true, obs)
    out["at_estimate"] = residual_stats(at_est, obs)
    out["final_err"] = float(metrics.localisation_error(est, tr.poses)[-1])
    out["pi_final_err"] = float(metrics.localisation_error(pi, tr.poses)[-1])
    out["along_track"] = float(metrics.along_track_error(est, tr.poses)[-1])
    out["wall_s"] = time.perf_counter() - t0
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--maze-seeds", default="991,992,993")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--map-poses", choices=["filter", "true", "pi"], default="filter")
    p.add_argument("--oracle", action="store_true", help="score the wall map instead (no SLAM)")
    p.add_argument("--set", nargs="*", default=[], help="SLAMConfig overrides key=value")
    args = p.parse_args(argv)
    mazes = parse_maze_seeds(p, args.maze_seeds, MAZE_SEEDS, TUNING_SEEDS)
    import torch

    torch.set_num_threads(1)
    over = parse_overrides(args.set)
    from tqdm import tqdm

    rows = []
    for m in tqdm(mazes, desc="mazes"):  # the bar on stderr, one JSON line per maze on stdout
        rows.append(run_maze(m, args.steps, over, args.map_poses, args.oracle))
        print(json.dumps(rows[-1]), flush=True)
    summary = {"summary": True, "mazes": mazes, "map_poses": args.map_poses, "set": over,
               "oracle": args.oracle,
               "rms_at_true_mean": float(np.mean([r["at_true"]["rms"] for r in rows]))}  # fmt: skip
    if not args.oracle:
        summary["final_err_mean"] = float(np.mean([r["final_err"] for r in rows]))
        summary["pi_final_err_mean"] = float(np.mean([r["pi_final_err"] for r in rows]))
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
