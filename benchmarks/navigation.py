"""Navigation (paper Section V, Fig. 6c): pose and observation targets, learned model vs truth.

For each test maze (moderate-medium, maze seeds 1001-1006), start/target pairs from a 5 x 5 grid
over free space (start heading 0): plan with hybrid A* (:mod:`pyro_slam.planning`) in the
learned model and, as the upper bound, with the simulator's true geometry and kinematics (the
learned planner also trusts the free space of the agent's real, noise-free scan at the start,
``--start-scan``; :meth:`~pyro_slam.planning.LearnedEnv.with_observation`); execute the
controls open loop in the pymunk World (noise-free, and again with the calibrated actuation
noise).

The learned model's map belief ``q(M)`` and its emission (``--emission-steps`` 3000, ``--n-world``
60 world directions, then frozen) are fitted on a ``--traversal-steps`` 6000 mapping traversal
that ends (``--cover-grid``) with a tour through the grid points it passed farther than 0.02
from. They are fitted at the traversal's true poses (``--map-poses true``, mapping with known
poses) or at the pose means of online DVBF-LM SLAM on it (``--map-poses slam``: no ground truth
enters the learned model; the SLAM run is a preset of :mod:`pyro_slam.slam.presets`,
``--slam-preset`` (default ``paper``) with ``--slam-config`` overrides; its poses are kept
in ``OUT/mazes/slam_m<seed>.json`` and reused).

**Pose targets** succeed when the agent stops within 0.05 of the target. The learned planner's
agent (:func:`~pyro_slam.planning.seek_pose`) plans; where the target lies in space the map has
not explored and there is no plan, it goes to the place its search reached nearest to the
target, scans there, trusts the scan's free space and plans again (up to ``--observe-rounds``
3 times; the observation-target agent does the same for each of its goals). A* is
deterministic, so one run with the largest budget gives the whole success-vs-budget curve (an
agent's expansions summed over its searches).

**Observation targets** (planner ``learned_obs``): the target is the simulator's scan at the
target grid point with a random heading; the goals are up to ``--hypotheses`` modes of
``p(z | x, M)`` found with the inverse model ``q(z | x)`` (:mod:`pyro_slam.planning.inverse`,
trained once per maze on the mapping traversal's scans), at least ``--mode-separation`` apart.
The agent (:func:`~pyro_slam.planning.seek_observation`) heads for them best first and stops
where its own view (turning on the spot) matches the target scan within ``--accept-tol``, else
returns to the best view; ``--accept-tol 0`` visits every mode and adds, per tolerance, what
each would have decided (``obs_failure_by_accept_tol``: the tolerance is screened on the tuning
mazes with it). Each run records its legs' stops, view differences and verdicts. They are
judged on two criteria (:mod:`pyro_slam.planning.evaluation`):

1. primary, in observation space: the agent stops within 0.05 of a place whose true scan, at
   some heading, differs from the target scan by less than ``--alias-tol`` 0.01 (mean absolute
   difference of the ranges) -- a target seen identically elsewhere is reached at either place;
2. secondary, by position: the agent stops within 0.05 of the target, counted only over the
   targets whose scan has no look-alike (a place more than 0.05 away whose true scan differs by
   less than ``--alias-tol``) anywhere in the maze.

The upper bound for observation targets (planner ``ground_truth_obs``) is the truth's own
inverse, :meth:`~pyro_slam.planning.GroundTruthEnv.places` (every place whose true scan matches
the target scan; the best is the goal), planned and executed like ``ground_truth``.

The JSON object printed last starts with the headline figures: ``obs_failure_ratio_obs_space``,
``obs_failure_ratio_position_unaliased`` over ``unaliased_targets`` runs,
``pose_success_ratio_known_pose_map`` or ``pose_success_ratio_slam_map`` (the learned planner's
pose targets reached, over the pairs the ground-truth planner solves; the other is null) and
``wall_s``. One observation-target run per maze is drawn, plan in the learned belief next to
its execution, in ``OUT/plots/m<seed>_obs.png``.

    python -m benchmarks.navigation --workers 2                      # full sample: 300 pairs
    python -m benchmarks.navigation --quick --workers 2              # 2 mazes, 20 pairs
    python -m benchmarks.navigation --map-poses slam --slam-preset manhattan --workers 2

Each maze's rows are saved to ``OUT/mazes/m<seed>.json`` when the maze is done; a re-run with the
same settings resumes from them (``wall_s`` then counts only the mazes computed in that run,
``resumed_mazes`` lists the others). ``--maze-seeds`` runs a share of the mazes, or the held-out
tuning mazes 991-996 on which options are screened.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from types import SimpleNamespace

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import torch
from tqdm.auto import tqdm

from benchmarks._common import (
    MAZE_SEEDS,
    TUNING_SEEDS,
    add_config_args,
    parse_maze_seeds,
    slam_config,
)
from pyro_slam import metrics
from pyro_slam.planning import (
    NAVIGATION_BENCHMARK,
    GroundTruthEnv,
    Look,
    Mover,
    execute,
    free_grid,
    learned_env,
    lookalikes,
    plan,
    seek_observation,
    seek_pose,
    sensor,
)
from pyro_slam.planning.evaluation import (
    PLANNERS,
    SUCCESS_RADIUS,
    mean_or_none,
    miss_counts,
    observation_reached,
    observation_targets,
    pose_reached,
    reached_within,
    success_ratios,
)
from pyro_slam.planning.inverse import fit_inverse
from pyro_slam.plotting import plot_navigation
from pyro_slam.slam import SLAM, path_integration
from simulators import make_maze, simulate_traversal

SIZES = {"full": (6, 50), "quick": (2, 10)}  # (mazes, pairs per maze)
# row format: 6: the learned planner's agent explores towards a goal without a plan (scans taken)
ROWS = "6"


def main(argv=None) -> int:
    p = _parser()
    args = p.parse_args(argv)
    mazes = _resolve(p, args)
    torch.set_num_threads(1)
    (args.out / "mazes").mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    runs, targets, resumed = run_mazes(mazes, args)
    summary = summarise(runs, targets, args, time.perf_counter() - t0, resumed)
    (args.out / "targets.json").write_text(json.dumps(targets, indent=1))
    (args.out / "runs.json").write_text(json.dumps(runs, indent=1))
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    _plot(summary, args.out / "navigation.png")
    print(json.dumps({k: v for k, v in summary.items() if k != "args"}))
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.navigation", description=__doc__.split("\n")[0]
    )
    p.add_argument("--out", type=Path, default=Path("out/navigation"))
    p.add_argument(
        "--quick",
        action="store_true",
        help="2 mazes, 10 pairs each (instead of all 6 test mazes, 50 pairs each)",
    )
    p.add_argument("--mazes", type=int, default=None, help="the first N of the 6 test mazes")
    p.add_argument(
        "--maze-seeds",
        default=None,
        help="comma-separated maze seeds (instead of --mazes): a share of the test mazes, or the "
        f"held-out tuning mazes {list(TUNING_SEEDS)}; a maze's pairs are the same whichever run",
    )
    p.add_argument("--pairs-limit", type=int, default=None, help="random pairs per maze (0: all)")
    p.add_argument("--workers", type=int, default=1, help="mazes run in parallel (1 thread each)")
    _add_model_args(p)
    add_config_args(p, "paper", prefix="slam-")  # --slam-preset, --slam-config
    return p


def _add_model_args(p: argparse.ArgumentParser) -> None:
    """The learned model's fits, the planner, the targets and the verdicts' tolerances."""
    nav = NAVIGATION_BENCHMARK
    p.add_argument("--max-expansions", type=int, default=nav.max_expansions)
    p.add_argument("--fit-steps", type=int, default=nav.fit_steps)
    p.add_argument(
        "--traversal-steps", type=int, default=nav.traversal_steps, help="mapping traversal length"
    )
    p.add_argument(
        "--emission-steps",
        type=int,
        default=nav.emission_steps,
        help="fit the emission per maze for this many steps (0: shipped, frozen)",
    )
    p.add_argument(
        "--n-world", type=int, default=nav.n_world, help="world directions of a fitted emission"
    )
    p.add_argument(
        "--max-std", type=float, default=nav.max_std, help="explored: chart std below this"
    )
    p.add_argument(
        "--hit-margin",
        type=float,
        default=nav.hit_margin,
        help="the learned planner keeps this far from the mapping scans' returns (0: off)",
    )
    p.add_argument(
        "--check-path",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="every step of a primitive must be explored (not only its end pose)",
    )
    p.add_argument(
        "--start-scan",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the learned planner also trusts the free space of the real scan at the start",
    )
    p.add_argument(
        "--cover-grid",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="end the mapping traversal with a tour through the grid points it missed",
    )
    _add_seek_args(p, nav)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--sleep-steps", type=int, default=3000, help="q(z|x) sleep-phase steps")
    p.add_argument("--inverse-steps", type=int, default=1000, help="q(z|x) ELBO steps")
    p.add_argument(
        "--alias-tol",
        type=float,
        default=0.01,
        help="scans closer than this (mean absolute range difference) look alike",
    )
    p.add_argument(
        "--exact-tol",
        type=float,
        default=1e-6,
        help="a place whose true scan differs from the target's by less (mean absolute range, "
        "after refinement) is an exact look-alike",
    )
    p.add_argument(
        "--map-poses",
        choices=["true", "slam"],
        default="true",
        help="poses the emission and q(M) are fitted at: the traversal's true poses (mapping "
        "with known poses) or the pose means of online DVBF-LM SLAM on it",
    )


def _add_seek_args(p: argparse.ArgumentParser, nav) -> None:
    """The agents: an observation target's hypotheses and when it stops, and (both agents) the
    scans taken towards a goal without a plan."""
    p.add_argument(
        "--hypotheses",
        type=int,
        default=nav.hypotheses,
        help="an observation target's goals: up to this many modes of the inverse model",
    )
    p.add_argument(
        "--mode-separation",
        type=float,
        default=nav.mode_separation,
        help="modes closer than this are one place",
    )
    p.add_argument(
        "--observe-rounds",
        type=int,
        default=nav.observe_rounds,
        help="a goal without a plan: scans taken towards it, each followed by a new plan (0: off)",
    )
    p.add_argument(
        "--accept-tol",
        type=float,
        default=nav.accept_tol,
        help="the agent stops where its own view matches the target scan within this (mean "
        "absolute range difference; 0: visit every mode, then return to the best view)",
    )


def _resolve(p: argparse.ArgumentParser, args) -> tuple[int, ...]:
    """Check the arguments (usage errors exit 2), fill in the sample's size (``--quick`` or the
    full sample) and the SLAM configuration; returns the maze seeds to run."""
    if args.quick and (args.mazes is not None or args.pairs_limit is not None):
        p.error("--quick sets --mazes 2 and --pairs-limit 10: give neither with it")
    n_mazes, n_pairs = SIZES["quick" if args.quick else "full"]
    args.mazes = n_mazes if args.mazes is None else args.mazes
    args.pairs_limit = n_pairs if args.pairs_limit is None else args.pairs_limit
    if not 1 <= args.mazes <= len(MAZE_SEEDS):
        p.error(f"--mazes {args.mazes}: must be 1 to {len(MAZE_SEEDS)}")
    if not 0 <= args.pairs_limit <= 25 * 24:
        p.error(f"--pairs-limit {args.pairs_limit}: must be 0 to 600 (the 5 x 5 grid's pairs)")
    if args.workers < 1:
        p.error(f"--workers {args.workers}: must be at least 1")
    if args.max_expansions < 1:
        p.error(f"--max-expansions {args.max_expansions}: must be at least 1")
    if not args.alias_tol > 0 or not args.exact_tol > 0:
        p.error("--alias-tol and --exact-tol must be positive")
    if args.observe_rounds < 0:
        p.error(f"--observe-rounds {args.observe_rounds}: must be at least 0")
    if args.hypotheses < 1 or not args.mode_separation > 0 or args.accept_tol < 0:
        p.error("--hypotheses must be at least 1, --mode-separation positive, --accept-tol >= 0")
    args.slam = slam_config(p, args.slam_preset, args.slam_config, "--slam-config")
    if args.maze_seeds is not None:
        return tuple(parse_maze_seeds(p, args.maze_seeds, MAZE_SEEDS, TUNING_SEEDS))
    return MAZE_SEEDS[: args.mazes]


def _settings(args) -> dict:
    """What a maze's rows depend on: a saved maze is resumed only with the same settings."""
    skip = ("out", "mazes", "maze_seeds", "quick", "workers", "slam", "slam_preset", "slam_config")
    settings = {k: str(v) for k, v in vars(args).items() if k not in skip}
    settings["slam_config"] = "{}"
    if args.map_poses == "slam":  # the SLAM run's configuration
        settings["slam_config"] = json.dumps(args.slam.to_dict(), sort_keys=True)
    settings["rows"] = ROWS
    return settings


