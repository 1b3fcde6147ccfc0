"""SLAM speed: each preset on one fixed traversal, online and offline, optionally side by side
with another commit's code.

The traversal is the held-out tuning maze 991 (moderate-medium), driver seed 1, 3000 steps. For
each preset and mode it prints steps per second (online: steps / wall time; offline: the time
per 3000-step traversal), and a breakdown of the online run from a profile of its first
``--profile-steps`` steps: the filter, SVI, scan insertion and everything else. The last line
is one JSON object.

    python -m benchmarks.slam_speed                                   # the default preset
    python -m benchmarks.slam_speed --presets paper,raycast,manhattan --modes online,offline
    python -m benchmarks.slam_speed --against REV --against-config '{"lidar_emission": ...}'

``--against REV`` checks out commit ``REV`` into a temporary git worktree and times its
``pyro-slam slam`` command on the same traversal, in the same run, so that the ratio is measured
side by side (absolute times on a shared machine vary from day to day). A commit without
presets takes the preset's settings as ``--against-config`` (its own JSON format) and
``--against-transition`` (its learned transition file, if the preset uses one). Threads:
``--threads`` for both (torch intra-op threads). ``--smc`` also times the online run with Pyro's
``SMCFilter`` as the filter, next to ours with the same per-particle weights.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from benchmarks._common import add_config_args, slam_config
from pyro_slam.metrics import localisation_error
from pyro_slam.slam import SLAM, presets
from simulators import simulate_traversal
from simulators.maze import make_maze

REPO = Path(__file__).resolve().parents[1]
MAZE, DRIVER_SEED = 991, 1  # a held-out tuning maze, never a test maze
PARTS = {  # profile rows of the online loop -> breakdown
    "filter": ("loop.py", "filter_step"),
    "svi": ("loop.py", "svi_step"),
    "insertion": ("insertion.py", "insert"),
}


def traversal(steps: int):
    maze = make_maze("moderate-medium", MAZE)
    return simulate_traversal(maze, steps=steps, seed=DRIVER_SEED, noise_seed=(DRIVER_SEED, MAZE))


def time_run(tr, config, mode: str, smc: bool = False) -> tuple[float, float]:
    """Wall seconds of one SLAM run (no progress bar, seed 1) and its final position error;
    ``smc``: Pyro's ``SMCFilter`` as the online filter."""
    slam = SLAM(tr, config, seed=1, smc=smc, threads=torch.get_num_threads())
    t0 = time.perf_counter()
    res = slam.run(mode, progress=False)
    wall = time.perf_counter() - t0
    return wall, float(localisation_error(res["mean"], tr.poses)[-1])


def breakdown(tr, config, steps: int) -> dict:
    """Fractions of the online loop's time in the filter, SVI, scan insertion and the rest,
    from a cProfile of its first ``steps`` steps."""
    slam = SLAM(tr.slice(0, steps), config, seed=1, threads=torch.get_num_threads())
    prof = cProfile.Profile()
    prof.enable()
    slam.run("online", progress=False)
    prof.disable()
    stats = pstats.Stats(prof).stats
    total = max(v[3] for k, v in stats.items() if k[2] == "online_sweep")
    out = {}
    for part, (file, func) in PARTS.items():
        out[part] = sum(v[3] for k, v in stats.items() if k[0].endswith(file) and k[2] == func)
    out = {k: v / total for k, v in out.items()}
    out["other"] = max(0.0, 1.0 - sum(out.values()))
    return {k: round(v, 3) for k, v in out.items()}


