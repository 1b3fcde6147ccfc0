"""Navigation (paper Section V, Fig. 6c): success ratio vs A* expansion budget, learned vs truth.

For each test maze (moderate-medium, maze seeds 1001-1006), start/target pairs from a 5 x 5 grid
over free space (start heading 0): plan with hybrid A* (:mod:`pyro_slam.planning`) in the
learned model and, as the upper bound, with the simulator's true geometry and kinematics (the
learned planner also trusts the free space of the agent's real, noise-free scan at the start,
``--start-scan``; :meth:`~pyro_slam.planning.LearnedEnv.with_observation`); execute
the controls open loop in the pymunk World (noise-free, and again with the calibrated actuation
noise); success = final position within 0.05 of the target.

The learned model's map belief ``q(M)`` is fitted with *known poses* (``fit_map`` at the true
poses of a ``--traversal-steps`` traversal, default 6000), or with ``--map-poses slam`` at the
pose means of online DVBF-LM SLAM on that traversal (then no ground truth enters the learned
model: emission and map are both fitted at the SLAM poses; the SLAM run is a preset of
:mod:`pyro_slam.slam.presets`, ``--slam-preset`` (default ``paper``), with ``--slam-config``
overrides). With ``--cover-grid``
(default) the mapping traversal ends with a tour through the grid points its random walk
passed farther than 0.02 from (a few hundred steps: the walk misses some dead ends for
20,000 steps), so every start and target has been seen. The emission is fitted
to the same traversal first (``--emission-steps`` 3000, ``--n-world`` 60 world directions) and
then frozen; ``--emission-steps 0 --n-world 20 --traversal-steps 3000`` uses the shipped
pretrained emission instead.

A* is deterministic, so one search with the largest budget gives the whole curve: a pair
succeeds at budget B iff the search found the goal within B expansions and the execution ended
within 0.05 of the target.

Pose-to-observation (planner ``learned_obs``): per maze the inverse model ``q(z | x)``
(:mod:`pyro_slam.planning.inverse`) is trained once on the mapping traversal's scans; the target
is the simulator's scan at the target position with a random heading, the goal its inferred pose
(the mode), and success is measured against the *true* target position. The inverse model is also
evaluated alone on every grid point with two random headings (encoder mean and mode errors),
next to a check of how ambiguous each target scan is under the *true* geometry (a pose more
than 0.05 away whose true scan differs by less than ``--alias-tol`` mean absolute range), and
of whether a wrong mode is the world's own ambiguity (``mode_far_true_scan_matches``: the
*true* scan at the inferred mode, more than 0.05 from the target, differs from the target scan
by less than ``--alias-tol``). Observation runs are also judged in observation space
(``obs_failure_ratio_scan_*``): a run fails only if the agent ends neither within 0.05 of the
target nor within 0.05 of a pose whose true scan matches the target scan (``--alias-tol``), so an
aliased target reached at its look-alike place counts as reached.

The upper bound for observation targets (planner ``ground_truth_obs``): the truth's own inverse,
:meth:`~pyro_slam.planning.GroundTruthEnv.places` (every place whose true, noise-free scan
matches the target scan, refined; the best one is the goal), planned and executed like
``ground_truth``. The places also measure the targets' *exact* perceptual aliasing: a target
with a look-alike place more than 0.05 away whose true scan differs by less than
``--exact-tol`` (1e-6) cannot be told from it by any inverse reading the scan;
``obs_oracle_expected_failure`` is the failure ratio of a uniform choice among the exact
look-alike places, and ``*_obs_failure_ratio_unaliased`` the failure ratios on the runs whose
target has no exact look-alike.

    python -m benchmarks.navigation --out out/navigation --pairs-limit 4
    python -m benchmarks.navigation --map-poses slam --slam-preset manhattan --out out/nav_slam

Each maze's rows are saved to ``OUT/mazes/m<seed>.json`` when the maze is done; a re-run with the
same settings resumes from them (``wall_s`` then counts only the mazes computed in that run,
``resumed_mazes`` lists the others). ``--maze-seeds`` runs a share of the mazes (the files of
shares run into other ``--out`` folders can be copied into one, whose run then resumes them all):

    python -m benchmarks.navigation --out out/nav_a --maze-seeds 1001,1002 &
    python -m benchmarks.navigation --out out/nav_b --maze-seeds 1003,1004
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks._common import add_config_args, parse_maze_seeds, slam_config

MAZE_SEEDS = (1001, 1002, 1003, 1004, 1005, 1006)
# planner rows per pair: the learned model and the truth, to the pose and to the observation
PLANNERS = ("learned", "ground_truth", "learned_obs", "ground_truth_obs")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.navigation", description=__doc__.split("\n")[0]
    )
    p.add_argument("--out", type=Path, default=Path("out/navigation"))
    p.add_argument("--mazes", type=int, default=6, help="the first N of the 6 test mazes")
    p.add_argument(
        "--maze-seeds", default=None,
        help="comma-separated test-maze seeds (instead of --mazes): a share of the protocol, e.g. "
        "for two processes; the pairs drawn for a maze are the same whichever mazes run",
    )  # fmt: skip
    p.add_argument("--pairs-limit", type=int, default=0, help="random pairs per maze (0: all)")
    p.add_argument("--max-expansions", type=int, default=1500)
    p.add_argument("--fit-steps", type=int, default=1500)
    p.add_argument("--traversal-steps", type=int, default=6000, help="mapping traversal length")
    p.add_argument(
        "--emission-steps", type=int, default=3000,
        help="fit the emission per maze (true poses) for this many steps (0: shipped, frozen)",
    )  # fmt: skip
    p.add_argument("--n-world", type=int, default=60, help="world directions of a fitted emission")
    p.add_argument("--max-std", type=float, default=0.6, help="explored: chart std below this")
    p.add_argument(
        "--check-path", action=argparse.BooleanOptionalAction, default=True,
        help="every step of a primitive must be explored (not only its end pose)",
    )  # fmt: skip
    p.add_argument(
        "--start-scan", action=argparse.BooleanOptionalAction, default=True,
        help="the learned planner also trusts the free space of the real scan at the start",
    )  # fmt: skip
    p.add_argument(
        "--cover-grid",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="end the mapping traversal with a tour through the grid points it missed",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--sleep-steps", type=int, default=3000, help="q(z|x) sleep-phase steps")
    p.add_argument("--inverse-steps", type=int, default=1000, help="q(z|x) ELBO steps")
    p.add_argument("--alias-tol", type=float, default=0.01)
    p.add_argument(
        "--exact-tol", type=float, default=1e-6,
        help="a place whose true scan differs from the target's by less (mean absolute range, "
        "after refinement) is an exact look-alike",
    )  # fmt: skip
    p.add_argument(
        "--map-poses", choices=["true", "slam"], default="true",
        help="poses the emission and q(M) are fitted at: the traversal's true poses (mapping "
        "with known poses) or the pose means of online DVBF-LM SLAM on it",
    )  # fmt: skip
    add_config_args(p, "paper", prefix="slam-")  # --slam-preset, --slam-config
    args = p.parse_args(argv)
    args.slam = slam_config(p, args.slam_preset, args.slam_config, "--slam-config")
    mazes = MAZE_SEEDS[: args.mazes]
    if args.maze_seeds is not None:
        mazes = tuple(parse_maze_seeds(p, args.maze_seeds, MAZE_SEEDS))

    import torch

    torch.set_num_threads(1)
    from simulators import make_maze

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "mazes").mkdir(exist_ok=True)
    runs, targets, resumed = [], [], []
    t0 = time.perf_counter()
    skip = ("out", "mazes", "maze_seeds", "slam", "slam_preset", "slam_config")
    settings = {k: str(v) for k, v in vars(args).items() if k not in skip}
    settings["slam_config"] = "{}"
    if args.map_poses == "slam":  # the SLAM run's configuration
        settings["slam_config"] = json.dumps(args.slam.to_dict(), sort_keys=True)
    # row format: 2 adds the observation-space success, 3 the ground-truth observation-target
    # planner and the exact look-alikes
    settings["rows"] = "3"
    all_pairs = maze_pairs(args.pairs_limit, args.seed)
    for ms in mazes:
        maze = make_maze("moderate-medium", ms)
        pairs = all_pairs[ms]
        done = args.out / "mazes" / f"m{ms}.json"
        if done.exists():
            saved = json.loads(done.read_text())
            if saved["settings"] == settings:
                print(f"maze {ms}: resumed from {done}", file=sys.stderr)
                runs += saved["runs"]
                targets += saved["targets"]
                resumed.append(ms)
                continue
            print(f"maze {ms}: {done} has other settings, recomputing", file=sys.stderr)
        r, t = run_maze(maze, ms, pairs, args)
        tmp = done.with_suffix(".tmp")  # written whole, then renamed: no half-written results
        tmp.write_text(json.dumps({"settings": settings, "runs": r, "targets": t}))
        tmp.replace(done)
        runs += r
        targets += t
    budgets = sorted(
        {int(b) for b in np.linspace(min(100, args.max_expansions), args.max_expansions, 15)}
    )
    summary = {
        "budgets": budgets,
        "pairs": len(runs) // len(PLANNERS),
        "wall_s": time.perf_counter() - t0,
        "resumed_mazes": resumed,
        "args": {k: str(v) for k, v in vars(args).items() if k != "slam"},
        # --map-poses slam: the SLAM run's preset and configuration (None: no SLAM ran)
        "slam_preset": args.slam_preset if args.map_poses == "slam" else None,
        "slam_config": args.slam.to_dict() if args.map_poses == "slam" else None,
    }
    for name in PLANNERS:
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
    obs = [r for r in runs if r["planner"] == "learned_obs"]
    summary["obs_failure_ratio"] = float(np.mean([not r["success_noiseless"] for r in obs]))
    pose_ok = {
        (r["maze"], r["start"], r["goal"])
        for r in runs
        if r["planner"] == "learned" and r["success_noiseless"]
    }
    extra = [
        not r["success_noiseless"] for r in obs if (r["maze"], r["start"], r["goal"]) in pose_ok
    ]
    summary["obs_failure_ratio_on_pose_solved"] = float(np.mean(extra)) if extra else float("nan")
    # the same runs judged in observation space: a failure only if the agent did not reach the
    # target nor any place (within 0.05) whose true scan matches the target scan (--alias-tol)
    for nz in ("noiseless", "noisy"):
        summary[f"obs_failure_ratio_scan_{nz}"] = float(
            np.mean([not r[f"scan_success_{nz}"] for r in obs])
        )
    # the upper bound for observation targets: the truth's inverse (GroundTruthEnv.places, the
    # best-matching pose, exact ties broken by the order of the refinement) and the truth's
    # planner; and what any inverse reading only the scan can expect on these targets: the
    # runs whose target has an exact look-alike place > 0.05 away, and the failure ratio of a
    # uniform choice among the exact look-alikes
    gobs = [r for r in runs if r["planner"] == "ground_truth_obs"]
    summary["ground_truth_obs_failure_ratio"] = float(
        np.mean([not r["success_noiseless"] for r in gobs])
    )
    summary["ground_truth_obs_failure_ratio_scan_noiseless"] = float(
        np.mean([not r["scan_success_noiseless"] for r in gobs])
    )
    summary["obs_target_aliased_exact"] = float(
        np.mean([r["target_lookalikes_exact"] > 0 for r in obs])
    )
    summary["obs_oracle_expected_failure"] = float(
        np.mean([r["target_oracle_failure"] for r in obs])
    )
    for name, rs in (("learned_obs", obs), ("ground_truth_obs", gobs)):
        clear = [not r["success_noiseless"] for r in rs if r["target_lookalikes_exact"] == 0]
        summary[f"{name}_failure_ratio_unaliased"] = float(np.mean(clear)) if clear else None
    # the search's own resolution: where the agent did reach the target, the smallest
    # difference found near it is not 0 (grid 0.01, 1 deg), so a tolerance below its maximum
    # would reject the target itself
    reached = [r["scan_diff_noiseless"] for r in obs if r["success_noiseless"]]
    summary["obs_scan_diff_at_reached_targets"] = (
        {"median": float(np.median(reached)), "max": float(np.max(reached))} if reached else None
    )
    # how the verdict depends on the tolerance (the model's sigma_E is 0.1)
    summary["obs_failure_ratio_scan_noiseless_by_tol"] = {
        f"{tol:g}": float(
            np.mean(
                [
                    not (r["success_noiseless"] or (r["found"] and r["scan_diff_noiseless"] < tol))
                    for r in obs
                ]
            )
        )
        for tol in sorted({0.0025, 0.005, args.alias_tol})
    }
    summary["per_maze"] = _counts(runs)
    em = np.array([t["error_mode"] for t in targets])
    ee = np.array([t["error_encoder"] for t in targets])
    al = np.array([t["aliased"] for t in targets])
    summary["inverse"] = {
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
            np.mean(
                [t["error_mode"] > 0.05 and t["ll_mode"] >= t["ll_true_refined"] for t in targets]
            )
        ),
        "mode_far_true_scan_matches": float(
            np.mean(
                [
                    t["error_mode"] > 0.05 and t["true_scan_diff_at_mode"] < args.alias_tol
                    for t in targets
                ]
            )
        ),
        "mode_within_0.05_not_aliased": float(np.mean(em[~al] <= 0.05)) if (~al).any() else None,
        "fit_s_per_maze": float(np.mean([t["fit_s"] for t in targets])),
        "slam_error": {  # --map-poses slam: per maze, the SLAM run the map was fitted at
            str(t["maze"]): t["slam_error"] for t in targets if t.get("slam_error")
        },
        "infer_s_per_scan": float(np.mean([t["infer_s"] for t in targets])),
    }
    (args.out / "targets.json").write_text(json.dumps(targets, indent=1))
    (args.out / "runs.json").write_text(json.dumps(runs, indent=1))
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    _plot(summary, args.out / "navigation.png")
    print(json.dumps({k: v for k, v in summary.items() if k != "args"}))
    return 0


def _counts(runs: list[dict]) -> dict[str, dict[str, int]]:
    """Per maze and over all (``"all"``), the counts behind the summary's ratios (noise-free
    runs): pairs, ground-truth-solved pairs and the learned planner's successes on them,
    observation targets missed by position and in observation space (``scan_success``), and
    the latter by cause: ``not_found`` (no plan), ``wrong_goal`` (a plan to an inferred goal
    more than 0.05 from the target, ending where the target's view is not), ``execution`` (the
    goal was within 0.05 of the target, the executed controls ended elsewhere); observation
    runs whose target has an exact look-alike place more than 0.05 away, and the ground-truth
    observation-target planner's misses by position."""
    out = {}
    for ms in sorted({r["maze"] for r in runs}):
        by = {
            p: {(r["start"], r["goal"]): r for r in runs if r["maze"] == ms and r["planner"] == p}
            for p in PLANNERS
        }
        solved = [k for k, r in by["ground_truth"].items() if r["success_noiseless"]]
        obs = by["learned_obs"].values()
        missed = [r for r in obs if not r["scan_success_noiseless"]]
        out[str(ms)] = {
            "pairs": len(by["ground_truth"]),
            "gt_solved": len(solved),
            "learned_on_gt_solved": sum(by["learned"][k]["success_noiseless"] for k in solved),
            "obs_missed": sum(not r["success_noiseless"] for r in obs),
            "obs_missed_scan": len(missed),
            "obs_missed_scan_not_found": sum(not r["found"] for r in missed),
            "obs_missed_scan_wrong_goal": sum(
                r["found"] and r["inference_error"] > 0.05 for r in missed
            ),
            "obs_missed_scan_execution": sum(
                r["found"] and r["inference_error"] <= 0.05 for r in missed
            ),
            "obs_target_aliased": sum(r.get("target_lookalikes_exact", 0) > 0 for r in obs),
            "gt_obs_missed": sum(
                not r["success_noiseless"] for r in by["ground_truth_obs"].values()
            ),
        }
    out["all"] = {k: sum(c[k] for c in out.values()) for k in next(iter(out.values()), {})}
    return out