def run_mazes(mazes, args) -> tuple[list, list, list]:
    """The rows of ``runs.json`` and ``targets.json`` of every maze, in the order of ``mazes``,
    and the mazes resumed from ``OUT/mazes``; the others run in ``--workers`` processes."""
    settings, all_pairs = _settings(args), maze_pairs(args.pairs_limit, args.seed)
    done, todo = {}, []
    for ms in mazes:
        f = args.out / "mazes" / f"m{ms}.json"
        saved = json.loads(f.read_text()) if f.exists() else None
        if saved is not None and saved["settings"] == settings:
            print(f"maze {ms}: resumed from {f}", file=sys.stderr)
            done[ms] = (saved["runs"], saved["targets"])
            continue
        if saved is not None:
            print(f"maze {ms}: {f} has other settings, recomputing", file=sys.stderr)
        todo.append(ms)
    jobs = [(ms, all_pairs[ms], args, settings) for ms in todo]
    if args.workers > 1 and len(jobs) > 1:
        ctx = get_context("spawn")
        with ProcessPoolExecutor(min(args.workers, len(jobs)), mp_context=ctx) as pool:
            done.update(zip(todo, pool.map(_maze_job, *zip(*jobs))))
    else:
        done.update((job[0], _maze_job(*job)) for job in jobs)
    runs = [r for ms in mazes for r in done[ms][0]]
    targets = [t for ms in mazes for t in done[ms][1]]
    return runs, targets, [ms for ms in mazes if ms not in todo]


