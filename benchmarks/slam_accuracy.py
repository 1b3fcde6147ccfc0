"""SLAM accuracy (paper Section IV-A, Fig. 4): online / offline DVBF-LM vs path integration.

6 test mazes (moderate-medium, maze seeds 1001-1006) x 4 traversals (driver seeds 1-4) of 3000
steps. SLAM runs a preset of :mod:`pyro_slam.slam.presets` (``--preset``, default: the default
preset) with ``--config`` overrides; the ``paper`` preset is the paper's model, whose emission
network and learned transition are the shipped ones (``pyro_slam/pretrained``, trained by
``pyro-slam pretrain`` on maze seed 100, never a test maze). Prints JSON with mean +- std over
runs of the error at t = T and writes a Fig. 4-style plot (median, 50% and 80% bands) of error
and error relative to distance travelled.

    python -m benchmarks.slam_accuracy --out out/slam_accuracy        # full: 24 runs x modes
    python -m benchmarks.slam_accuracy --mazes 2 --traversals 1 --steps 1000 --modes online
    python -m benchmarks.slam_accuracy --preset paper --out out/slam_accuracy_paper
    python -m benchmarks.slam_accuracy --config '{"filter": {"particles": 512}}' --out out/k512
    python -m benchmarks.slam_accuracy --modes online --map-poses true --out out/slam_oracle
    python -m benchmarks.slam_accuracy --traversals 1 --maze-seeds 991,992,993,994,995,996

``--maze-seeds`` runs chosen mazes instead of the first ``--mazes``: test mazes, or the held-out
tuning mazes ``TUNING_SEEDS`` (991-996, never in the test figures) on which options should be
screened before they are run on the test mazes.

Each run's actuation noise is seeded with (traversal, maze seed) (``--per-maze-noise``, the
default). ``--no-per-maze-noise``: the noise follows the traversal seed alone, so the 6 mazes of
a traversal share one noise sequence (the same heading drift, as the rotation noise is added
whatever the controls): 24 runs, 4 draws.

``--map-poses true|pi`` is a diagnostic: the particle cache is pinned to the true (or the
path-integration) poses, so the map is learned there while the filter still localises against
it (:func:`benchmarks._diagnostics.pin_cache`); the gap to the default ``filter`` is what pose
errors written into the map cost.

Each run's result is written to ``OUT/runs/<mode>_m<maze>_t<traversal>.npz`` as it finishes, so
an interrupted benchmark resumes where it stopped (finished runs are not recomputed);
``OUT/config.json`` records the configuration they were made with, and a run with another
configuration into the same ``OUT`` stops with an error instead of mixing the two. Besides the
errors over time each run holds the trajectories ``estimate``, ``truth`` and ``pi_poses``
``[T, 3]`` and the filter's posterior std ``std [T, 3]``; the summary adds the error averaged
over time (less noisy than the final one) and ``std_over_error_median``, the filter's
calibration (1: its position std matches its error), and ``std_over_aligned_error_median``, the
same against the error left after a rigid alignment of the whole trajectory.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from benchmarks._common import (
    MAZE_SEEDS,
    TUNING_SEEDS,
    add_config_args,
    check_out_config,
    parse_maze_seeds,
    slam_config,
)
from benchmarks._diagnostics import pin_cache
from pyro_slam import metrics
from pyro_slam.plotting import plot_error_bands
from pyro_slam.slam import SLAM, path_integration, presets
from simulators import simulate_traversal
from simulators.maze import make_maze
from simulators.world import LidarConfig


def _traversal(
    maze_seed: int, seed: int, steps: int, per_maze_noise: bool = False, world: dict | None = None
):
    """``world``: ``{"lidar": LidarConfig fields, "rotation": rad}`` (None: the paper's)."""
    world = world or {}
    maze = make_maze("moderate-medium", maze_seed)
    noise_seed = (seed, maze_seed) if per_maze_noise else None  # None: the noise follows seed
    lidar = LidarConfig(**world.get("lidar", {}))
    rotation = world.get("rotation", 0.0)
    return simulate_traversal(
        maze, steps=steps, seed=seed, noise_seed=noise_seed, lidar=lidar, rotation=rotation
    )


def _add_world_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("sensor and world (default: the paper's noise-free LiDAR)")
    helps = {
        "range-noise": "Gaussian range noise std, a fraction of the maximum range (e.g. 0.01)",
        "short-prob": "probability of a random short return per beam",
        "dropout-prob": "probability of no return (max range) per beam",
        "rotation": "turn each maze by this angle (rad), which the filter is not told",
    }
    for name, text in helps.items():
        g.add_argument(f"--{name}", type=float, default=0.0, help=text)


def _world(p: argparse.ArgumentParser, args) -> tuple[dict, str]:
    """The simulated world's options and the tag they add to run names."""
    lidar = {k: getattr(args, k) for k in ("range_noise", "short_prob", "dropout_prob")}
    for k, v in lidar.items():
        if not 0.0 <= v < 1.0:
            p.error(f"--{k.replace('_', '-')} must be in [0, 1), got {v}")
    lidar = {k: v for k, v in lidar.items() if v}
    world = {"lidar": lidar, "rotation": args.rotation} if lidar or args.rotation else {}
    tag = "".join(f"_{k[0]}{v:g}" for k, v in lidar.items())
    return world, tag + (f"_rot{args.rotation:g}" if args.rotation else "")


def run_one(job) -> dict:
    """One SLAM run (in a worker process, 1 thread); returns errors over time."""
    mode, maze_seed, seed, steps, config, map_poses, path, per_maze_noise, world = job
    torch.set_num_threads(1)
    tr = _traversal(maze_seed, seed, steps, per_maze_noise, world)
    t0 = time.perf_counter()
    slam = SLAM(tr, config, seed=seed)
    pi = path_integration(tr, slam.model.transition)
    if map_poses != "filter":  # diagnostic: the map is learned at these poses, see --map-poses
        pin_cache(slam, tr.poses if map_poses == "true" else pi, seed=seed)
    res = slam.run(mode, progress=False)
    wall = time.perf_counter() - t0
    out = {
        "slam": metrics.localisation_error(res["mean"], tr.poses),
        "pi": metrics.localisation_error(pi, tr.poses),
        "distance": metrics.distance_travelled(tr.poses),
        "wall_s": wall,
        # trajectories [T, 3] (x, y, heading): SLAM's pose means, the truth, path integration
        "estimate": np.asarray(res["mean"], dtype=np.float32),
        "truth": np.asarray(tr.poses, dtype=np.float32),
        "pi_poses": np.asarray(pi, dtype=np.float32),
        "std": np.asarray(res["std"], dtype=np.float32),  # [T, 3] the filter's posterior std
    }
    if slam.heading is not None:  # the Manhattan frame's error (modulo a quarter turn)
        frame = slam.heading.frame
        out["frame_error"] = metrics.frame_error(frame.mean, world.get("rotation", 0.0))
        out["frame_std"] = math.sqrt(frame.var)  # its guide's std at the end
    np.savez(path, **out)
    final, pi_final = float(out["slam"][-1]), float(out["pi"][-1])
    return {
        "mode": mode,
        "maze": maze_seed,
        "seed": seed,
        "final": final,
        "pi": pi_final,
        "wall_s": wall,
    }


def main(argv=None) -> int:
    p = _parser()
    args = p.parse_args(argv)
    config, mazes, seeds, world, world_tag = _resolve(p, args)
    (args.out / "runs").mkdir(parents=True, exist_ok=True)
    # the run names carry mode, maze, traversal, steps and the diagnostics; the configuration
    # must match the folder's
    check_out_config(args.out / "config.json", {"config": config.to_dict(), **world})
    files, jobs = _jobs(args, config, mazes, seeds, world, world_tag)
    with mp.get_context("spawn").Pool(args.workers) as pool:
        for r in tqdm(pool.imap_unordered(run_one, jobs), total=len(jobs), desc="SLAM runs"):
            tqdm.write(json.dumps(r))
    summary, curves, dist = summarise(files, args, config, mazes, seeds, world)
    plot_error_bands(curves, args.out / "error_bands.png", distance=dist, title="DVBF-LM SLAM")
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.slam_accuracy", description=__doc__.split("\n")[0]
    )
    p.add_argument("--out", type=Path, default=Path("out/slam_accuracy"))
    p.add_argument("--mazes", type=int, default=6)
    p.add_argument(
        "--maze-seeds",
        default=None,
        help=f"comma-separated maze seeds instead of --mazes: test mazes {list(MAZE_SEEDS)} or "
        f"held-out tuning mazes {list(TUNING_SEEDS)} (for screening options)",
    )
    p.add_argument(
        "--traversals",
        default="4",
        help="N: traversals (driver seeds) 1..N; or comma-separated driver seeds, e.g. '3,4' "
        "to split the 24 runs between machines ('3,': seed 3 alone)",
    )
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--modes", default="online,offline")
    add_config_args(p, presets.DEFAULT)
    _add_world_args(p)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument(
        "--map-poses",
        choices=["filter", "true", "pi"],
        default="filter",
        help="diagnostic: learn the map at the true / path-integration poses (pin_cache)",
    )
    p.add_argument(
        "--per-maze-noise",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="seed each run's actuation noise with (traversal, maze seed) (the default); "
        "--no-per-maze-noise: the noise follows the traversal seed alone, so the 6 mazes of one "
        "traversal share one noise sequence",
    )
    return p