def maze_pairs(pairs_limit: int, seed: int) -> dict[int, list[tuple[int, int]]]:
    """The (start, target) grid-point pairs of every test maze: all ordered pairs, or
    ``pairs_limit`` of them drawn at random. Drawn for all mazes in turn from one ``seed``, so a
    maze's pairs do not depend on which mazes a run computes (``--mazes``, ``--maze-seeds``)."""
    from pyro_slam.planning import free_grid
    from simulators import make_maze

    rng = np.random.default_rng(seed)
    out = {}
    for ms in MAZE_SEEDS:
        n = len(free_grid(make_maze("moderate-medium", ms)))
        pairs = [(a, b) for a in range(n) for b in range(n) if a != b]
        if pairs_limit:
            pairs = [pairs[i] for i in rng.choice(len(pairs), pairs_limit, replace=False)]
        out[ms] = pairs
    return out


def observation_targets(pts: np.ndarray, ms: int, seed: int) -> np.ndarray:
    """The observation targets of maze ``ms``: every grid point of ``pts [n, 2]``, two random
    headings each, ``[2 n, 3]`` (own rng: the pairs drawn in main stay those of the
    pose-to-pose runs)."""
    trng = np.random.default_rng([seed, ms])
    return np.concatenate([np.repeat(pts, 2, 0), trng.uniform(-np.pi, np.pi, (2 * len(pts), 1))], 1)


