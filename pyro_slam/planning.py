"""Navigation in the learned DVBF-LM model: latent hybrid A* (paper section V-A, Appendix C-A).

* :func:`safety` -- ``s(x) = mu / (1 + exp((x - delta) * sigma))`` (mu = 1e4, delta = 0.03,
  sigma = 1e2) and :func:`safety_cost` ``L_safe = sum_i s(l_i)`` over a scan's beams.
* :class:`LearnedEnv` -- the model as a black-box simulator: predicted scans ``mu_E(f_m(z, M))``
  from a map ``M`` (the mean of ``q(M)``), motion by the mean of the engineered
  :class:`~pyro_slam.transitions.KinematicTransition` with ``clip_margin`` (moves forward only
  while the predicted reading ahead exceeds the step).
* :class:`GroundTruthEnv` -- the same interface on the simulator's true geometry: analytic raycast
  on the maze walls, exact (noise-free) pymunk kinematics with collisions. The upper bound.
* :func:`plan` -- hybrid A*: a grid of ``cell`` x ``cell`` position cells, each tied to the
  continuous pose that first reached it; successors by motion primitives (turn on the spot, then
  ``forward_steps`` straight steps); edge cost = travel distance + ``L_safe`` at the primitive's
  end pose; heuristic = Euclidean distance; backtracking gives the executable control sequence.
  Every step of a primitive must be valid: explored (chart std under ``q(M)`` below
  ``max_std``) or inside the free space of a real scan (:meth:`LearnedEnv.with_observation`).
* :func:`execute` -- run a control sequence in the pymunk :class:`~simulators.World`.

``pyro-slam navigate`` (:func:`add_navigate_parser`) plans in one maze and plots the plan over the
map belief next to the executed trajectory.
"""

from __future__ import annotations

import argparse
import copy
import heapq
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from .transitions import KinematicTransition

SAFETY_MU, SAFETY_DELTA, SAFETY_SIGMA = 1e4, 0.03, 1e2


def safety(x, mu: float = SAFETY_MU, delta: float = SAFETY_DELTA, sigma: float = SAFETY_SIGMA):
    """``s(x) = mu / (1 + exp((x - delta) * sigma))`` (stable form), tensors or arrays."""
    x = torch.as_tensor(x)
    return mu * torch.sigmoid(-(x - delta) * sigma)


def safety_cost(scan, **kw) -> torch.Tensor:
    """``L_safe = sum_i s(l_i)`` over the last (beam) dimension: ``[..., B]`` -> ``[...]``."""
    return safety(scan, **kw).sum(-1)


# --------------------------------------------------------------------------- primitives
@dataclass(frozen=True)
class Primitives:
    """Motion primitives: turn by each of ``turns`` (rad, in steps of at most
    ``max_rotation``), then ``forward_steps`` straight steps of ``step`` each."""

    turns: tuple[float, ...] = tuple(k * math.pi / 6 for k in range(-5, 7))
    forward_steps: int = 5
    step: float = 0.008
    max_rotation: float = 0.3

    def controls(self) -> list[np.ndarray]:
        out = []
        for th in self.turns:
            n = math.ceil(abs(th) / self.max_rotation - 1e-9)
            rot = [[th / n, 0.0]] * n if n else []
            out.append(np.array(rot + [[0.0, self.step]] * self.forward_steps, dtype=np.float64))
        return out

    def padded(self) -> torch.Tensor:
        """``[P, L, 2]`` with no-op ``(0, 0)`` steps in front (exact for the kinematic model)."""
        cs = self.controls()
        L = max(len(c) for c in cs)
        pad = [np.concatenate([np.zeros((L - len(c), 2)), c]) for c in cs]
        return torch.as_tensor(np.stack(pad), dtype=torch.get_default_dtype())