def _maze_job(ms: int, pairs, args, settings: dict) -> tuple[list, list]:
    """:func:`run_maze` in a worker (one torch thread), its rows saved to ``OUT/mazes``."""
    torch.set_num_threads(1)
    runs, targets = run_maze(ms, pairs, args)
    f = args.out / "mazes" / f"m{ms}.json"
    tmp = f.with_suffix(".tmp")  # written whole, then renamed: no half-written results
    tmp.write_text(json.dumps({"settings": settings, "runs": runs, "targets": targets}))
    tmp.replace(f)
    return runs, targets


# ------------------------------------------------------------------------------- summaries
def summarise(runs: list[dict], targets: list[dict], args, wall_s: float, resumed) -> dict:
    """The summary of ``summary.json``: the headline figures first, then the run's settings,
    the success curves and other ratios, the per-maze counts and the inverse model's figures."""
    return {
        **headline(runs, args.map_poses),
        "wall_s": wall_s,
        "map_poses": args.map_poses,
        "pairs": len(runs) // len(PLANNERS),
        "resumed_mazes": resumed,
        "args": {k: str(v) for k, v in vars(args).items() if k != "slam"},
        # --map-poses slam: the SLAM run's preset and configuration (None: no SLAM ran)
        "slam_preset": args.slam_preset if args.map_poses == "slam" else None,
        "slam_config": args.slam.to_dict() if args.map_poses == "slam" else None,
        **details(runs, args),
        "per_maze": miss_counts(runs),
        "inverse": _inverse_summary(targets, args.alias_tol),
    }