def _resolve(p: argparse.ArgumentParser, args):
    """The configuration, mazes, driver seeds, world options and run-name tag of the arguments;
    usage errors exit 2."""
    config = slam_config(p, args.preset, args.config)
    if config.emission.observation != "lidar":
        p.error(f"--preset {args.preset}: a camera emission; this benchmark runs LiDAR SLAM")
    mazes = list(MAZE_SEEDS[: args.mazes])
    if args.maze_seeds is not None:
        mazes = parse_maze_seeds(p, args.maze_seeds, MAZE_SEEDS, TUNING_SEEDS)
    try:
        seeds = [int(v) for v in args.traversals.split(",") if v.strip()]
    except ValueError:
        p.error(f"--traversals: N or comma-separated driver seeds, got {args.traversals!r}")
    if "," not in args.traversals:
        seeds = list(range(1, seeds[0] + 1))
    if not seeds or min(seeds) < 1:
        p.error(f"--traversals needs driver seeds >= 1, got {args.traversals!r}")
    return config, mazes, seeds, *_world(p, args)


def _jobs(args, config, mazes, seeds, world: dict, world_tag: str) -> tuple[dict, list]:
    """Each mode's run files ``OUT/runs/<mode><tags>_m<maze>_t<seed>_T<steps>.npz``, and the
    jobs of :func:`run_one` for those not finished yet."""
    tag = "" if args.map_poses == "filter" else f"_map-{args.map_poses}"
    tag += ("_pn" if args.per_maze_noise else "") + world_tag
    files, jobs = {}, []
    for mode in args.modes.split(","):
        for m in mazes:
            for s in seeds:
                f = args.out / "runs" / f"{mode}{tag}_m{m}_t{s}_T{args.steps}.npz"
                files.setdefault(mode, []).append(f)
                if not f.is_file():
                    job = (mode, m, s, args.steps, config, args.map_poses, f, args.per_maze_noise)
                    jobs.append((*job, world))
    return files, jobs