def run_maze(maze, ms: int, pairs, args) -> tuple[list, list]:
    """Fit the learned model of maze ``ms``, evaluate q(z|x), plan and execute ``pairs``.

    Returns the rows of ``runs.json`` and ``targets.json`` for this maze.
    """
    import torch
    from tqdm.auto import tqdm

    from pyro_slam.metrics import heading_error
    from pyro_slam.planning import (
        GroundTruthEnv,
        execute,
        free_grid,
        learned_env,
        lookalikes,
        plan,
    )
    from pyro_slam.planning.inverse import fit_inverse

    runs, targets = [], []
    pts = free_grid(maze)
    tour = pts if args.cover_grid else None
    traversal, poses, slam_err = None, None, None
    if args.map_poses == "slam":
        traversal, poses, slam_err = _slam_poses(maze, tour, args.traversal_steps, args.slam)
    lenv, _, traversal = learned_env(
        maze, traversal=traversal, poses=poses, steps=args.traversal_steps,
        fit_steps=args.fit_steps, emission_steps=args.emission_steps, n_world=args.n_world,
        max_std=args.max_std, tour=tour,
    )  # fmt: skip
    envs = {"learned": lenv, "ground_truth": GroundTruthEnv(maze)}
    t = time.perf_counter()
    inv = fit_inverse(
        lenv, traversal, steps=args.inverse_steps, sleep_steps=args.sleep_steps, seed=ms
    )
    inv_fit_s = time.perf_counter() - t
    tposes = observation_targets(pts, ms, args.seed)  # [2 * 25, 3]
    tscans = envs["ground_truth"].scan(tposes)  # [2 * 25, B]
    t = time.perf_counter()
    mode, ll_mode = (v.numpy() for v in inv.infer(tscans))
    infer_s = (time.perf_counter() - t) / len(tposes)
    # is the model's likelihood higher near the truth than at the mode? (search failure)
    zt = inv.refine(tscans, torch.as_tensor(tposes, dtype=tscans.dtype))
    ll_true = inv.log_likelihood(tscans, zt).detach().numpy()
    enc = inv.infer(tscans, n_samples=0, n_restarts=0, refine_steps=0)[0].numpy()
    # the truth's own inverse: every place whose TRUE scan matches the target's (refined), the
    # best of them the ground-truth planner's goal; exact look-alikes (< --exact-tol) more than
    # 0.05 away are ambiguity that no inverse reading the scan can resolve
    places = envs["ground_truth"].places(tscans.numpy())
    # the world's own ambiguity at the answer: the TRUE scan at the mode vs the target scan
    mode_diff = np.abs(envs["ground_truth"].scan(mode).numpy() - tscans.numpy()).mean(1)
    for i, tp in enumerate(tposes):
        pz, pd = places[i]  # [k, 3], [k]
        n_far, oracle_failure = lookalikes(pz, pd, tp, args.exact_tol)
        targets.append(
            {
                "maze": ms,
                "point": i // 2,
                "pose": tp.tolist(),
                "mode": mode[i].tolist(),
                "error_mode": float(np.hypot(*(mode[i, :2] - tp[:2]))),
                "error_encoder": float(np.hypot(*(enc[i, :2] - tp[:2]))),
                "heading_error_mode": float(heading_error(mode[i, 2], tp[2])),
                "aliased": lookalikes(pz, pd, tp, args.alias_tol)[0] > 0,
                "lookalikes_exact": n_far,
                # a uniform choice among the exact look-alike places misses the target this often
                "oracle_failure": oracle_failure,
                "gt_inverse": pz[0].tolist(),
                "gt_inverse_error": float(np.hypot(*(pz[0, :2] - tp[:2]))),
                "gt_inverse_diff": float(pd[0]),
                "true_scan_diff_at_mode": float(mode_diff[i]),
                "ll_mode": float(ll_mode[i]),
                "ll_true_refined": float(ll_true[i]),
                "fit_s": inv_fit_s,
                "traversal_steps": len(traversal.poses),
                "slam_error": slam_err,
                "infer_s": infer_s,
            }
        )
    for a, b in tqdm(pairs, desc=f"maze {ms} pairs", leave=False):
        start = np.array([*pts[a], 0.0])
        goals = {"learned": pts[b], "ground_truth": pts[b], "learned_obs": mode[2 * b, :2],
                 "ground_truth_obs": places[2 * b][0][0, :2]}  # fmt: skip
        if args.start_scan:  # the agent's own scan at the start: trusted free space
            seen = lenv.with_observation(start, envs["ground_truth"].scan(start)[0].numpy())
        for name in PLANNERS:
            env, goal = envs[name.removesuffix("_obs")], goals[name]
            if args.start_scan and not name.startswith("ground_truth"):
                env = seen
            t = time.perf_counter()
            r = plan(
                env, start, goal, max_expansions=args.max_expansions,
                check_path=args.check_path,
            )  # fmt: skip
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
            if name.endswith("_obs"):
                row["target_heading"] = float(tposes[2 * b, 2])
                row["inference_error"] = float(np.hypot(*(goal - pts[b])))
                row["target_lookalikes_exact"] = targets[2 * b]["lookalikes_exact"]
                row["target_oracle_failure"] = targets[2 * b]["oracle_failure"]
            for noise_name, noise in (("noiseless", 0), ("noisy", None)):
                ex, coll = execute(maze, start, r.controls, noise=noise, seed=a * 100 + b)
                err = float(np.hypot(*(ex[-1, :2] - pts[b])))  # to the TRUE target
                row[f"error_{noise_name}"] = err
                row[f"success_{noise_name}"] = bool(r.success and err <= 0.05)
                row[f"collisions_{noise_name}"] = int(coll)
                if name.endswith("_obs"):  # the place it reached looks like the target
                    d = _scan_match(envs["ground_truth"], maze, ex[-1, :2], tscans[2 * b].numpy())
                    row[f"scan_diff_{noise_name}"] = d
                    row[f"scan_success_{noise_name}"] = bool(
                        row[f"success_{noise_name}"] or (r.success and d < args.alias_tol)
                    )
            runs.append(row)
            tqdm.write(json.dumps(row))
    return runs, targets