def inside_scan(xy, pose, scan, margin: float = SAFETY_DELTA, radius: float = 0.1) -> np.ndarray:
    """Positions ``xy [N, 2]`` inside the free space that a scan ``[B]`` (beams evenly spaced
    over the circle, the first along the heading) shows from ``pose [3]``: at least ``margin``
    before the shorter of the two beams around each position's bearing, and within
    ``radius`` of the pose (farther out, a corner can hide between two beams): ``[N]``."""
    scan = np.minimum(np.asarray(scan, dtype=np.float64), radius + margin)
    B = len(scan)
    d = np.asarray(xy, dtype=np.float64) - pose[:2]
    bearing = np.remainder(np.arctan2(d[:, 1], d[:, 0]) - pose[2], 2 * np.pi)
    i0 = np.floor(bearing / (2 * np.pi / B)).astype(int) % B
    reach = np.minimum(scan[i0], scan[(i0 + 1) % B])
    return np.hypot(d[:, 0], d[:, 1]) <= reach - margin


# --------------------------------------------------------------------------- environments
class LearnedEnv:
    """The DVBF-LM model with a fixed map ``M`` (mean of ``q(M)``) as planning environment.

    Args:
        model: a :class:`~pyro_slam.model.DVBFLM` (its emission is used, frozen).
        M: map ``[w, h, D_m]``.
        clip_margin: stop this far before the predicted range ahead.
        bounds: ``(x0, x1, y0, y1)`` poses must stay within (default: the map extent).
    """

    name = "learned"

    def __init__(
        self,
        model,
        M: torch.Tensor,
        clip_margin: float = 0.01,
        bounds=None,
        scale: torch.Tensor | None = None,
        max_std: float = 0.6,
    ):
        self.model, self.M, self.scale, self.max_std = model, M, scale, max_std
        self.transition = KinematicTransition(0.0, "rotate_forward", clip_margin=clip_margin)
        self.bounds = bounds if bounds is not None else model.grid.extent()
        self.seen: list[tuple] = []  # (pose [3], real scan [B], margin, radius)

    def with_observation(
        self, pose, scan, margin: float = SAFETY_DELTA, radius: float = 0.1
    ) -> LearnedEnv:
        """A copy that also trusts the free space of a *real* scan ``[B]`` taken at ``pose
        [3]`` (e.g. the agent's own LiDAR at the start): positions at least ``margin`` inside
        it and within ``radius`` of the pose (:func:`inside_scan`) count as valid even where
        the map is unexplored."""
        out = copy.copy(self)
        seen = (np.asarray(pose, float), np.asarray(scan, float), margin, radius)
        out.seen = [*self.seen, seen]
        return out

    @torch.no_grad()
    def scan(self, z: torch.Tensor) -> torch.Tensor:
        return self.model.emission_mean(self.M, z)

    @torch.no_grad()
    def std(self, xy) -> np.ndarray:
        """Mean std of the chart ``m = f_m(z, M)`` under ``q(M)`` at positions ``[N, 2]``."""
        xy = torch.as_tensor(np.asarray(xy)[..., :2], dtype=self.M.dtype)
        var = self.model.grid.attend(self.scale**2, xy, power=2)
        return var.mean(-1).sqrt().numpy()

    def valid(self, z) -> np.ndarray:
        """Explored positions: chart std under ``q(M)`` below ``max_std`` (prior: 1); the
        model's predicted scans are extrapolations elsewhere."""
        if self.scale is None:
            return np.ones(len(z), dtype=bool)
        ok = self.std(z) < self.max_std
        for pose, scan, margin, radius in self.seen:
            ok |= inside_scan(np.asarray(z)[:, :2], pose, scan, margin, radius)
        return ok

    @torch.no_grad()
    def rollout(self, z0: np.ndarray, controls: torch.Tensor):
        """Apply ``controls [P, L, 2]`` from pose ``z0 [3]`` through the transition mean.

        Returns final poses ``[P, 3]``, travel ``[P]``, end scans ``[P, B]``, paths
        ``[P, L + 1, 3]``.
        """
        P, L, _ = controls.shape
        z = torch.as_tensor(z0, dtype=controls.dtype).expand(P, 3).clone()
        path, travel = [z], torch.zeros(P)
        for k in range(L):
            u = controls[:, k]
            zr = torch.cat([z[:, :2], z[:, 2:] + u[:, :1]], -1)
            if bool((u[:, 1] > 0).any()):
                # the scan read at the rotated pose: its forward beam looks along the motion
                nz = self.transition.mean(
                    zr, torch.stack([torch.zeros(P), u[:, 1]], -1), self.scan(zr)
                )
            else:
                nz = zr
            travel = travel + (nz[:, :2] - z[:, :2]).norm(dim=-1)
            z = nz
            path.append(z)
        return z.numpy(), travel.numpy(), self.scan(z), torch.stack(path, 1).numpy()


