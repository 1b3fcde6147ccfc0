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

``pyro-slam navigate`` plans in one maze and plots the plan over the
map belief next to the executed trajectory.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .config import NAVIGATION

SAFETY_MU, SAFETY_DELTA, SAFETY_SIGMA = 1e4, 0.03, 1e2


def safety(x, mu: float = SAFETY_MU, delta: float = SAFETY_DELTA, sigma: float = SAFETY_SIGMA):
    """``s(x) = mu / (1 + exp((x - delta) * sigma))`` (stable form), tensors or arrays."""
    x = torch.as_tensor(x)
    return mu * torch.sigmoid(-(x - delta) * sigma)


def safety_cost(scan, **kw) -> torch.Tensor:
    """``L_safe = sum_i s(l_i)`` over the last (beam) dimension: ``[..., B]`` -> ``[...]``."""
    return safety(scan, **kw).sum(-1)


def expected_safety(scans, **kw) -> np.ndarray:
    """``L_safe`` of end scans ``[P, B]``, or its mean over draws of them ``[P, S, B]`` (the
    model's predictive): ``[P]``."""
    cost = safety_cost(scans, **kw).double()
    return (cost if cost.dim() == 1 else cost.mean(-1)).numpy()


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


def check_endpoints(bounds, start, goal, names=("start", "goal")) -> None:
    """Refuse a ``start [3]`` or ``goal [2+]`` position outside ``bounds`` ``(x0, x1, y0, y1)``
    (where the search never goes; to within 1e-6, the bounds' own rounding) or not finite:
    :class:`ValueError` naming it (``names``)."""
    x0, x1, y0, y1 = (float(b) for b in bounds)
    x0, x1, y0, y1 = x0 - 1e-6, x1 + 1e-6, y0 - 1e-6, y1 + 1e-6
    for name, pose in zip(names, (start, goal)):
        p = np.asarray(pose, dtype=np.float64).reshape(-1)
        if not np.isfinite(p).all() or not (x0 <= p[0] <= x1 and y0 <= p[1] <= y1):
            shown = " ".join(f"{v:g}" for v in p)
            raise ValueError(
                f"{name} {shown}: outside the map, which spans x {x0:g} .. {x1:g} and "
                f"y {y0:g} .. {y1:g}"
            )


def plan(
    env,
    start,
    goal,
    *,
    max_expansions: int = NAVIGATION.max_expansions,
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
    The search is exact A*; successors are computed ahead, for the popped node together with
    the next open ones (``env.rollout_batch`` poses per rollout).
    """
    primitives = primitives or Primitives()
    prims = primitives.padded()
    unpadded = primitives.controls()
    start = np.asarray(start, dtype=np.float64)
    goal = np.asarray(goal, dtype=np.float64)[:2]
    check_endpoints(env.bounds, start, goal)
    x0, x1, y0, y1 = env.bounds
    succ = _Successors(env, prims, safety_weight, safety_kw or {}, check_path)

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
        g = nodes[k][1]
        ends, cost, ok, paths = succ(k, nodes, heap, closed)
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
    return _backtrack(nodes, found, start, unpadded, expansions, visited)


class _Successors:
    """The successors of the search's nodes: end poses ``[P, 3]``, edge costs ``[P]``, validity
    ``[P]`` and step paths ``[P, L + 1, 3]`` of the primitives ``prims [P, L, 2]``. A node not
    yet rolled out is rolled out together with the best open nodes of the heap, up to
    ``env.rollout_batch`` of them (a rollout depends only on the node's pose)."""

    def __init__(self, env, prims, safety_weight: float, safety_kw: dict, check_path: bool):
        self.env, self.prims, self.check_path = env, prims, check_path
        self.safety_weight, self.safety_kw = safety_weight, safety_kw
        self.batch = max(1, int(getattr(env, "rollout_batch", 1)))
        self.done: dict = {}  # node key -> rollout of its pose

    def __call__(self, k, nodes: dict, heap: list, closed: set):
        if k not in self.done:
            keys = [k]
            for _, _, c in heapq.nsmallest(4 * self.batch, heap):
                if len(keys) == self.batch:
                    break
                if c not in closed and c not in self.done and c not in keys:
                    keys.append(c)
            out = self.env.rollout(np.stack([nodes[c][0] for c in keys]), self.prims)
            for i, c in enumerate(keys):
                self.done[c] = tuple(v[i] for v in out)
        ends, travel, scans, paths = self.done.pop(k)
        cost = travel + self.safety_weight * expected_safety(scans, **self.safety_kw)
        if self.check_path:  # every step of the primitive must be valid, not only its end;
            # turning on the spot, before the primitive's first forward control, stays valid
            # (the search may start in unexplored space)
            steps = paths[:, 1:]  # [P, L, 3]
            here = np.cumsum(np.abs(np.asarray(self.prims[..., 1])), 1) == 0  # [P, L]
            ok = (self.env.valid(steps.reshape(-1, 3)).reshape(here.shape) | here).all(1)
        else:
            ok = self.env.valid(ends)
        return ends, cost, ok, paths


def _backtrack(nodes: dict, found, start, unpadded, expansions: int, visited) -> PlanResult:
    """The plan that reaches cell ``found``: controls, step path and cell poses from start."""
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
