"""Measures of navigation: whether an executed plan reached its target, by position or in
observation space, how ambiguous observation targets are, and the ratios over a sample of runs.

A run is judged where the executed controls left the agent (its final position):

* a **pose target** is reached when a plan was found and the agent stopped within
  :data:`SUCCESS_RADIUS` (0.05) of it (:func:`pose_reached`);
* an **observation target** (the true scan at a target pose) is reached in observation space
  when a plan was found and the agent stopped within that radius of the target, or of a place
  whose true scan, at some heading, differs from the target scan by less than a tolerance
  (:func:`scan_reached`, :func:`observation_reached`): a target seen identically at several
  places is reached at any of them.

The ratios (:func:`success_ratios`, :func:`miss_counts`) read run records, one dict per
planner and (start, target) pair, with the keys

* ``maze``, ``start``, ``goal`` (the pair), ``planner`` (one of :data:`PLANNERS`: ``learned``
  and ``ground_truth`` plan to pose targets, ``learned_obs`` and ``ground_truth_obs`` to
  observation targets) and ``found`` (a plan was found);
* ``success_noiseless``: the pose target (for an observation target, the pose it was seen
  from) reached, controls executed without actuation noise (:func:`pose_reached`);
* observation targets also: ``scan_success_noiseless`` and ``scan_diff_noiseless``
  (:func:`observation_reached`), ``inference_error`` (the inferred goal's distance from the
  target), ``target_lookalikes_tol`` and ``target_lookalikes_exact`` (places more than
  :data:`SUCCESS_RADIUS` away that see the target scan within the tolerance, and exactly;
  :func:`~pyro_slam.planning.lookalikes`).
"""

from __future__ import annotations

import numpy as np

from simulators import raycast
from simulators.world import point_segment_distance

from .envs import GroundTruthEnv, lookalikes

SUCCESS_RADIUS = 0.05  # a run reached a place when it stopped this close to it
# the planners of a run record: the learned model and the truth, to a pose and to a scan
PLANNERS = ("learned", "ground_truth", "learned_obs", "ground_truth_obs")


# ------------------------------------------------------------------------------- targets
def observation_targets(points: np.ndarray, maze_seed: int, seed: int) -> np.ndarray:
    """The observation-target poses of maze ``maze_seed``: every point of ``points [n, 2]``
    twice, each with a random heading drawn from ``(seed, maze_seed)``, ``[2 n, 3]``."""
    trng = np.random.default_rng([seed, maze_seed])
    headings = trng.uniform(-np.pi, np.pi, (2 * len(points), 1))
    return np.concatenate([np.repeat(points, 2, 0), headings], 1)


def aliasing(maze, poses: np.ndarray, lidar, tols, spacing: float = 0.01) -> dict:
    """Look-alikes of the target ``poses [n, 3]`` in ``maze`` seen by ``lidar`` (a
    :class:`~simulators.LidarConfig`), for each tolerance of ``tols`` (mean absolute range
    difference): per target the number of look-alike places more than :data:`SUCCESS_RADIUS`
    away and the failure probability of an ideal inverse, a uniform choice among all its places
    within the tolerance (:func:`~pyro_slam.planning.lookalikes` of the truth's
    :meth:`~pyro_slam.planning.GroundTruthEnv.places`, searched on a ``spacing`` grid).
    Returns ``{tol: {"lookalikes": [n], "ideal_failure": [n]}}``."""
    env = GroundTruthEnv(maze, lidar)
    n_headings = 360 if 360 % lidar.n_beams == 0 else 18 * lidar.n_beams
    places = env.places(env.scan(poses).numpy(), spacing=spacing, n_headings=n_headings)
    out = {}
    for tol in tols:
        counts = [lookalikes(pz, pd, tp, tol) for tp, (pz, pd) in zip(poses, places)]
        out[tol] = {"lookalikes": [c[0] for c in counts], "ideal_failure": [c[1] for c in counts]}
    return out


