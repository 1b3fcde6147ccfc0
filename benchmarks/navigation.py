"""Navigation (paper Section V, Fig. 6c): success ratio vs A* expansion budget, learned vs truth.

For each test maze (moderate-medium, maze seeds 1001-1006), start/target pairs from a 5 x 5 grid
over free space (start heading 0): plan with hybrid A* (:mod:`pyro_slam.planning`) in the
learned model and, as the upper bound, with the simulator's true geometry and kinematics; execute
the controls open loop in the pymunk World (noise-free, and again with the calibrated actuation
noise); success = final position within 0.05 of the target.

The learned model's map belief ``q(M)`` is fitted with *known poses* (``fit_map`` on a 3000-step
traversal at its true poses, shipped frozen emission), not by SLAM.

A* is deterministic, so one search with the largest budget gives the whole curve: a pair
succeeds at budget B iff the search found the goal within B expansions and the execution ended
within 0.05 of the target.

    python benchmarks/navigation.py --out out/navigation --pairs-limit 4
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

MAZE_SEEDS = (1001, 1002, 1003, 1004, 1005, 1006)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=Path("out/navigation"))
    p.add_argument("--mazes", type=int, default=6)
    p.add_argument("--pairs-limit", type=int, default=0, help="random pairs per maze (0: all)")
    p.add_argument("--max-expansions", type=int, default=1500)
    p.add_argument("--fit-steps", type=int, default=1500)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    import torch

    torch.set_num_threads(1)
    from pyro_slam.planning import GroundTruthEnv, execute, free_grid, learned_env, plan
    from simulators import make_maze

    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    runs = []
    t0 = time.perf_counter()
    for ms in MAZE_SEEDS[: args.mazes]:
        maze = make_maze("moderate-medium", ms)
        pts = free_grid(maze)
        pairs = [(a, b) for a in range(len(pts)) for b in range(len(pts)) if a != b]
        if args.pairs_limit:
            pairs = [pairs[i] for i in rng.choice(len(pairs), args.pairs_limit, replace=False)]
        envs = {
            "learned": learned_env(maze, fit_steps=args.fit_steps)[0],
            "ground_truth": GroundTruthEnv(maze),
        }
        for a, b in pairs:
            start, goal = np.array([*pts[a], 0.0]), pts[b]
            for name, env in envs.items():
                t = time.perf_counter()
                r = plan(env, start, goal, max_expansions=args.max_expansions)
                wall = time.perf_counter() - t
                row = {
                    "maze": ms,
                    "start": a,
                    "goal": b,
                    "planner": name,
                    "found": r.success,
                    "expansions": r.expansions,
                    "steps": len(r.controls),
                    "plan_s": wall,
                }
                for noise_name, noise in (("noiseless", 0), ("noisy", None)):
                    ex, coll = execute(maze, start, r.controls, noise=noise, seed=a * 100 + b)
                    err = float(np.hypot(*(ex[-1, :2] - goal)))
                    row[f"error_{noise_name}"] = err
                    row[f"success_{noise_name}"] = bool(r.success and err <= 0.05)
                    row[f"collisions_{noise_name}"] = int(coll)
                runs.append(row)
                print(json.dumps(row), flush=True)
    budgets = sorted({int(b) for b in np.linspace(100, args.max_expansions, 15)})
    summary = {
        "budgets": budgets,
        "pairs": len(runs) // 2,
        "wall_s": time.perf_counter() - t0,
        "args": {k: str(v) for k, v in vars(args).items()},
    }
    for name in ("learned", "ground_truth"):
        rs = [r for r in runs if r["planner"] == name]
        for nz in ("noiseless", "noisy"):
            summary[f"{name}_{nz}"] = [
                float(np.mean([r[f"success_{nz}"] and r["expansions"] <= b for r in rs]))
                for b in budgets
            ]
        summary[f"{name}_found"] = float(np.mean([r["found"] for r in rs]))
    gt = {
        (r["maze"], r["start"], r["goal"])
        for r in runs
        if r["planner"] == "ground_truth" and r["success_noiseless"]
    }
    ok = [
        r["success_noiseless"]
        for r in runs
        if r["planner"] == "learned" and (r["maze"], r["start"], r["goal"]) in gt
    ]
    summary["learned_success_on_gt_solved"] = float(np.mean(ok)) if ok else float("nan")
    (args.out / "runs.json").write_text(json.dumps(runs, indent=1))
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    _plot(summary, args.out / "navigation.png")
    print(json.dumps({k: v for k, v in summary.items() if k != "args"}))
    return 0


def _plot(s, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, c in (("learned", "tab:blue"), ("ground_truth", "tab:green")):
        ax.plot(s["budgets"], s[f"{name}_noiseless"], "-", color=c, label=f"{name}, noise-free")
        ax.plot(s["budgets"], s[f"{name}_noisy"], "--", color=c, label=f"{name}, actuation noise")
    ax.set_xlabel("A* expansion budget")
    ax.set_ylabel("success ratio")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"pose-to-pose navigation, {s['pairs']} pairs")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