class GroundTruthEnv:
    """The simulator's truth: analytic raycast on the walls, exact pymunk kinematics."""

    name = "ground_truth"

    def __init__(self, maze, lidar=None):
        from simulators import LidarConfig, World

        self.maze = maze
        self.lidar = lidar or LidarConfig()
        self.world = World(maze, self.lidar, odometry_noise=0, seed=0)
        self.bounds = maze_bounds(maze)
        self._grid_key, self._grid = None, None  # places(): the ray-cast search grid

    def scan(self, z) -> torch.Tensor:
        from simulators import raycast

        z = np.atleast_2d(np.asarray(z, dtype=np.float64))
        ang = z[:, 2:3] + self.lidar.beam_angles[None]
        r = raycast(self.maze.walls, z[:, :2], ang, self.lidar.max_range)
        return torch.as_tensor(r, dtype=torch.get_default_dtype())

    def rollout(self, z0: np.ndarray, controls: torch.Tensor):
        c = controls.numpy()
        P, L, _ = c.shape
        paths = np.zeros((P, L + 1, 3))
        for p in range(P):
            self.world.reset(z0)
            paths[p, 0] = self.world.pose
            for k in range(L):
                paths[p, k + 1] = self.world.step(c[p, k]) if c[p, k].any() else paths[p, k]
        travel = np.linalg.norm(np.diff(paths[:, :, :2], axis=1), axis=-1).sum(1)
        return paths[:, -1], travel, self.scan(paths[:, -1]), paths

    def valid(self, z) -> np.ndarray:
        return np.ones(len(z), dtype=bool)

    def places(
        self,
        scans,
        *,
        spacing: float = 0.01,
        n_headings: int = 360,
        coarse_tol: float = 0.03,
        separation: float = 0.05,
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """The exact inverse of the noise-free LiDAR: for each scan of ``scans [N, B]``, the
        distinct places whose *true* scan matches it, as ``(poses [k, 3], diffs [k])`` sorted by
        ``diffs``, the mean absolute range difference (``k = 0`` if no pose is within
        ``coarse_tol``).

        The positions of a ``spacing`` grid (free of walls) are ray-cast once in ``n_headings``
        directions (a multiple of the beam count: the scan of every grid heading is then a
        rotation of those rays). The grid poses whose scan is within ``coarse_tol`` of the
        target are thinned greedily, best first, to one per ``separation``, and each is refined
        by Nelder-Mead on the difference (non-smooth, so derivative-free); refinements that end
        within ``separation`` of a better one are dropped. ``poses[0]`` is the
        best match, the truth's mode: the ground-truth planner's goal for an observation target.
        Entries with ``diffs`` below ~1e-6 are exact look-alikes, perceptual aliasing that no
        inverse model reading this one scan can resolve.
        """
        from scipy.optimize import minimize

        from simulators import raycast

        def diff(z, x):  # float64, no torch round trip
            r = raycast(self.maze.walls, z[None, :2], z[2] + self.lidar.beam_angles[None],
                        self.lidar.max_range)  # fmt: skip
            return np.abs(r[0] - x).mean()

        B = self.lidar.n_beams
        if n_headings % B:
            raise ValueError(f"n_headings={n_headings} must be a multiple of the {B} beams")
        scans = np.atleast_2d(np.asarray(scans, dtype=np.float64))  # [N, B]
        if scans.shape[-1] != B:
            raise ValueError(f"scans have {scans.shape[-1]} beams, the LiDAR {B}: {scans.shape}")
        xy, rays = self._ray_grid(spacing, n_headings)  # [P, 2], [P, H]
        angles = 2 * np.pi * np.arange(n_headings) / n_headings  # [H]
        step = n_headings // B
        out = []
        for x in scans:
            d = torch.zeros_like(rays)  # [P, H]: grid pose (p, h) reads ray h + step * i
            for i in range(B):
                d += (torch.roll(rays, -i * step, dims=1) - float(x[i])).abs()
            best, h = (d / B).min(1)  # [P]
            reps: list[int] = []
            for p in torch.argsort(best).tolist():
                if best[p] > coarse_tol:
                    break
                if all(np.hypot(*(xy[p] - xy[q])) > separation for q in reps):
                    reps.append(p)
            poses, diffs = [], []
            for p in reps:
                z0 = np.array([*xy[p], angles[h[p]]])
                simplex = z0 + np.array([[0, 0, 0], [spacing / 2, 0, 0], [0, spacing / 2, 0],
                                         [0, 0, np.pi / n_headings]])  # fmt: skip
                r = minimize(
                    diff, z0, args=(x,), method="Nelder-Mead",
                    options={"initial_simplex": simplex, "xatol": 1e-8, "fatol": 1e-10},
                )  # fmt: skip
                z = r.x.copy()
                z[2] = (z[2] + np.pi) % (2 * np.pi) - np.pi
                poses.append(z)
                diffs.append(float(r.fun))
            keep: list[int] = []  # refinements that converged to one place count once
            for j in np.argsort(diffs, kind="stable"):
                if all(np.hypot(*(poses[j][:2] - poses[q][:2])) > separation for q in keep):
                    keep.append(j)
            out.append((np.array(poses).reshape(-1, 3)[keep], np.array(diffs)[keep]))
        return out

    def _ray_grid(self, spacing: float, n_headings: int):
        """Cached: the wall-free positions ``[P, 2]`` of a ``spacing`` grid over the maze and
        their ranges ``[P, n_headings]`` at ``n_headings`` evenly spaced directions from 0."""
        from simulators import raycast
        from simulators.world import point_segment_distance

        key = (spacing, n_headings)
        if self._grid_key != key:
            xs = np.arange(spacing / 2, self.maze.side, spacing)
            xy = np.stack(np.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
            xy = xy[[point_segment_distance(p, self.maze.walls).min() > 1e-3 for p in xy]]
            ang = 2 * np.pi * np.arange(n_headings) / n_headings
            rays = raycast(self.maze.walls, xy, np.broadcast_to(ang, (len(xy), n_headings)),
                           self.lidar.max_range)  # fmt: skip
            self._grid_key, self._grid = key, (xy, torch.as_tensor(rays))
        return self._grid


def lookalikes(poses, diffs, target, tol: float = 1e-6, radius: float = 0.05) -> tuple[int, float]:
    """Perceptual aliasing of a target pose ``target [2 or 3]`` from its
    :meth:`GroundTruthEnv.places` ``(poses [k, 3], diffs [k])``: the number of look-alike places
    (``diffs < tol``) more than ``radius`` from the target, and how often a uniform choice among
    all its places within ``tol`` (the target's own counted once at least) lands farther than
    ``radius`` -- the expected failure of an ideal inverse that reads only the scan."""
    far = np.hypot(*(np.asarray(poses)[:, :2] - np.asarray(target)[:2]).T) > radius  # [k]
    alike = np.asarray(diffs) < tol  # [k]
    n_far, n_near = int((far & alike).sum()), int((~far & alike).sum())
    return n_far, n_far / (n_far + max(n_near, 1))


# --------------------------------------------------------------------------- hybrid A*
@dataclass
class PlanResult:
    success: bool
    expansions: int
    controls: np.ndarray  # [T, 2] executable (rotation, forward) sequence
    path: np.ndarray  # [T + 1, 3] planned poses, step by step
    nodes: np.ndarray  # [n, 3] continuous poses of the cells on the path
    cost: float = float("nan")
    visited: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # expanded poses


def plan(
    env,
    start,
    goal,
    *,
    max_expansions: int = 2000,
    cell: float = 0.025,
    goal_tol: float = 0.025,
    primitives: Primitives | None = None,
    safety_weight: float = 1.0,
    heuristic_weight: float = 1.0,
    safety_kw: dict | None = None,
    check_path: bool = True,
) -> PlanResult:
    """Hybrid A* from pose ``start [3]`` to position ``goal [2+]`` in ``env``.

    A successor whose end pose lands in an already reached cell is discarded (each cell keeps
    the continuous pose that first reached it). Edge cost: travel distance +
    ``safety_weight * L_safe`` at the end pose; heuristic: ``heuristic_weight`` x Euclidean
    distance to the goal. The goal test (end pose within ``goal_tol``) is applied when a
    successor is generated; ``expansions`` counts popped nodes. ``check_path``: every step of a
    primitive (not only its end pose) must be ``env.valid``, except turning on the spot.
    """
    primitives = primitives or Primitives()
    prims = primitives.padded()
    unpadded = primitives.controls()
    start = np.asarray(start, dtype=np.float64)
    goal = np.asarray(goal, dtype=np.float64)[:2]
    x0, x1, y0, y1 = env.bounds
    safety_kw = safety_kw or {}

    def key(z):
        return (int(math.floor(z[0] / cell)), int(math.floor(z[1] / cell)))

    def h(z):
        return heuristic_weight * float(np.hypot(*(z[:2] - goal)))

    # node: pose, g, parent key, primitive index, step path
    nodes = {key(start): (start, 0.0, None, -1, start[None])}
    heap = [(h(start), 0, key(start))]
    closed, expansions, counter, found = set(), 0, 1, None
    if np.hypot(*(start[:2] - goal)) <= goal_tol:
        found = key(start)
    while heap and found is None and expansions < max_expansions:
        _, _, k = heapq.heappop(heap)
        if k in closed:
            continue
        closed.add(k)
        expansions += 1
        z, g = nodes[k][0], nodes[k][1]
        ends, travel, scans, paths = env.rollout(z, prims)
        cost = travel + safety_weight * safety_cost(scans, **safety_kw).double().numpy()
        if check_path:  # every step of the primitive must be valid, not only its end;
            # turning on the spot stays valid (the search may start in unexplored space)
            steps = paths[:, 1:]  # [P, L, 3]
            here = np.hypot(*(steps[..., :2] - z[:2]).transpose(2, 0, 1)) < 1e-5
            ok = (env.valid(steps.reshape(-1, 3)).reshape(here.shape) | here).all(1)
        else:
            ok = env.valid(ends)
        for p in range(len(ends)):
            e = ends[p]
            ke = key(e)
            if ke in nodes or not ok[p] or not (x0 <= e[0] <= x1 and y0 <= e[1] <= y1):
                continue
            n_pad = prims.shape[1] - len(unpadded[p])
            nodes[ke] = (e, g + float(cost[p]), k, p, paths[p, n_pad + 1 :])
            if np.hypot(*(e[:2] - goal)) <= goal_tol:
                found = ke
                break
            heapq.heappush(heap, (g + float(cost[p]) + h(e), counter, ke))
            counter += 1
    visited = np.array([nodes[c][0] for c in closed]) if closed else np.zeros((0, 3))
    if found is None:
        empty = np.zeros((0, 2))
        return PlanResult(False, expansions, empty, start[None], start[None], visited=visited)
    ctrl, steps, poses, k = [], [], [], found
    cost = nodes[found][1]
    while k is not None:
        pose, _, parent, p, path = nodes[k]
        poses.append(pose)
        if p >= 0:
            ctrl.append(unpadded[p])
            steps.append(path)
        k = parent
    ctrl = np.concatenate(ctrl[::-1]) if ctrl else np.zeros((0, 2))
    path = np.concatenate([start[None], *steps[::-1]]) if steps else start[None]
    return PlanResult(True, expansions, ctrl, path, np.array(poses[::-1]), cost, visited)


def execute(maze, start, controls, noise=0, seed: int = 0):
    """Run ``controls [T, 2]`` in the pymunk :class:`~simulators.World` from ``start``.

    ``noise``: actuation noise (``0`` = none, ``None`` = the simulator's calibrated default).
    Returns the executed poses ``[T + 1, 3]`` and the number of blocked moves.
    """
    from simulators import World

    w = World(maze, odometry_noise=noise, seed=seed, pose=start)
    poses = [w.pose]
    for u in np.asarray(controls):
        poses.append(w.step(u))
    return np.array(poses), w.collisions


def segments_cross(path_xy: np.ndarray, walls: np.ndarray) -> bool:
    """True if any segment of the polyline ``[n, 2]`` properly intersects a wall ``[W, 4]``."""
    if len(path_xy) < 2 or not len(walls):
        return False
    a, b = path_xy[:-1, None], path_xy[1:, None]  # [n-1, 1, 2]
    c, d = walls[None, :, :2], walls[None, :, 2:]  # [1, W, 2]

    def orient(p, q, r):
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (
            r[..., 0] - p[..., 0]
        )

    o1, o2 = orient(a, b, c), orient(a, b, d)
    o3, o4 = orient(c, d, a), orient(c, d, b)
    return bool(np.any((o1 * o2 < 0) & (o3 * o4 < 0)))


# --------------------------------------------------------------------------- learned map
def learned_env(
    maze,
    traversal=None,
    steps: int = 3000,
    seed: int = 1,
    fit_steps: int = 1500,
    poses=None,
    progress: bool = False,
    max_std: float = 0.6,
    emission_steps: int = 0,
    n_world: int = 20,
    tour=None,
):
    """A :class:`LearnedEnv` for ``maze``: simulate a traversal (unless given; ``steps``
    exploring steps, then a tour through the positions ``tour`` ``[P, 2]`` it missed, see
    :func:`simulators.simulate_traversal`), fit ``q(M)``
    with :func:`~pyro_slam.slam.fit_map` at ``poses`` (default: the true poses, i.e. mapping
    with known poses) under a frozen emission.

    The emission is the shipped pretrained one (``emission_steps = 0``; 20 world directions)
    or, with ``emission_steps > 0``, one fitted to this traversal together with a map by
    :func:`~pyro_slam.slam.pretrain_emission` (``n_world`` world directions, from scratch, at
    the same ``poses``), after which ``q(M)`` is refitted under it.

    Returns ``(env, (q_loc, q_scale), traversal)``."""
    from .cli import EMISSION_FILE, PRETRAINED, load_emission
    from .slam import SLAMConfig, build_model, fit_map, pretrain_emission

    if traversal is None:
        from simulators import simulate_traversal

        traversal = simulate_traversal(maze, steps=steps, seed=seed, tour=tour)
    cfg = SLAMConfig(learn_emission=False, n_world=n_world)
    if emission_steps > 0:
        fit_on = traversal if poses is None else replace(traversal, poses=np.asarray(poses))
        em, _ = pretrain_emission([fit_on], cfg, steps=emission_steps, seed=seed, progress=progress)
    else:
        em = load_emission(PRETRAINED / EMISSION_FILE, traversal, cfg)
    model, _ = build_model(traversal, cfg, emission=em)
    loc, scale = fit_map(traversal, model, poses, fit_steps, seed=seed, progress=progress)
    env = LearnedEnv(model, loc, bounds=maze_bounds(maze), scale=scale, max_std=max_std)
    return env, (loc, scale), traversal


def maze_bounds(maze, margin: float = SAFETY_DELTA):
    """The maze's extent shrunk by ``margin``: unexplored space outside the outer walls reads
    as free in the learned model (prior map), so the search is kept inside."""
    return (margin, maze.side - margin, margin, maze.side - margin)


def free_grid(maze, n: int = 5, clearance: float = 0.04) -> np.ndarray:
    """An ``n x n`` grid of positions over the maze; a point closer than ``clearance`` to a wall
    moves to the centre of its maze cell. Returns ``[n * n, 2]``."""
    from simulators.world import point_segment_distance

    pts = []
    for j in range(n):
        for i in range(n):
            p = np.array([(i + 0.5) / n, (j + 0.5) / n]) * maze.side
            if point_segment_distance(p, maze.walls).min() < clearance:
                c = maze.cell_of(p)
                p = maze.cell_center(c[0], c[1])
            pts.append(p)
    return np.array(pts)


# --------------------------------------------------------------------------- plot + CLI
def plot_navigation(
    maze,
    env,
    result: PlanResult,
    executed: np.ndarray,
    goal,
    path_png,
    title: str = "",
    inferred=None,
) -> Path:
    """Left: the plan over the map belief (predicted nearest range per position); right: the
    executed trajectory in the simulator with the true walls. ``inferred``: the goal inferred
    from an observation target (drawn as a cross; ``goal`` is then the true target)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .plotting import _save, _walls

    fig, axes = plt.subplots(1, 2, figsize=(10, 5))
    n = 80
    xs = (np.arange(n) + 0.5) / n * maze.side
    X, Y = np.meshgrid(xs, xs)
    z = torch.as_tensor(
        np.stack([X.ravel(), Y.ravel(), np.zeros(n * n)], -1), dtype=torch.get_default_dtype()
    )
    with torch.no_grad():
        img = env.scan(z).min(-1).values.reshape(n, n).numpy()
    ax = axes[0]
    ax.imshow(img, origin="lower", extent=(0, maze.side, 0, maze.side), cmap="gray")
    if len(result.visited):
        ax.plot(*result.visited[:, :2].T, ".", ms=2, color="tab:orange", alpha=0.4)
    ax.plot(*result.path[:, :2].T, "-", color="tab:blue", lw=2, label="plan")
    ax.set_title(f"plan in {env.name} belief ({result.expansions} expansions)")
    ax = axes[1]
    _walls(ax, maze.walls)
    ax.plot(*result.path[:, :2].T, "--", color="tab:blue", lw=1, label="plan")
    ax.plot(*executed[:, :2].T, "-", color="tab:green", lw=2, label="executed")
    err = float(np.hypot(*(executed[-1, :2] - np.asarray(goal)[:2])))
    ax.set_title(f"executed in simulator: final error {err:.3f}")
    for ax in axes:
        ax.plot(*result.path[0, :2], "o", color="k")
        ax.plot(*np.asarray(goal)[:2], "*", color="tab:red", ms=14)
        ax.add_patch(plt.Circle(np.asarray(goal)[:2], 0.05, fill=False, color="tab:red"))
        if inferred is not None:
            ax.plot(*np.asarray(inferred)[:2], "x", color="tab:purple", ms=12, mew=3)
        ax.set_xlim(0, maze.side)
        ax.set_ylim(0, maze.side)
        ax.set_aspect("equal")
    axes[1].legend(loc="upper right", fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, path_png)


def add_navigate_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "navigate", help="plan with hybrid A* in the learned model and execute in the simulator"
    )
    p.add_argument("--maze", default="moderate-medium")
    p.add_argument("--maze-seed", type=int, default=1001)
    p.add_argument("--start", type=float, nargs=3, default=None, help="x y heading")
    p.add_argument("--goal", type=float, nargs=2, default=None, help="x y")
    p.add_argument(
        "--target-scan-from-pose",
        type=float,
        nargs=3,
        default=None,
        metavar=("X", "Y", "H"),
        help="observation target: render the simulator's scan at this pose, infer the goal "
        "with the inverse model q(z|x) (pyro_slam.inverse; with --planner ground_truth the "
        "truth's own inverse, GroundTruthEnv.places); overrides --goal",
    )
    p.add_argument("--inverse-steps", type=int, default=1000, help="ELBO steps of q(z|x)")
    p.add_argument("--inverse-sleep-steps", type=int, default=3000, help="sleep steps of q(z|x)")
    p.add_argument("--planner", choices=["learned", "ground_truth"], default="learned")
    p.add_argument(
        "--map",
        choices=["known_poses", "slam"],
        default="known_poses",
        help="q(M) fitted at the true poses, or at an online SLAM run's pose means",
    )
    p.add_argument("--traversal-steps", type=int, default=3000)
    p.add_argument("--fit-steps", type=int, default=1500)
    p.add_argument(
        "--emission-steps", type=int, default=0,
        help="fit the emission on the mapping traversal for this many steps (0: shipped, frozen)",
    )  # fmt: skip
    p.add_argument("--n-world", type=int, default=20, help="world directions of a fitted emission")
    p.add_argument("--max-expansions", type=int, default=3000)
    p.add_argument("--noise", action="store_true", help="execute with actuation noise")
    p.add_argument("--out", type=Path, default=Path("navigate.png"))
    p.set_defaults(func=run_navigate)
    return p


def run_navigate(args) -> int:
    import json

    from simulators import make_maze, simulate_traversal

    torch.set_num_threads(1)
    maze = make_maze(args.maze, args.maze_seed)
    pts = free_grid(maze)
    start = np.array(args.start) if args.start else np.array([*pts[0], 0.0])
    goal = np.array(args.goal) if args.goal else pts[-1]
    tr = simulate_traversal(maze, steps=args.traversal_steps, seed=1)
    poses = None
    if args.map == "slam":
        from .cli import EMISSION_FILE, PRETRAINED, load_emission
        from .slam import SLAM, SLAMConfig

        cfg = SLAMConfig(learn_emission=False)
        res = SLAM(tr, cfg, emission=load_emission(PRETRAINED / EMISSION_FILE, tr, cfg)).run(
            "online", progress=True
        )
        poses = np.asarray(res["mean"])
    lenv, _, _ = learned_env(
        maze, tr, fit_steps=args.fit_steps, poses=poses, progress=True,
        emission_steps=args.emission_steps, n_world=args.n_world,
    )  # fmt: skip
    if args.planner == "learned":  # the agent's own scan at the start: trusted free space
        env = lenv.with_observation(start, GroundTruthEnv(maze).scan(start)[0].numpy())
    else:
        env = GroundTruthEnv(maze)
    inferred, n_lookalikes = None, None
    if args.target_scan_from_pose is not None:
        from .inverse import fit_inverse

        target = np.array(args.target_scan_from_pose)
        truth = GroundTruthEnv(maze)
        tscan = truth.scan(target)  # [1, B]
        pz, pd = truth.places(tscan.numpy())[0]  # every place that looks like the target
        n_lookalikes = lookalikes(pz, pd, target)[0]
        if args.planner == "learned":
            inv = fit_inverse(
                lenv, tr, steps=args.inverse_steps, sleep_steps=args.inverse_sleep_steps,
                progress=True,
            )  # fmt: skip
            inferred = inv.infer(tscan[0])[0].numpy()
        else:  # the truth's own inverse: its best-matching place
            inferred = pz[0]
        goal = inferred[:2]
    res = plan(env, start, goal, max_expansions=args.max_expansions)
    executed, coll = execute(maze, start, res.controls, noise=None if args.noise else 0)
    true_goal = goal if inferred is None else target[:2]
    err = float(np.hypot(*(executed[-1, :2] - true_goal)))
    plot_navigation(
        maze,
        lenv if args.planner == "learned" else env,
        res,
        executed,
        true_goal,
        args.out,
        f"maze {args.maze_seed}, {args.planner} planner"
        + ("" if inferred is None else " (x: goal inferred from the target scan)"),
        inferred=inferred,
    )
    report = {
        "found": res.success,
        "expansions": res.expansions,
        "steps": len(res.controls),
        "final_error": err,
        "success": bool(res.success and err <= 0.05),
        "collisions": int(coll),
        "plot": str(args.out),
    }
    if inferred is not None:
        report["inferred_goal"] = inferred.tolist()
        report["inference_error"] = float(np.hypot(*(inferred[:2] - target[:2])))
        report["target_lookalikes_exact"] = n_lookalikes  # places > 0.05 away that look the same
    print(json.dumps(report))
    return 0