# ------------------------------------------------------------------------- one run's verdict
def scan_match(gt_env, xy, scan, radius=SUCCESS_RADIUS, spacing=0.01, headings=360) -> float:
    """Smallest mean absolute range difference between a true ``scan [B]`` and the true scans
    at the wall-free positions within ``radius`` of position ``xy [2]`` (a ``spacing`` grid
    around ``xy``, and ``xy`` itself) at ``headings`` evenly spaced headings (the agent may
    turn in place at the end), in the maze and LiDAR of ``gt_env`` (a
    :class:`~pyro_slam.planning.GroundTruthEnv`). Each position is ray-cast once in the
    ``headings`` directions (a multiple of the beam count): every heading's scan is a rotation
    of those rays."""
    B = len(scan)
    if headings % B:
        raise ValueError(f"headings={headings} must be a multiple of the {B} beams")
    off = np.arange(-radius, radius + 1e-9, spacing)
    pts = np.array([(dx, dy) for dx in off for dy in off if np.hypot(dx, dy) <= radius])
    pts = np.concatenate([np.zeros((1, 2)), pts]) + np.asarray(xy)[None]  # [P, 2]
    walls = gt_env.maze.walls
    pts = pts[[point_segment_distance(q, walls).min() > 1e-3 for q in pts]]
    ang = 2 * np.pi * np.arange(headings) / headings - np.pi  # [H]
    directions = np.broadcast_to(ang, (len(pts), headings))
    rays = raycast(walls, pts, directions, gt_env.lidar.max_range)  # [P, H]
    beams = (np.arange(headings)[:, None] + (headings // B) * np.arange(B)) % headings  # [H, B]
    return float(np.abs(rays[:, beams] - np.asarray(scan)).mean(-1).min())


def scan_reached(gt_env, xy, scan, tol: float = 0.01, radius: float = SUCCESS_RADIUS):
    """The verdict in observation space for an agent that stopped at position ``xy [2]``: did
    it stop within ``radius`` of a place whose true scan, at some heading, differs from the
    target's true ``scan [B]`` by less than ``tol`` (mean absolute range difference)? A target
    seen identically at several places is reached at any of them. Returns ``(reached, the
    smallest difference)`` (:func:`scan_match`)."""
    d = scan_match(gt_env, xy, scan, radius=radius)
    return d < tol, d


def pose_reached(found: bool, stop, target, radius: float = SUCCESS_RADIUS) -> tuple[bool, float]:
    """A pose target's verdict: a plan was ``found`` and the agent stopped (position ``stop
    [>= 2]``) within ``radius`` of ``target [>= 2]``. Returns ``(reached, distance)``."""
    err = float(np.hypot(*(np.asarray(stop)[:2] - np.asarray(target)[:2])))
    return bool(found and err <= radius), err


def observation_reached(
    found: bool, stop, target, gt_env, scan, tol: float = 0.01, radius: float = SUCCESS_RADIUS
) -> tuple[bool, float]:
    """An observation target's verdict in observation space: a plan was ``found`` and the agent
    stopped (position ``stop [>= 2]``) within ``radius`` of the pose ``target [>= 2]`` the
    target ``scan [B]`` was taken at, or of a place that sees that scan within ``tol``
    (:func:`scan_reached` in ``gt_env``). Returns ``(reached, the smallest scan difference near
    the stop)``."""
    at_target = pose_reached(found, stop, target, radius)[0]
    seen, d = scan_reached(gt_env, np.asarray(stop)[:2], scan, tol, radius)
    return bool(found and (at_target or seen)), d


def reached_within(run: dict, tol: float) -> bool:
    """A noise-free observation-target run (a run record) reached its target's view within
    ``tol``: at the target, or a plan was found and the smallest scan difference near where it
    stopped is below ``tol``."""
    return run["success_noiseless"] or (run["found"] and run["scan_diff_noiseless"] < tol)


# ------------------------------------------------------------------------- over a sample
def mean_or_none(xs) -> float | None:
    """The mean of ``xs`` (the share of true values of booleans); None if there are none."""
    return float(np.mean(xs)) if len(xs) else None


def _pair(r: dict) -> tuple[int, int, int]:
    return r["maze"], r["start"], r["goal"]


def success_ratios(runs: list[dict]) -> dict:
    """The sample's verdicts over run records (noise-free executions): the ``learned_obs``
    observation targets failed in observation space; failed by position over the runs whose
    target has no look-alike within the tolerance (and how many runs that leaves); the
    ``learned`` planner's pose targets reached over the pairs the ``ground_truth`` planner
    solves (None where a ratio has no runs)."""
    obs = [r for r in runs if r["planner"] == "learned_obs"]
    clear = [r for r in obs if r["target_lookalikes_tol"] == 0]
    gt = {_pair(r) for r in runs if r["planner"] == "ground_truth" and r["success_noiseless"]}
    pose = [r["success_noiseless"] for r in runs if r["planner"] == "learned" and _pair(r) in gt]
    return {
        "obs_failure_ratio_obs_space": mean_or_none([not r["scan_success_noiseless"] for r in obs]),
        "obs_failure_ratio_position_unaliased": mean_or_none(
            [not r["success_noiseless"] for r in clear]
        ),
        "unaliased_targets": len(clear),
        "pose_success_ratio": mean_or_none(pose),
    }


def miss_counts(runs: list[dict]) -> dict[str, dict[str, int]]:
    """Per maze and over all (``"all"``), the counts behind the ratios, from run records
    (noise-free runs): pairs, ground-truth-solved pairs and the learned planner's successes on
    them, observation targets missed by position and in observation space (``scan_success``),
    and the latter by cause: ``not_found`` (no plan), ``wrong_goal`` (a plan to an inferred goal
    more than :data:`SUCCESS_RADIUS` from the target, ending where the target's view is not),
    ``execution`` (the goal was within that radius of the target, the executed controls ended
    elsewhere); observation runs whose target has no look-alike within the tolerance and the
    misses by position among them, runs whose target has an exact look-alike place more than
    the radius away, and the ground-truth observation-target planner's misses by position."""
    out = {str(ms): _maze_counts([r for r in runs if r["maze"] == ms]) for ms in _mazes(runs)}
    out["all"] = {k: sum(c[k] for c in out.values()) for k in next(iter(out.values()), {})}
    return out


def _mazes(runs: list[dict]) -> list[int]:
    return sorted({r["maze"] for r in runs})


def _maze_counts(runs: list[dict]) -> dict[str, int]:
    """:func:`miss_counts` of one maze's run records."""
    by = {p: {(r["start"], r["goal"]): r for r in runs if r["planner"] == p} for p in PLANNERS}
    solved = [k for k, r in by["ground_truth"].items() if r["success_noiseless"]]
    obs = by["learned_obs"].values()
    missed = [r for r in obs if not r["scan_success_noiseless"]]
    clear = [r for r in obs if r["target_lookalikes_tol"] == 0]
    planned = [r["inference_error"] for r in missed if r["found"]]  # their goals' errors
    return {
        "pairs": len(by["ground_truth"]),
        "gt_solved": len(solved),
        "learned_on_gt_solved": sum(by["learned"][k]["success_noiseless"] for k in solved),
        "obs_missed": sum(not r["success_noiseless"] for r in obs),
        "obs_missed_scan": len(missed),
        "obs_missed_scan_not_found": sum(not r["found"] for r in missed),
        "obs_missed_scan_wrong_goal": sum(e > SUCCESS_RADIUS for e in planned),
        "obs_missed_scan_execution": sum(e <= SUCCESS_RADIUS for e in planned),
        "obs_unaliased": len(clear),
        "obs_unaliased_missed": sum(not r["success_noiseless"] for r in clear),
        "obs_target_aliased": sum(r["target_lookalikes_exact"] > 0 for r in obs),
        "gt_obs_missed": sum(not r["success_noiseless"] for r in by["ground_truth_obs"].values()),
    }