def headline(runs: list[dict], map_poses: str) -> dict:
    """The sample's verdicts (:func:`~pyro_slam.planning.evaluation.success_ratios`), the pose
    targets' ratio under the name of the map the learned planner planned in."""
    ratios = success_ratios(runs)
    pose = ratios.pop("pose_success_ratio")
    return {
        **ratios,
        "pose_success_ratio_known_pose_map": pose if map_poses == "true" else None,
        "pose_success_ratio_slam_map": pose if map_poses == "slam" else None,
    }


def details(runs: list[dict], args) -> dict:
    """Success vs A* budget per planner (noise-free and with actuation noise), and the
    observation targets' other figures: by position over all targets, in observation space with
    actuation noise and by tolerance, the truth's inverse and planner, and exact aliasing."""
    top = args.max_expansions
    budgets = sorted({int(b) for b in np.linspace(min(100, top), top, 15)})
    out: dict = {"budgets": budgets}
    for name in PLANNERS:
        rs = [r for r in runs if r["planner"] == name]
        for nz in ("noiseless", "noisy"):
            out[f"{name}_{nz}"] = [
                mean_or_none([r[f"success_{nz}"] and r["expansions"] <= b for r in rs])
                for b in budgets
            ]
        out[f"{name}_found"] = mean_or_none([r["found"] for r in rs])
    obs = [r for r in runs if r["planner"] == "learned_obs"]
    gobs = [r for r in runs if r["planner"] == "ground_truth_obs"]
    out["obs_failure_ratio_position"] = mean_or_none([not r["success_noiseless"] for r in obs])
    out["obs_failure_ratio_obs_space_noisy"] = mean_or_none(
        [not r["scan_success_noisy"] for r in obs]
    )
    # how the verdict depends on the tolerance (the model's sigma_E is 0.1)
    out["obs_failure_ratio_obs_space_by_tol"] = {
        f"{tol:g}": mean_or_none([not reached_within(r, tol) for r in obs])
        for tol in sorted({0.0025, 0.005, args.alias_tol})
    }
    # the search's own resolution: where the agent did reach the target, the smallest scan
    # difference found near it is not 0 (grid 0.01, 1 deg), so a tolerance below its maximum
    # would reject the target itself
    reached = [r["scan_diff_noiseless"] for r in obs if r["success_noiseless"]]
    out["obs_scan_diff_at_reached_targets"] = (
        {"median": float(np.median(reached)), "max": float(np.max(reached))} if reached else None
    )
    # the upper bound: the truth's inverse (its best-matching place) and planner; and what any
    # inverse reading only the scan can expect: the runs whose target has an exact look-alike
    # more than 0.05 away, the failure of a uniform choice among the exact look-alikes
    out["ground_truth_obs_failure_ratio_position"] = mean_or_none(
        [not r["success_noiseless"] for r in gobs]
    )
    out["ground_truth_obs_failure_ratio_obs_space"] = mean_or_none(
        [not r["scan_success_noiseless"] for r in gobs]
    )
    out["obs_target_aliased_exact"] = mean_or_none([r["target_lookalikes_exact"] > 0 for r in obs])
    out["obs_oracle_expected_failure"] = mean_or_none([r["target_oracle_failure"] for r in obs])
    for name, rs in (("learned_obs", obs), ("ground_truth_obs", gobs)):
        clear = [not r["success_noiseless"] for r in rs if r["target_lookalikes_exact"] == 0]
        out[f"{name}_failure_ratio_position_unaliased_exact"] = mean_or_none(clear)
    out["obs_legs_mean"] = mean_or_none([r["legs_noiseless"] for r in obs])
    out["obs_accepted_ratio"] = mean_or_none([r["accepted_noiseless"] is not None for r in obs])
    if args.accept_tol == 0:  # every mode visited: what each tolerance would have decided
        out["obs_failure_by_accept_tol"] = _by_accept_tol(obs)
    return out


