"""A scripted, "human-like" exploring driver producing ``(rotation, forward)`` controls.

Each step it (1) keeps a target heading, re-chosen every ``replan_every`` steps or when the way
ahead is blocked, among the LiDAR beams that see open space, scoring openness, straightness and
the novelty (few visits) of the cell one corridor width along the beam; (2) steers towards the
target with a proportional controller plus a smoothly varying (Ornstein-Uhlenbeck) wiggle and a
wall-centering term from the diagonal beams; (3) slows down as the forward range shrinks or the
turn sharpens. Distances are in corridor widths, so one configuration serves every maze scale.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from simulators.maze import Maze
from simulators.world import wrap_angle


@dataclass(frozen=True)
class DriverConfig:
    speed: float = 0.05  # forward offset per step at full speed, corridor widths
    max_rotation: float = 0.3  # rad per step
    gain: float = 0.35  # proportional steering gain towards the target heading
    wiggle: float = 0.03  # std of the OU rotation noise innovations, rad
    persistence: float = 0.9  # OU decay per step
    centering: float = 0.15  # rad per corridor width of left/right diagonal range imbalance
    replan_every: int = 25
    novelty: float = 1.5  # weight of the visit bias
    blocked: float = 0.35  # forward range (corridor widths) below which the agent replans
    choice_noise: float = 0.3  # std of the random perturbation of beam scores

    def to_dict(self) -> dict:
        return asdict(self)


class ExploringDriver:
    """Wall-avoiding random walk with persistence and a bias towards less-visited cells.

    Args:
        maze: used for its corridor width and cell grid (visit counts).
        beam_angles: LiDAR beam angles relative to the heading ``[B]``.
        seed: seeds the driver's randomness.
    """

    def __init__(self, maze: Maze, beam_angles, seed: int = 0, config=DriverConfig()):  # noqa: B008
        self.maze = maze
        self.w = maze.corridor_width
        self.beam_angles = np.asarray(beam_angles, dtype=np.float64)  # [B]
        self.config = config
        self.rng = np.random.default_rng(seed)
        self.visits = np.zeros((maze.cells, maze.cells))  # [n, n]
        self._target = None
        self._since_plan = 0
        self._wiggle = 0.0
        rel = wrap_angle(self.beam_angles)
        self._front = np.abs(rel) <= np.deg2rad(25) + 1e-9  # [B] beams counting as "ahead"
        self._left = self._nearest(np.deg2rad(40))
        self._right = self._nearest(np.deg2rad(-40))

    def _nearest(self, rel_angle: float) -> int:
        return int(np.argmin(np.abs(wrap_angle(self.beam_angles - rel_angle))))

    def coverage(self) -> float:
        """Fraction of maze cells visited so far."""
        return float(np.mean(self.visits > 0))

    def act(self, ranges, pose) -> np.ndarray:
        """Control ``[2]`` = (rotation rad, forward offset) given LiDAR ``ranges`` ``[B]``."""
        cfg, w = self.config, self.w
        ranges = np.asarray(ranges, dtype=np.float64) / w  # [B] in corridor widths
        pose = np.asarray(pose, dtype=np.float64)
        i, j = self.maze.cell_of(pose[:2])
        self.visits[i, j] += 1
        front = ranges[self._front].min()
        self._since_plan += 1
        if self._target is None or self._since_plan >= cfg.replan_every or front < cfg.blocked:
            self._target = self._choose_heading(ranges, pose)
            self._since_plan = 0
        self._wiggle = cfg.persistence * self._wiggle + cfg.wiggle * self.rng.standard_normal()
        err = float(wrap_angle(self._target - pose[2]))
        centre = cfg.centering * (ranges[self._left] - ranges[self._right])
        rot = float(
            np.clip(cfg.gain * err + self._wiggle + centre, -cfg.max_rotation, cfg.max_rotation)
        )
        slow = np.clip((front - cfg.blocked) / 0.6, 0.0, 1.0) * (
            1.0 - 0.7 * abs(rot) / cfg.max_rotation
        )
        fwd = cfg.speed * w * slow
        return np.array([rot, fwd])

    def _choose_heading(self, ranges, pose) -> float:
        """Absolute heading of the best-scoring open beam."""
        cfg = self.config
        absolute = pose[2] + self.beam_angles  # [B]
        reach = np.clip(ranges - 0.4, 0.0, 1.0)  # [B] look one corridor width ahead at most
        ahead = pose[:2] + (reach * self.w)[:, None] * np.stack(
            [np.cos(absolute), np.sin(absolute)], -1
        )
        cells = self.maze.cell_of(ahead)  # [B, 2]
        novelty = 1.0 / (1.0 + self.visits[cells[:, 0], cells[:, 1]] / 20.0)
        score = (
            np.minimum(ranges, 2.0) / 2.0
            + 0.5 * np.cos(self.beam_angles)
            + cfg.novelty * novelty
            + cfg.choice_noise * self.rng.standard_normal(len(ranges))
        )
        score[ranges < cfg.blocked + 0.3] = -np.inf
        if not np.isfinite(score).any():  # boxed in: turn towards the most open beam
            return float(absolute[np.argmax(ranges)])
        return float(absolute[np.argmax(score)])


class TourDriver:
    """Drives to each of a list of positions in turn, through the maze's cell graph.

    For a mapping traversal that must *cover* given places (e.g. the navigation benchmark's
    start/target grid, which a random walk can miss for 20,000 steps): the next point is the
    one fewest cells away (breadth-first search over :meth:`Maze.neighbours`); the agent goes
    through the centres of the cells on the way, then to the point itself, turning on the spot
    towards each waypoint (at most ``max_rotation`` per step) and moving forward once facing it.
    The points must lie in free space with room for the agent (e.g.
    :func:`pyro_slam.planning.free_grid`). Closed loop on the true pose, like
    :class:`ExploringDriver`.

    Args:
        maze: the maze (cell graph and corridor width).
        points: positions to visit ``[P, 2]``.
        speed: forward offset per step, corridor widths.
        tol: a point counts as reached within this distance (cell centres: 2 * tol).
    """

    def __init__(
        self, maze: Maze, points, speed: float = 0.05, max_rotation: float = 0.3, tol: float = 0.005
    ):
        self.maze = maze
        self.todo = [np.asarray(p, dtype=np.float64) for p in np.asarray(points).reshape(-1, 2)]
        self.step_len = speed * maze.corridor_width
        self.max_rotation = max_rotation
        self.tol = tol
        self.route: list[np.ndarray] = []  # waypoints to the current point, the point last
        self.reached: list[np.ndarray] = []

    @property
    def done(self) -> bool:
        return not self.route and not self.todo

    def _cell_path(self, a, b) -> list[tuple[int, int]]:
        """Cells from ``a`` to ``b`` (inclusive) by breadth-first search."""
        a, b = tuple(int(v) for v in a), tuple(int(v) for v in b)
        prev, frontier = {a: None}, [a]
        while frontier and b not in prev:
            nxt = []
            for c in frontier:
                for n in self.maze.neighbours(*c):
                    if n not in prev:
                        prev[n] = c
                        nxt.append(n)
            frontier = nxt
        if b not in prev:
            raise ValueError(f"cell {b} cannot be reached from cell {a}")
        path = [b]
        while path[-1] != a:
            path.append(prev[path[-1]])
        return path[::-1]

    def _plan(self, xy) -> None:
        here = self.maze.cell_of(xy)
        paths = [self._cell_path(here, self.maze.cell_of(p)) for p in self.todo]
        k = int(np.argmin([len(p) for p in paths]))
        point = self.todo.pop(k)
        self.route = [self.maze.cell_center(*c) for c in paths[k]] + [point]

    def act(self, pose) -> np.ndarray | None:
        """Control ``[2]`` towards the next waypoint, or ``None`` when every point is reached."""
        pose = np.asarray(pose, dtype=np.float64)
        while True:
            if not self.route:
                if not self.todo:
                    return None
                self._plan(pose[:2])
            d = self.route[0] - pose[:2]
            dist = float(np.hypot(*d))
            last = len(self.route) == 1
            if dist > (self.tol if last else 2 * self.tol):
                break
            p = self.route.pop(0)
            if last:
                self.reached.append(p)
        err = float(wrap_angle(np.arctan2(d[1], d[0]) - pose[2]))
        rot = float(np.clip(err, -self.max_rotation, self.max_rotation))
        left = err - rot  # heading error after the rotation
        fwd = min(self.step_len, dist) * np.cos(left) if abs(left) < 0.1 else 0.0
        return np.array([rot, fwd])