def _slam_poses(maze, tour, steps: int, config, seed: int = 1):
    """``--map-poses slam``: online DVBF-LM SLAM with ``config`` (``--slam-preset`` and
    ``--slam-config``) on the mapping traversal. Returns ``(traversal, pose means [T, 3], error
    summary)``; the traversal is the one :func:`~pyro_slam.planning.learned_env` would simulate
    (same seed)."""
    from pyro_slam import metrics
    from pyro_slam.slam import SLAM, path_integration
    from simulators import simulate_traversal

    tr = simulate_traversal(maze, steps=steps, seed=seed, tour=tour)
    slam = SLAM(tr, config, seed=seed)
    est = slam.run("online", progress=False)["mean"]  # [T, 3]
    err = metrics.localisation_error(est, tr.poses)  # [T]
    pi = metrics.localisation_error(path_integration(tr, slam.model.transition), tr.poses)
    summary = {"final": float(err[-1]), "mean": float(err.mean()), "max": float(err.max()),
               "pi_final": float(pi[-1]), "pi_mean": float(pi.mean())}  # fmt: skip
    return tr, est, summary


def _scan_match(gt_env, maze, xy, scan, radius=0.05, spacing=0.01, headings=360) -> float:
    """Smallest mean absolute range difference between the target's true ``scan [B]`` and the
    true scans at the free poses within ``radius`` of position ``xy [2]`` (a ``spacing`` grid
    plus ``xy`` itself, ``headings`` headings each: the agent may turn in place at the end).
    Below ``--alias-tol``, the agent stands within the success radius of a pose that sees what
    the target sees, i.e. it reached the observation even where that observation is aliased."""
    from simulators.world import point_segment_distance

    off = np.arange(-radius, radius + 1e-9, spacing)
    pts = np.array([(dx, dy) for dx in off for dy in off if np.hypot(dx, dy) <= radius])
    pts = np.concatenate([np.zeros((1, 2)), pts]) + np.asarray(xy)[None]  # [P, 2]
    pts = pts[[point_segment_distance(q, maze.walls).min() > 1e-3 for q in pts]]
    grid = _with_headings(pts, headings)  # [P * headings, 3]
    return float(np.abs(gt_env.scan(grid).numpy() - scan[None]).mean(1).min())


def _with_headings(xy, headings: int) -> np.ndarray:
    """Poses ``[P * headings, 3]``: each position of ``xy [P, 2]`` with ``headings`` evenly
    spaced headings in ``[-pi, pi)``."""
    hs = 2 * np.pi * np.arange(headings) / headings - np.pi
    return np.concatenate([np.repeat(xy, headings, 0), np.tile(hs, len(xy))[:, None]], 1)


def _plot(s, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    ax.set_ylabel("success ratio")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"navigation, {s['pairs']} pairs (*_obs: observation targets)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