def _by_accept_tol(obs: list[dict]) -> dict:
    """From runs that visited every mode (``--accept-tol 0``): per tolerance, the observation
    targets failed in observation space and by position (unaliased), had the agent stopped at
    the first leg whose view matched within it, else at the best view, and the legs walked."""
    out = {}
    for tol in (0.005, 0.01, 0.015, 0.02, 0.03, 0.05):
        picks = [_pick(r["leg_diffs"], tol) for r in obs]
        out[f"{tol:g}"] = {
            "obs_space": mean_or_none(
                [k is None or not r["leg_scan_success"][k] for r, k in zip(obs, picks)]
            ),
            "position_unaliased": mean_or_none(
                [
                    k is None or not r["leg_success"][k]
                    for r, k in zip(obs, picks)
                    if r["target_lookalikes_tol"] == 0
                ]
            ),
            "legs_mean": mean_or_none(
                [len(r["leg_diffs"]) if k is None else k + 1 for r, k in zip(obs, picks)]
            ),
        }
    return out


def _pick(diffs: list, tol: float) -> int | None:
    """The leg an agent accepting views within ``tol`` stops at: the first within it, else the
    best view (None: no leg had a plan)."""
    seen = [i for i, d in enumerate(diffs) if d is not None and np.isfinite(d)]
    for i in seen:
        if diffs[i] < tol:
            return i
    return min(seen, key=lambda i: diffs[i]) if seen else None


def _inverse_summary(targets: list[dict], alias_tol: float) -> dict:
    """The inverse model q(z|x) alone on every target scan: errors of its mode and encoder
    mean, aliasing, the truth's inverse, and whether a far mode is a search failure (the model
    prefers it over the refined truth) or the world's own ambiguity (its true scan matches)."""
    em = np.array([t["error_mode"] for t in targets])
    ee = np.array([t["error_encoder"] for t in targets])
    al = np.array([t["aliased"] for t in targets])
    far = em > 0.05
    return {
        "targets": len(targets),
        "mode_error_median": float(np.median(em)),
        "mode_error_p90": float(np.quantile(em, 0.9)),
        "encoder_error_median": float(np.median(ee)),
        "mode_heading_error_median": float(np.median([t["heading_error_mode"] for t in targets])),
        "mode_within_0.025": float(np.mean(em <= 0.025)),
        "mode_within_0.05": float(np.mean(em <= 0.05)),
        "aliased": float(np.mean(al)),
        "lookalike_exact": float(np.mean([t["lookalikes_exact"] > 0 for t in targets])),
        "oracle_expected_failure": float(np.mean([t["oracle_failure"] for t in targets])),
        "gt_inverse_within_0.05": float(np.mean([t["gt_inverse_error"] <= 0.05 for t in targets])),
        "mode_far_and_model_prefers_it": float(
            np.mean(far & np.array([t["ll_mode"] >= t["ll_true_refined"] for t in targets]))
        ),
        "mode_far_true_scan_matches": float(
            np.mean(far & np.array([t["true_scan_diff_at_mode"] < alias_tol for t in targets]))
        ),
        "mode_within_0.05_not_aliased": float(np.mean(em[~al] <= 0.05)) if (~al).any() else None,
        "fit_s_per_maze": float(np.mean([t["fit_s"] for t in targets])),
        "slam_error": {  # --map-poses slam: per maze, the SLAM run the map was fitted at
            str(t["maze"]): t["slam_error"] for t in targets if t.get("slam_error")
        },
        "infer_s_per_scan": float(np.mean([t["infer_s"] for t in targets])),
    }


def maze_pairs(pairs_limit: int, seed: int) -> dict[int, list[tuple[int, int]]]:
    """The (start, target) grid-point pairs of every test and tuning maze: all ordered pairs,
    or ``pairs_limit`` of them drawn at random. Drawn for all mazes in turn from one ``seed``
    (the test mazes first), so a maze's pairs do not depend on which mazes a run computes."""
    rng = np.random.default_rng(seed)
    out = {}
    for ms in MAZE_SEEDS + TUNING_SEEDS:
        n = len(free_grid(make_maze("moderate-medium", ms)))
        pairs = [(a, b) for a in range(n) for b in range(n) if a != b]
        if pairs_limit:
            pairs = [pairs[i] for i in rng.choice(len(pairs), pairs_limit, replace=False)]
        out[ms] = pairs
    return out


# ------------------------------------------------------------------------------- one maze
def run_maze(ms: int, pairs, args) -> tuple[list, list]:
    """Fit the learned model of maze ``ms``, evaluate q(z|x), plan and execute ``pairs``; the
    first pair's observation-target run is drawn to ``OUT/plots/m<ms>_obs.png``.

    Returns the rows of ``runs.json`` and ``targets.json`` for this maze."""
    maze = make_maze("moderate-medium", ms)
    m = _fit_models(maze, ms, args)
    targets, goals = _targets(maze, ms, m, args)
    runs = []
    for i, (a, b) in enumerate(tqdm(pairs, desc=f"maze {ms} pairs", leave=False)):
        plot = args.out / "plots" / f"m{ms}_obs.png" if i == 0 else None
        runs += _run_pair(maze, ms, (a, b), m, targets, goals, args, plot)
    return runs, targets