def time_commit(
    rev: str, tr_path: Path, config: str, transition: str | None, mode: str, threads: int
) -> float:
    """Wall seconds of ``pyro-slam slam`` at commit ``rev`` (a temporary worktree) on the saved
    traversal, from its ``timing.json`` (older commits: ``metrics.json``)."""
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(
            ["git", "-C", str(REPO), "worktree", "add", "--detach", "-q", str(tree), rev],
            check=True,
        )
        try:
            out, cfg = Path(tmp) / "run", Path(tmp) / "config.json"
            cfg.write_text(config)  # (a file: long JSON strings are not always taken inline)
            argv = [
                sys.executable,
                "-m",
                "pyro_slam.cli",
                "slam",
                str(tr_path),
                "--out",
                str(out),
                "--mode",
                mode,
                "--seed",
                "1",
                "--config",
                str(cfg),
            ]
            if transition:
                argv += ["--transition", str(tree / transition)]
            if '"--threads"' in (tree / "pyro_slam" / "cli.py").read_text():
                argv += ["--threads", str(threads)]
            env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": str(threads)}
            run = subprocess.run(argv, cwd=tree, env=env, capture_output=True, text=True)
            if run.returncode:
                raise RuntimeError(f"{rev}: pyro-slam slam failed: {run.stderr.strip()[-500:]}")
            timing = out / "timing.json"  # (older commits: in metrics.json)
            timing = timing if timing.is_file() else out / "metrics.json"
            return float(json.loads(timing.read_text())["wall_time_s"])
        finally:
            subprocess.run(
                ["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)], check=False
            )


def parse(argv):
    p = argparse.ArgumentParser(prog="python -m benchmarks.slam_speed", description=__doc__)
    p.add_argument("--presets", default=presets.DEFAULT, help="comma-separated preset names")
    add_config_args(p, presets.DEFAULT)
    p.add_argument("--modes", default="online,offline")
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--profile-steps", type=int, default=300)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument(
        "--smc",
        action="store_true",
        help="also time the online run with Pyro's SMCFilter as the filter (the same "
        "model, proposal and weights)",
    )
    p.add_argument("--against", metavar="REV", help="also time this commit's code")
    p.add_argument(
        "--against-config",
        default="{}",
        metavar="JSON",
        help="the preset's settings in that commit's --config format",
    )
    p.add_argument(
        "--against-transition",
        metavar="PATH",
        help="its learned transition file (relative to its tree), if the preset uses one",
    )
    args = p.parse_args(argv)
    names = [n for n in args.presets.split(",") if n]
    if unknown := [n for n in names if n not in presets.PRESETS]:
        p.error(f"--presets: unknown {unknown}; presets: {list(presets.PRESETS)}")
    modes = [m for m in args.modes.split(",") if m]
    if bad := [m for m in modes if m not in ("online", "offline")]:
        p.error(f"--modes: {bad}: online or offline")
    if args.steps < 2 or args.profile_steps < 2 or args.threads < 1:
        p.error("--steps and --profile-steps must be >= 2, --threads >= 1")
    configs = {n: slam_config(p, n, args.config) for n in names}
    return args, names, modes, configs


def main(argv=None) -> int:
    args, names, modes, configs = parse(argv)
    torch.set_num_threads(args.threads)
    tr = traversal(args.steps)
    summary = {
        "maze": MAZE,
        "driver_seed": DRIVER_SEED,
        "steps": args.steps,
        "threads": args.threads,
        "presets": {},
    }
    for name in names:
        row = {}
        cfg = configs[name]
        runs = [(mode, mode, cfg, False) for mode in modes]
        if args.smc:  # Pyro's SMCFilter as the filter, same model, proposal and weights
            runs += [("online_smc", "online", cfg, True)]
        for key, mode, config, smc in runs:
            wall, err = time_run(tr, config, mode, smc)
            row[key] = {
                "wall_s": round(wall, 3),
                "steps_per_s": round(args.steps / wall, 2),
                "final_error": round(err, 4),
            }
            print(
                f"{name} {key}: {wall:.1f} s, {args.steps / wall:.1f} steps/s, "
                f"final error {err:.4f}",
                flush=True,
            )
        row["breakdown_online"] = breakdown(tr, configs[name], min(args.profile_steps, args.steps))
        print(f"{name} online breakdown: {row['breakdown_online']}", flush=True)
        summary["presets"][name] = row
    if args.against:
        with tempfile.TemporaryDirectory() as tmp:
            path = tr.save(Path(tmp) / "traversal.npz")
            for mode in modes:
                wall = time_commit(
                    args.against,
                    path,
                    args.against_config,
                    args.against_transition,
                    mode,
                    args.threads,
                )
                ours = summary["presets"][names[0]][mode]["wall_s"]
                summary.setdefault("against", {"rev": args.against, "preset": names[0]})[mode] = {
                    "wall_s": round(wall, 3),
                    "steps_per_s": round(args.steps / wall, 2),
                    "speedup": round(wall / ours, 2),
                }
                print(f"{args.against} {mode}: {wall:.1f} s ({wall / ours:.2f}x ours)", flush=True)
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
