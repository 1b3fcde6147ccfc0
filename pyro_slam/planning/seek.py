"""Navigating to an observation target with several hypotheses (paper section V-c, closed loop).

A target scan can be explained by several places of the learned map: the inverse model's best
mode (:meth:`~pyro_slam.planning.inverse.InversePose.modes`) is sometimes a wrong one, a place
that the map fitted by SLAM predicts to look like the target but that does not. The agent of
:func:`seek_observation` therefore treats the modes as hypotheses, best first:

1. plan with hybrid A* (:func:`~pyro_slam.planning.plan`) from where it believes it stands to
   the next hypothesis, close the rest of the way (A* stops within its goal tolerance) with a
   turn and a straight drive (:func:`approach`), and execute both;
2. look: turn on the spot and compare its own scans there with the target scan (the smallest
   mean absolute range difference over headings, ``look``);
3. stop when that difference is below ``accept_tol``; otherwise go on to the next hypothesis.
   When none is accepted, it returns to the hypothesis whose view matched best.

The agent's belief of its pose is the plan's end pose (controls executed open loop); only its
own sensor at the place it reached enters the decision, never the target's pose.

A goal in space that the map has not explored has no plan: every step of a plan must be
explored or inside the free space of a scan the agent took itself. Given its sensor
(``sense``), the agent then goes to the reached place nearest to the goal, takes a scan there,
trusts its free space (:meth:`~pyro_slam.planning.LearnedEnv.with_observation`) and plans again,
up to ``rounds`` times, while each round brings it nearer. :func:`seek_pose` is the same agent
with one goal and no view to check (a pose target).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simulators import raycast
from simulators.traversal import integrate_controls

from ..geometry import wrap_angle
from .config import NAVIGATION
from .envs import execute
from .planner import PlanResult, Primitives, plan


@dataclass
class SeekResult:
    """The outcome of :func:`seek_observation`."""

    found: bool  # some plan was found and executed
    poses: np.ndarray  # [T + 1, 3] executed (true) poses, every leg one after the other
    controls: np.ndarray  # [T, 2] every leg's controls
    path: np.ndarray  # [T + 1, 3] the planned (believed) poses, every leg one after the other
    goals: list  # the hypotheses' positions [2] in the order the agent headed for them
    stops: list  # the true pose [3] where each leg stopped (None: no plan)
    diffs: list  # the view's difference from the target at each leg's stop (nan: no plan)
    accepted: int | None  # index into goals of the accepted hypothesis (None: none)
    expansions: int  # A* expansions over every leg
    scans: int = 0  # scans taken to explore towards goals without a plan

    def as_plan(self) -> PlanResult:
        """The legs as one :class:`~pyro_slam.planning.PlanResult` (for plotting)."""
        return PlanResult(self.found, self.expansions, self.controls, self.path, self.path[[0, -1]])


class Mover:
    """``move`` for :func:`seek_observation` in the simulator: executes a leg's controls from a
    true pose in the pymunk World of ``maze`` (:func:`~pyro_slam.planning.execute`; actuation
    ``noise`` as there, each leg its own seed) and counts the blocked moves."""

    def __init__(self, maze, noise=0, seed: int = 0):
        self.maze, self.noise, self.seed, self.legs, self.collisions = maze, noise, seed, 0, 0

    def __call__(self, pose, controls) -> np.ndarray:
        seed = self.seed + 10_000 * self.legs
        ex, coll = execute(self.maze, pose, controls, noise=self.noise, seed=seed)
        self.legs, self.collisions = self.legs + 1, self.collisions + int(coll)
        return ex


def seek_observation(
    env,
    start,
    hypotheses,
    move,
    look,
    *,
    accept_tol: float,
    sense=None,
    rounds: int = NAVIGATION.observe_rounds,
    **plan_kw,
) -> SeekResult:
    """Visit the ``hypotheses [K, 2+]`` (best first) from the true pose ``start [3]`` until the
    view at a stop matches the target within ``accept_tol``.

    ``env``: the planning environment (the learned model); ``move(pose [3], controls [T, 2])``
    executes controls from a true pose and returns the executed poses ``[T + 1, 3]``;
    ``look(pose [3])`` is what the agent makes of its view at a true pose (turning on the spot):
    the smallest difference from the target and the offset ``[2]`` from where it stands to the
    place nearby that shows it (:func:`match_view`). An accepted view, and the best one when
    none is, is reached by driving that offset. ``sense(pose [3])``: the agent's scan ``[B]`` at
    a true pose, taken where a goal has no plan (module doc; None: it gives up on that goal),
    at most ``rounds`` times per goal. ``plan_kw`` go to :func:`~pyro_slam.planning.plan`.
    """
    if sense is not None and not hasattr(env, "with_observation"):
        raise TypeError(f"sense needs an env that trusts a scan (with_observation); got {env!r}")
    st = _Walk(env, move, start, plan_kw, sense, rounds)
    goals, stops, diffs, places = [], [], [], []
    for goal in np.asarray(hypotheses, dtype=np.float64)[:, :2]:
        goals.append(goal)
        if not st.leg(goal):
            diffs.append(float("nan"))
            stops.append(None)
            places.append(None)
            continue
        d, offset = look(st.true)
        stops.append(st.true)
        diffs.append(float(d))
        places.append(st.belief[:2] + np.asarray(offset, dtype=np.float64))
        if d < accept_tol:
            st.drive(places[-1])
            return st.result(goals, stops, diffs, len(goals) - 1)
    seen = [i for i, d in enumerate(diffs) if np.isfinite(d)]
    if not seen:
        return st.result(goals, stops, diffs, None, found=False)
    best = min(seen, key=lambda i: diffs[i])
    if best == seen[-1] or st.leg(goals[best]):  # back to the hypothesis of the best view
        st.drive(places[best])
    return st.result(goals, stops, diffs, None)


def seek_pose(env, start, goal, move, sense=None, **kw) -> SeekResult:
    """Go to position ``goal [2+]`` from the true pose ``start [3]``: :func:`seek_observation`
    with the goal as its one hypothesis and no view to check (``kw``: its ``rounds`` and
    :func:`~pyro_slam.planning.plan`'s arguments)."""
    goal = np.asarray(goal, dtype=np.float64)[None, :2]
    return seek_observation(env, start, goal, move, _no_view, accept_tol=np.inf, sense=sense, **kw)


def _no_view(pose) -> tuple[float, np.ndarray]:
    """The look of a pose target: nothing to compare, no offset."""
    return 0.0, np.zeros(2)


class _Walk:
    """The agent's legs: its pose belief (the plans' end poses), its true pose, and the executed
    poses, controls and planned path so far."""

    def __init__(self, env, move, start, plan_kw: dict, sense=None, rounds: int = 0):
        self.env, self.move, self.plan_kw = env, move, plan_kw
        self.sense, self.rounds, self.scans = sense, rounds, 0
        self.belief = self.true = np.asarray(start, dtype=np.float64)
        self.poses, self.controls, self.path = (
            [self.true[None]],
            [np.zeros((0, 2))],
            [self.true[None]],
        )
        self.expansions = 0

    def leg(self, goal) -> bool:
        """Plan to position ``goal [2]``, approach it and execute; where there is no plan,
        explore towards it (:meth:`explore`) and plan again. False if no plan."""
        for attempt in range(self.rounds + 1):
            r = plan(self.env, self.belief, goal, **self.plan_kw)
            self.expansions += r.expansions
            if r.success:
                self._execute(r.controls, r.path)
                self.drive(goal)
                return True
            if self.sense is None or attempt == self.rounds or not self.explore(r.visited, goal):
                return False
        return False

    def explore(self, visited, goal) -> bool:
        """Go to the pose of ``visited [N, 3]`` (where a search reached) nearest to ``goal
        [2]``, scan there and trust the scan's free space from then on; False (staying put) if
        none is nearer than where the agent believes it stands."""
        if not len(visited):
            return False
        d = np.hypot(*(visited[:, :2] - goal).T)
        k = int(np.argmin(d))
        if d[k] >= np.hypot(*(self.belief[:2] - goal)) - 1e-9:
            return False
        r = plan(self.env, self.belief, visited[k, :2], **self.plan_kw)
        self.expansions += r.expansions
        if not r.success:
            return False
        self._execute(r.controls, r.path)
        self.env = self.env.with_observation(self.belief, self.sense(self.true))
        self.scans += 1
        return True

    def drive(self, goal) -> None:
        """Turn towards position ``goal [2]`` and drive straight to it (:func:`approach`)."""
        u = approach(self.belief, goal)
        self._execute(u, integrate_controls(self.belief, u))

    def _execute(self, u, planned) -> None:  # u [T, 2], planned [T + 1, 3]
        if len(u):
            ex = self.move(self.true, u)
            self.poses.append(ex[1:])
            self.controls.append(u)
            self.path.append(planned[1:])
            self.belief, self.true = planned[-1], ex[-1]

    def result(self, goals, stops, diffs, accepted, found=True) -> SeekResult:
        return SeekResult(
            found=found,
            poses=np.concatenate(self.poses),
            controls=np.concatenate(self.controls),
            path=np.concatenate(self.path),
            goals=goals,
            stops=stops,
            diffs=diffs,
            accepted=accepted,
            expansions=self.expansions,
            scans=self.scans,
        )


def approach(pose, goal, primitives: Primitives | None = None) -> np.ndarray:
    """Controls ``[n, 2]`` that turn from ``pose [3]`` towards position ``goal [2]`` and drive
    straight to it, in the ``primitives``' steps (turns of at most ``max_rotation``, forward
    steps of at most ``step``)."""
    prims = primitives or Primitives()
    d = np.asarray(goal, dtype=np.float64)[:2] - np.asarray(pose, dtype=np.float64)[:2]
    dist = float(np.hypot(*d))
    if dist < 1e-9:
        return np.zeros((0, 2))
    turn = float(wrap_angle(np.arctan2(d[1], d[0]) - pose[2]))
    n = int(np.ceil(abs(turn) / prims.max_rotation - 1e-9))
    m = int(np.ceil(dist / prims.step - 1e-9))
    turns = [[turn / n, 0.0]] * n if n else []  # (already facing the goal: no turn)
    return np.array(turns + [[0.0, dist / m]] * m).reshape(-1, 2)


def sensor(gt_env):
    """``sense`` for :func:`seek_observation` in the simulator: the agent's own LiDAR scan
    ``[B]`` at a true pose ``[3]``, from the maze and LiDAR of ``gt_env`` (a
    :class:`~pyro_slam.planning.GroundTruthEnv`)."""
    return lambda z: gt_env.scan(np.asarray(z, dtype=np.float64))[0].numpy()


class Look:
    """``look`` for :func:`seek_observation` in the simulator: the agent's own view at its true
    position, turning on the spot (``headings`` true ranges, from the maze and LiDAR of
    ``gt_env``, a :class:`~pyro_slam.planning.GroundTruthEnv`), matched against the target
    ``scan [B]`` by :func:`match_view`."""

    def __init__(self, gt_env, scan, headings: int = 360):
        if headings % len(scan):
            raise ValueError(f"headings={headings} must be a multiple of the {len(scan)} beams")
        self.env, self.scan = gt_env, np.asarray(scan, dtype=np.float64)
        self.angles = 2 * np.pi * np.arange(headings) / headings - np.pi  # [H]

    def __call__(self, pose) -> tuple[float, np.ndarray]:
        xy = np.asarray(pose, dtype=np.float64)[None, :2]
        max_range = self.env.lidar.max_range
        rays = raycast(self.env.maze.walls, xy, self.angles[None], max_range)[0]  # [H]
        return match_view(rays, self.scan, max_range)


def match_view(rays, scan, max_range: float, radius: float = 0.05, spacing: float = 0.01):
    """Where near the agent the target ``scan [B]`` was seen, judged from the agent's own view.

    ``rays [H]``: the agent's ranges in the world directions ``-pi + 2 pi k / H`` (its scans,
    turning on the spot; ``H`` a multiple of ``B``). Their returns, joined along walls (points
    between neighbouring returns closer than ``4 * spacing``), form a local point cloud; the
    ranges it shows from a position offset by ``d`` (within ``radius``, on a ``spacing`` grid)
    are the nearest point in each bearing bin (``max_range`` where none). Returns the smallest
    mean absolute difference to ``scan`` over offsets and headings, and its offset ``[2]`` (about
    the agent's own view at offset 0).
    """
    rays = np.asarray(rays, dtype=np.float64)
    H, B = len(rays), len(scan)
    ang = 2 * np.pi * np.arange(H) / H - np.pi  # [H]
    pts = np.stack([rays * np.cos(ang), rays * np.sin(ang)], -1)  # [H, 2]
    hit = rays < max_range - 1e-9
    nxt = np.roll(np.arange(H), -1)
    wall = hit & hit[nxt] & (np.hypot(*(pts - pts[nxt]).T) < 4 * spacing)  # [H]
    frac = np.linspace(0.0, 1.0, 6)[1:-1, None, None]  # [4, 1, 1]
    fill = pts[wall][None] + frac * (pts[nxt][wall] - pts[wall])[None]  # [4, n, 2]
    cloud = np.concatenate([pts[hit], fill.reshape(-1, 2)])  # [P, 2]
    g = np.arange(-radius, radius + 1e-9, spacing)
    off = np.array([(0.0, 0.0)] + [(x, y) for x in g for y in g if 0 < np.hypot(x, y) <= radius])
    rel = cloud[None] - off[:, None]  # [V, P, 2]
    k = np.round((np.arctan2(rel[..., 1], rel[..., 0]) + np.pi) * H / (2 * np.pi)).astype(int) % H
    prof = np.full((len(off), H), float(max_range))  # [V, H]
    np.minimum.at(
        prof,
        (np.arange(len(off))[:, None].repeat(cloud.shape[0], 1), k),
        np.hypot(*rel.transpose(2, 0, 1)),
    )
    beams = (np.arange(H)[:, None] + (H // B) * np.arange(B)) % H  # [H, B]
    d = np.abs(prof[:, beams] - np.asarray(scan)).mean(-1)  # [V, H]
    v = int(np.argmin(d.min(1)))
    return float(d[v].min()), off[v]