def _fit_models(maze, ms: int, args) -> SimpleNamespace:
    """The learned environment of maze ``ms`` (emission and ``q(M)`` fitted at the true or the
    SLAM poses of the mapping traversal), its inverse model, and the truth."""
    pts = free_grid(maze)
    tour = pts if args.cover_grid else None
    traversal, poses, slam_err = None, None, None
    if args.map_poses == "slam":
        traversal, poses, slam_err = _slam_poses(maze, ms, tour, args)
    lenv, _, traversal = learned_env(
        maze,
        traversal=traversal,
        poses=poses,
        steps=args.traversal_steps,
        fit_steps=args.fit_steps,
        emission_steps=args.emission_steps,
        n_world=args.n_world,
        max_std=args.max_std,
        tour=tour,
        hit_margin=args.hit_margin,
    )
    t = time.perf_counter()
    inv = fit_inverse(
        lenv, traversal, steps=args.inverse_steps, sleep_steps=args.sleep_steps, seed=ms
    )
    return SimpleNamespace(
        pts=pts,
        lenv=lenv,
        gt=GroundTruthEnv(maze),
        inv=inv,
        inv_fit_s=time.perf_counter() - t,
        traversal_steps=len(traversal.poses),
        slam_err=slam_err,
    )


def _targets(maze, ms: int, m, args) -> tuple[list, SimpleNamespace]:
    """The observation targets of maze ``ms`` (:func:`observation_targets`), their true scans,
    the inverse model's answers and the truth's places. Returns the rows of ``targets.json`` and
    ``(poses [2 n, 3], scans [2 n, B], mode [2 n, 3], hyps (2 n of [k, 3]), places)`` for the
    runs."""
    tposes = observation_targets(m.pts, ms, args.seed)  # [2 * 25, 3]
    tscans = m.gt.scan(tposes)  # [2 * 25, B]
    t = time.perf_counter()
    hyps = m.inv.modes(tscans, k=args.hypotheses, separation=args.mode_separation)
    mode = torch.stack([h[0] for h in hyps])  # [2 n, 3] the best mode: the first goal
    ll_mode = m.inv.log_likelihood(tscans, mode).detach().numpy()
    mode, hyps = mode.numpy(), [h.numpy() for h in hyps]
    infer_s = (time.perf_counter() - t) / len(tposes)
    # is the model's likelihood higher near the truth than at the mode? (search failure)
    zt = m.inv.refine(tscans, torch.as_tensor(tposes, dtype=tscans.dtype))
    ll_true = m.inv.log_likelihood(tscans, zt).detach().numpy()
    enc = m.inv.infer(tscans, n_samples=0, n_restarts=0, refine_steps=0)[0].numpy()
    # the truth's own inverse: every place whose TRUE scan matches the target's (refined), the
    # best of them the ground-truth planner's goal; exact look-alikes (< --exact-tol) more than
    # 0.05 away are ambiguity that no inverse reading the scan can resolve
    places = m.gt.places(tscans.numpy())
    # the world's own ambiguity at the answer: the TRUE scan at the mode vs the target scan
    mode_diff = np.abs(m.gt.scan(mode).numpy() - tscans.numpy()).mean(1)
    rows = []
    for i, tp in enumerate(tposes):
        pz, pd = places[i]  # [k, 3], [k]
        n_far, oracle_failure = lookalikes(pz, pd, tp, args.exact_tol)
        n_tol = lookalikes(pz, pd, tp, args.alias_tol)[0]  # look-alikes within --alias-tol
        rows.append(
            {
                "maze": ms,
                "point": i // 2,
                "pose": tp.tolist(),
                "mode": mode[i].tolist(),
                "hypotheses": hyps[i].tolist(),
                "error_mode": float(np.hypot(*(mode[i, :2] - tp[:2]))),
                "error_encoder": float(np.hypot(*(enc[i, :2] - tp[:2]))),
                "heading_error_mode": float(metrics.heading_error(mode[i, 2], tp[2])),
                "lookalikes_tol": n_tol,
                "aliased": n_tol > 0,
                "lookalikes_exact": n_far,
                # a uniform choice among the exact look-alike places misses the target this often
                "oracle_failure": oracle_failure,
                "gt_inverse": pz[0].tolist(),
                "gt_inverse_error": float(np.hypot(*(pz[0, :2] - tp[:2]))),
                "gt_inverse_diff": float(pd[0]),
                "true_scan_diff_at_mode": float(mode_diff[i]),
                "ll_mode": float(ll_mode[i]),
                "ll_true_refined": float(ll_true[i]),
                "fit_s": m.inv_fit_s,
                "traversal_steps": m.traversal_steps,
                "slam_error": m.slam_err,
                "infer_s": infer_s,
            }
        )
    return rows, SimpleNamespace(
        poses=tposes, scans=tscans.numpy(), mode=mode, hyps=hyps, places=places
    )