def summarise(files: dict, args, config, mazes, seeds, world: dict):
    """The summary of the finished runs (per mode and for path integration), the error curves
    ``[R, T]`` to plot by label, and the distance travelled ``[R, T]``."""
    summary = {
        "steps": args.steps,
        "runs_per_mode": len(mazes) * len(seeds),
        "mazes": mazes,
        "preset": args.preset,
        "config": config.to_dict(),
        "map_poses": args.map_poses,
        "per_maze_noise": args.per_maze_noise,
        **world,
    }
    curves = {}
    label = "" if args.map_poses == "filter" else f" (map at {args.map_poses} poses)"
    for mode, paths in files.items():
        data = [np.load(f) for f in paths]
        e = np.stack([d["slam"] for d in data])  # [R, T]
        curves[f"{mode} SLAM{label}"] = e
        pi, dist = np.stack([d["pi"] for d in data]), np.stack([d["distance"] for d in data])
        summary[mode] = _mode_summary(data, e, dist)
    summary["path_integration"] = {
        "final_mean": float(pi[:, -1].mean()),
        "final_std": float(pi[:, -1].std()),
        "relative_final_mean": float((pi[:, -1] / dist[:, -1]).mean()),
    }
    curves["path integration"] = pi
    return summary, curves, dist


def _mode_summary(data: list, e: np.ndarray, dist: np.ndarray) -> dict:
    """One mode's figures over its runs ``data`` (their errors ``e [R, T]``, distances ``dist
    [R, T]``)."""
    out = {
        "final_mean": float(e[:, -1].mean()),
        "final_std": float(e[:, -1].std()),
        "relative_final_mean": float((e[:, -1] / dist[:, -1]).mean()),
        # the error averaged over all steps: a less noisy figure than the final one
        "time_avg_mean": float(e.mean()),
        "wall_s_mean": float(np.mean([d["wall_s"] for d in data])),
    }
    # diagnostic: the error left after a rigid alignment of each whole trajectory to the
    # truth, and that alignment's rotation (a map turned as a whole about the start)
    al = [metrics.aligned_error(d["estimate"], d["truth"]) for d in data]
    out["aligned_final_mean"] = float(np.mean([a[0][-1] for a in al]))
    out["aligned_final_std"] = float(np.std([a[0][-1] for a in al]))
    out["aligning_rotation_abs_mean"] = float(np.mean([abs(a[1]) for a in al]))
    if all("frame_error" in d for d in data):  # the heading observation's frame
        out["frame_error_abs_max"] = float(max(abs(d["frame_error"]) for d in data))
    if all("frame_std" in d for d in data):  # and its guide's calibration: |error| / std
        z = [abs(float(d["frame_error"])) / max(float(d["frame_std"]), 1e-12) for d in data]
        out["frame_std_median"] = float(np.median([d["frame_std"] for d in data]))
        out["frame_error_over_std_median"] = float(np.median(z))
    if all("std" in d for d in data):  # runs from before the std was saved lack it
        # calibration: the filter's position std over its actual error (1.13 for a
        # calibrated Gaussian, metrics.std_over_error), raw and after the rigid alignment
        start = metrics.CALIBRATION_START
        cal = [metrics.calibration(d["std"], d["estimate"], d["truth"], start) for d in data]
        for key in cal[0] if cal else ():
            out[f"{key}_median"] = float(np.median([c[key] for c in cal]))
    return out


if __name__ == "__main__":
    raise SystemExit(main())