def _run_pair(maze, ms: int, pair, m, targets, tg, args, plot: Path | None) -> list[dict]:
    """Plan and execute pair ``(a, b)`` with each of :data:`PLANNERS`; the observation target is
    point ``b`` seen at its first heading. ``plot``: draw the ``learned_obs`` run there."""
    a, b = pair
    start = np.array([*m.pts[a], 0.0])
    goals = {
        "learned": m.pts[b],
        "ground_truth": m.pts[b],
        "ground_truth_obs": tg.places[2 * b][0][0, :2],
    }
    envs = {"learned": m.lenv, "ground_truth": m.gt}
    if args.start_scan:  # the agent's own scan at the start: trusted free space
        envs["learned"] = m.lenv.with_observation(start, m.gt.scan(start)[0].numpy())
    rows = []
    for name in PLANNERS:
        row = {"maze": ms, "start": a, "goal": b, "planner": name}
        obs = name.endswith("_obs")
        if obs:
            t = targets[2 * b]
            row.update(
                target_heading=float(tg.poses[2 * b, 2]),
                target_lookalikes_tol=t["lookalikes_tol"],
                target_lookalikes_exact=t["lookalikes_exact"],
                target_oracle_failure=t["oracle_failure"],
            )
        if name == "learned_obs":
            _seek_row(maze, m, envs["learned"], start, tg, b, row, args, plot)
            rows.append(row)
            continue
        if name == "learned":
            _pose_row(maze, m, envs["learned"], start, b, row, args)
            rows.append(row)
            continue
        goal = goals[name]
        t = time.perf_counter()
        r = plan(
            envs[name.removesuffix("_obs")],
            start,
            goal,
            max_expansions=args.max_expansions,
            check_path=args.check_path,
        )
        row.update(found=r.success, expansions=r.expansions, steps=len(r.controls))
        row["plan_s"] = time.perf_counter() - t
        if obs:
            row["inference_error"] = float(np.hypot(*(goal - m.pts[b])))
        tscan = tg.scans[2 * b] if obs else None
        _execute(maze, m, start, r, m.pts[b], tscan, row, args.alias_tol, seed=a * 100 + b)
        rows.append(row)
        print(json.dumps(row), file=sys.stderr)
    return rows


def _seek_row(maze, m, env, start, tg, b: int, row: dict, args, plot: Path | None) -> None:
    """The observation target of point ``b``: the agent visits the inverse model's modes
    (:func:`~pyro_slam.planning.seek_observation`), without and with actuation noise, each
    execution deciding from its own views. Adds to ``row`` the verdicts of :func:`_execute`,
    the legs, and (noise-free) each leg's stop, view difference and verdicts."""
    tscan, target, hyps = tg.scans[2 * b], m.pts[b], tg.hyps[2 * b]
    seed = row["start"] * 100 + b
    row["inference_error"] = float(np.hypot(*(hyps[0, :2] - target)))
    row["hypotheses"] = len(hyps)
    for nz, noise in (("noiseless", 0), ("noisy", None)):
        t = time.perf_counter()
        mover = Mover(maze, noise, seed)
        res = seek_observation(
            env,
            start,
            hyps,
            mover,
            Look(m.gt, tscan),
            accept_tol=args.accept_tol,
            sense=sensor(m.gt),
            rounds=args.observe_rounds,
            max_expansions=args.max_expansions,
            check_path=args.check_path,
        )
        stop = res.poses[-1]
        row[f"legs_{nz}"], row[f"accepted_{nz}"] = len(res.goals), res.accepted
        row[f"scans_{nz}"] = res.scans
        row[f"collisions_{nz}"] = mover.collisions
        row[f"error_{nz}"] = float(np.hypot(*(stop[:2] - target)))
        row[f"success_{nz}"] = bool(res.found and row[f"error_{nz}"] <= SUCCESS_RADIUS)
        ok, d = observation_reached(res.found, stop, target, m.gt, tscan, args.alias_tol)
        row[f"scan_diff_{nz}"], row[f"scan_success_{nz}"] = d, ok
        if nz == "noiseless":
            row.update(found=res.found, expansions=res.expansions, steps=len(res.controls))
            row["plan_s"] = time.perf_counter() - t
            row["leg_diffs"] = [d if np.isfinite(d) else None for d in res.diffs]
            _legs_verdicts(res, m, target, tscan, row, args.alias_tol)
            if plot is not None:
                _plot_run(
                    maze, m.lenv, res.as_plan(), res.poses, tg.poses[2 * b], hyps[0], row, plot
                )
    print(json.dumps(row), file=sys.stderr)


def _pose_row(maze, m, env, start, b: int, row: dict, args) -> None:
    """The pose target of point ``b`` in the learned model: the agent plans, exploring towards
    a goal without a plan (:func:`~pyro_slam.planning.seek_pose`), without and with actuation
    noise. Adds to ``row`` the plan's figures, each execution's error, success, collisions and
    the scans it took to explore."""
    target = m.pts[b]
    for nz, noise in (("noiseless", 0), ("noisy", None)):
        t = time.perf_counter()
        mover = Mover(maze, noise, row["start"] * 100 + b)
        res = seek_pose(
            env,
            start,
            target,
            mover,
            sense=sensor(m.gt),
            rounds=args.observe_rounds,
            max_expansions=args.max_expansions,
            check_path=args.check_path,
        )
        ok, err = pose_reached(res.found, res.poses[-1], target)
        row[f"error_{nz}"], row[f"success_{nz}"] = err, ok
        row[f"collisions_{nz}"], row[f"scans_{nz}"] = mover.collisions, res.scans
        if nz == "noiseless":
            row.update(found=res.found, expansions=res.expansions, steps=len(res.controls))
            row["plan_s"] = time.perf_counter() - t
    print(json.dumps(row), file=sys.stderr)


def _legs_verdicts(res, m, target, tscan, row: dict, alias_tol: float) -> None:
    """Each leg's verdicts had the agent stopped there: by position and in observation space
    (``leg_success``, ``leg_scan_success``; None where the leg had no plan)."""
    row["leg_success"] = [
        None if z is None else pose_reached(True, z, target)[0] for z in res.stops
    ]
    row["leg_scan_success"] = [
        None if z is None else observation_reached(True, z, target, m.gt, tscan, alias_tol)[0]
        for z in res.stops
    ]


def _execute(maze, m, start, r, target, tscan, row: dict, alias_tol: float, seed: int):
    """Execute plan ``r`` without and with actuation noise; adds each execution's error to the
    true ``target [2]``, success (:func:`~pyro_slam.planning.evaluation.pose_reached`) and
    collisions to ``row``, and for an observation target (``tscan [B]``, its true scan) the
    verdict in observation space
    (:func:`~pyro_slam.planning.evaluation.observation_reached`). Returns the noise-free
    executed poses ``[T + 1, 3]``."""
    out = None
    for nz, noise in (("noiseless", 0), ("noisy", None)):
        ex, coll = execute(maze, start, r.controls, noise=noise, seed=seed)
        out = ex if out is None else out
        ok, err = pose_reached(r.success, ex[-1], target)
        row[f"error_{nz}"], row[f"success_{nz}"] = err, ok
        row[f"collisions_{nz}"] = int(coll)
        if tscan is not None:  # the place it reached looks like the target
            ok, d = observation_reached(r.success, ex[-1], target, m.gt, tscan, alias_tol)
            row[f"scan_diff_{nz}"], row[f"scan_success_{nz}"] = d, ok
    return out


def _plot_run(maze, lenv, r, executed, target, goal, row: dict, path: Path) -> None:
    """One observation-target run: its plan over the learned belief next to its execution."""
    path.parent.mkdir(parents=True, exist_ok=True)
    verdict = "reached" if row["scan_success_noiseless"] else "missed"
    title = (
        f"maze {row['maze']}, observation target (x: goal inferred from its scan), {verdict} "
        f"in observation space (scan difference {row['scan_diff_noiseless']:.3f})"
    )
    plot_navigation(maze, lenv, r, executed, target[:2], path, title, inferred=goal)


def _slam_poses(maze, ms: int, tour, args):
    """``--map-poses slam``: online DVBF-LM SLAM with ``args.slam`` (``--slam-preset`` and
    ``--slam-config``) on the mapping traversal. Returns ``(traversal, pose means [T, 3], error
    summary)``; the traversal is the one :func:`~pyro_slam.planning.learned_env` would simulate
    (same seed). The poses are kept in ``OUT/mazes/slam_m<ms>.json`` and reused by runs with
    the same configuration and traversal."""
    seed = 1
    tr = simulate_traversal(maze, steps=args.traversal_steps, seed=seed, tour=tour)
    key = {
        "slam_config": args.slam.to_dict(),
        "steps": len(tr.poses),
        "seed": seed,
        "cover_grid": tour is not None,
    }
    key = json.loads(json.dumps(key))  # tuples as lists, as read back
    f = args.out / "mazes" / f"slam_m{ms}.json"
    saved = json.loads(f.read_text()) if f.exists() else None
    if saved is not None and saved["key"] == key:
        return tr, np.array(saved["poses"]), saved["summary"]
    slam = SLAM(tr, args.slam, seed=seed)
    est = slam.run("online", progress=False)["mean"]  # [T, 3]
    err = metrics.localisation_error(est, tr.poses)  # [T]
    pi = metrics.localisation_error(path_integration(tr, slam.model.transition), tr.poses)
    summary = {
        "final": float(err[-1]),
        "mean": float(err.mean()),
        "max": float(err.max()),
        "pi_final": float(pi[-1]),
        "pi_mean": float(pi.mean()),
    }
    est = np.asarray(est)
    f.write_text(json.dumps({"key": key, "poses": est.tolist(), "summary": summary}))
    return tr, est, summary


def _plot(s, path):
    matplotlib.use("Agg")
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, c in (
        ("learned", "tab:blue"),
        ("ground_truth", "tab:green"),
        ("learned_obs", "tab:orange"),
        ("ground_truth_obs", "tab:red"),
    ):
        ax.plot(s["budgets"], s[f"{name}_noiseless"], "-", color=c, label=f"{name}, noise-free")
        ax.plot(s["budgets"], s[f"{name}_noisy"], "--", color=c, label=f"{name}, actuation noise")
    ax.set_xlabel("A* expansion budget")
    ax.set_ylabel("success ratio (*_obs: by position)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"navigation, {s['pairs']} pairs, map at {s['map_poses']} poses")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
