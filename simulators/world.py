"""The maze world: a pymunk space with static walls, a tiny dynamic agent and a 2-D LiDAR.

Pose ``z = (x, y, heading)``, heading in ``[-pi, pi)``. A control ``u = (rotation, forward)``
first rotates the agent by ``u[0]`` rad, then moves it ``u[1]`` along the new heading. The
executed controls carry actuation noise (additive on the rotation, multiplicative on the forward
offset); callers record the *commanded* controls as odometry, so integrating them drifts.

Walls have zero thickness, so a move is checked by sweeping the agent's path with a pymunk
segment query (a discrete physics step would let a 1e-5 radius body tunnel through); on a hit the
agent stops ``clearance`` away from the wall, measured perpendicular to it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import pymunk

from simulators.camera import Camera, CameraConfig
from simulators.maze import Maze
from simulators.raycast import raycast
from slamdata import wrap_angle  # noqa: F401 (the simulator's, re-exported)

AGENT_RADIUS = 1e-5
_AGENT_CATEGORY = 0b10
_SENSE_FILTER = pymunk.ShapeFilter(mask=pymunk.ShapeFilter.ALL_MASKS() ^ _AGENT_CATEGORY)


@dataclass(frozen=True)
class LidarConfig:
    """Range finder: ``n_beams`` beams evenly over 2 pi, beam ``i`` at ``heading + 2 pi i / n``.

    ``method`` picks the range computation: ``"numpy"`` (analytic :func:`raycast`) or
    ``"pymunk"`` (one ``segment_query_first`` per beam); both agree to ~1e-12.

    Noise (off by default, the paper's noise-free sensor): each reading gets Gaussian noise of
    std ``range_noise * max_range`` (clipped to ``[0, max_range]``); with probability
    ``short_prob`` a beam returns a random short range (uniform up to the true one: an object
    the map does not hold), with probability ``dropout_prob`` no return (``max_range``).
    """

    n_beams: int = 20
    max_range: float = 0.53
    method: str = "numpy"
    range_noise: float = 0.0
    short_prob: float = 0.0
    dropout_prob: float = 0.0

    def __post_init__(self):
        for name in ("range_noise", "short_prob", "dropout_prob"):
            v = getattr(self, name)
            if not (0.0 <= v < 1.0):
                raise ValueError(f"LidarConfig.{name} must be in [0, 1), got {v!r}")

    @property
    def noisy(self) -> bool:
        return bool(self.range_noise or self.short_prob or self.dropout_prob)

    def corrupt(self, ranges: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """``ranges [..., B]`` with this sensor's noise (returned as is when noise-free)."""
        if not self.noisy:
            return ranges
        r = ranges + self.range_noise * self.max_range * rng.standard_normal(ranges.shape)
        r = np.clip(r, 0.0, self.max_range)
        u = rng.random(ranges.shape)
        short = u < self.short_prob
        r = np.where(short, ranges * rng.random(ranges.shape), r)
        drop = (u >= self.short_prob) & (u < self.short_prob + self.dropout_prob)
        return np.where(drop, self.max_range, r)

    @property
    def beam_angles(self) -> np.ndarray:
        return 2 * np.pi * np.arange(self.n_beams) / self.n_beams  # [B]


@dataclass(frozen=True)
class OdometryNoise:
    """Actuation noise per step: executed rotation ``u0 + rotation_std * N(0, 1)`` (rad) and
    executed forward offset ``u1 * (1 + forward_std * N(0, 1))``.

    Defaults are calibrated so that integrating the commanded controls of a 3000-step
    moderate-medium traversal ends ~0.1-0.2 away from the true position (paper: 0.14 +- 0.1).
    """

    rotation_std: float = 6e-3
    forward_std: float = 0.03

    @classmethod
    def coerce(cls, noise) -> OdometryNoise:
        """``None`` -> defaults, ``False`` / ``0`` -> noiseless, dict -> fields, else as is."""
        if noise is None:
            return cls()
        if noise is False or (isinstance(noise, int | float) and noise == 0):
            return cls(0.0, 0.0)
        if isinstance(noise, dict):
            return cls(**noise)
        if isinstance(noise, cls):
            return noise
        raise TypeError(f"cannot interpret {noise!r} as OdometryNoise")

    def to_dict(self) -> dict:
        return asdict(self)


class World:
    """A maze, optional distractor boxes, and an agent with LiDAR.

    Args:
        maze: the floor plan.
        lidar: range sensor configuration.
        odometry_noise: actuation noise (see :class:`OdometryNoise`); ``None`` = defaults.
        distractors: number of small boxes placed in free space; seen by the sensors and
            blocking motion, but not part of ``maze.walls``.
        seed: seeds distractor layout, start pose and actuation noise.
        noise_seed: seeds the actuation noise instead of ``seed`` (an int or a sequence of
            ints, as ``numpy.random.SeedSequence`` takes), so that worlds which share ``seed``
            (e.g. one traversal seed over several mazes) need not share their noise.
        pose: start pose ``[3]``; random free pose if ``None``.
        clearance: how far before a wall a blocked move stops.
    """

    def __init__(
        self,
        maze: Maze,
        lidar: LidarConfig = LidarConfig(),  # noqa: B008 (frozen dataclass)
        odometry_noise: OdometryNoise | dict | None = None,
        distractors: int = 0,
        seed: int = 0,
        pose=None,
        clearance: float = 1e-3,
        noise_seed: int | tuple[int, ...] | None = None,
    ):
        self.maze = maze
        self.lidar_config = lidar
        self.noise = OdometryNoise.coerce(odometry_noise)
        self.clearance = float(clearance)
        self.seed = int(seed)
        layout_seq, pose_seq, noise_seq = np.random.SeedSequence(self.seed).spawn(3)
        if noise_seed is not None:
            noise_seq = np.random.SeedSequence(noise_seed)
        self._noise_rng = np.random.default_rng(noise_seq)
        # the sensor's own noise stream (a noise-free sensor draws nothing from it)
        self._sensor_rng = np.random.default_rng(np.random.SeedSequence([self.seed, 7]))
        self.distractor_segments = _place_distractors(maze, distractors, layout_seq)  # [D, 4]
        self.segments = np.concatenate([maze.walls, self.distractor_segments])  # [W + D, 4]
        self.collisions = 0  # number of blocked moves so far
        self._camera = None  # built on the first camera() call
        self._build_space()
        self.reset(pose if pose is not None else self._free_start(np.random.default_rng(pose_seq)))

    # ---------------------------------------------------------------- construction
    def _build_space(self) -> None:
        self.space = pymunk.Space()
        static = self.space.static_body
        shapes = [pymunk.Segment(static, s[:2], s[2:], 0.0) for s in self.segments.tolist()]
        self.body = pymunk.Body(1.0, pymunk.moment_for_circle(1.0, 0.0, AGENT_RADIUS))
        agent = pymunk.Circle(self.body, AGENT_RADIUS)
        agent.filter = pymunk.ShapeFilter(categories=_AGENT_CATEGORY)
        for s in [*shapes, agent]:
            s.elasticity = 0.0
            s.friction = 0.0
        self.space.add(*shapes, self.body, agent)

    def _free_start(self, rng: np.random.Generator) -> np.ndarray:
        """A random free pose at least a quarter corridor away from every distractor."""
        for _ in range(1000):
            pose = self.maze.random_free_pose(rng)
            if not len(self.distractor_segments):
                return pose
            d = point_segment_distance(pose[:2], self.distractor_segments)
            if d.min() > 0.25 * self.maze.corridor_width:
                return pose
        raise RuntimeError("no free start pose found; too many distractors?")

    # ---------------------------------------------------------------- state
    @property
    def pose(self) -> np.ndarray:
        """Current true pose ``[3]``."""
        return np.array([self._x, self._y, self._heading])

    def reset(self, pose) -> None:
        x, y, h = (float(v) for v in pose)
        if not self.maze.contains((x, y)):
            raise ValueError(f"pose {pose} lies outside the maze")
        self._x, self._y, self._heading = x, y, float(wrap_angle(h))
        self._sync_body()

    def _sync_body(self) -> None:
        self.body.position = (self._x, self._y)
        self.body.angle = self._heading

    # ---------------------------------------------------------------- dynamics
    def step(self, u) -> np.ndarray:
        """Execute the commanded control ``u = (rotation, forward)`` with actuation noise.

        Returns the new true pose ``[3]``.
        """
        rot, fwd = float(u[0]), float(u[1])
        if self.noise.rotation_std:
            rot += self.noise.rotation_std * self._noise_rng.standard_normal()
        if self.noise.forward_std:
            fwd *= 1.0 + self.noise.forward_std * self._noise_rng.standard_normal()
        heading = float(wrap_angle(self._heading + rot))
        self._heading = heading
        if fwd != 0.0:
            sign = math.copysign(1.0, fwd)
            self._move(sign * math.cos(heading), sign * math.sin(heading), abs(fwd))
        self._sync_body()
        return self.pose

    def _move(self, ux: float, uy: float, length: float) -> None:
        """Move ``length`` along the unit vector ``(ux, uy)``, stopping before obstacles."""
        start = (self._x, self._y)
        end = (self._x + ux * length, self._y + uy * length)
        hit = self.space.segment_query_first(start, end, 0.0, _SENSE_FILTER)
        if hit is not None:
            self.collisions += 1
            incidence = abs(ux * hit.normal.x + uy * hit.normal.y)
            travel = hit.alpha * length - self.clearance / max(incidence, 1e-9)
            length = max(travel, 0.0)
        self._x += ux * length
        self._y += uy * length

    # ---------------------------------------------------------------- sensing
    def lidar(self) -> np.ndarray:
        """Range reading ``[B]`` at the current pose (method from the config), with the
        sensor's noise (:meth:`LidarConfig.corrupt`)."""
        exact = self.lidar_pymunk() if self.lidar_config.method == "pymunk" else self.lidar_numpy()
        return self.lidar_config.corrupt(exact, self._sensor_rng)

    def lidar_numpy(self) -> np.ndarray:
        cfg = self.lidar_config
        angles = (self._heading + cfg.beam_angles)[None]  # [1, B]
        return raycast(self.segments, np.array([[self._x, self._y]]), angles, cfg.max_range)[0]

    def lidar_pymunk(self) -> np.ndarray:
        cfg = self.lidar_config
        r = cfg.max_range
        out = np.full(cfg.n_beams, r)
        for i, a in enumerate((self._heading + cfg.beam_angles).tolist()):
            end = (self._x + r * math.cos(a), self._y + r * math.sin(a))
            hit = self.space.segment_query_first((self._x, self._y), end, 0.0, _SENSE_FILTER)
            if hit is not None:
                out[i] = hit.alpha * r
        return out

    def camera(self, config=None, depth: bool = False) -> np.ndarray:
        """First-person image ``[24, 32]`` (or depth image with ``depth=True``) at the pose."""
        config = config or CameraConfig()
        if self._camera is None or self._camera.config != config:
            w = self.maze.corridor_width
            self._camera = Camera(self.maze.walls, w, self.distractor_segments, config)
        return (self._camera.depth if depth else self._camera.render)(self.pose)[0]


def point_segment_distance(p, segments: np.ndarray) -> np.ndarray:
    """Euclidean distance from point ``p`` ``[2]`` to each segment ``[S, 4]`` -> ``[S]``."""
    a, b = segments[:, :2], segments[:, 2:]
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, -1) / np.maximum(np.sum(ab * ab, -1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(a + t[:, None] * ab - p, axis=-1)


def _place_distractors(maze: Maze, k: int, seed_seq) -> np.ndarray:
    """``k`` randomly rotated small boxes near cell centres, as edge segments ``[4k, 4]``."""
    if k < 0:
        raise ValueError(f"distractors must be >= 0, got {k}")
    rng = np.random.default_rng(seed_seq)
    w = maze.corridor_width
    cells = maze.free_cells()
    chosen = cells[rng.choice(len(cells), size=k, replace=k > len(cells))]
    centres = maze.cell_center(chosen[:, 0], chosen[:, 1]) + rng.uniform(-0.15, 0.15, (k, 2)) * w
    half = rng.uniform(0.06, 0.12, k) * w  # [k]
    theta = rng.uniform(0, np.pi / 2, k)
    corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)  # [4, 2]
    c, s = np.cos(theta), np.sin(theta)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # [k, 2, 2]
    verts = centres[:, None] + np.einsum("kij,vj->kvi", rot, corners) * half[:, None, None]
    segs = np.concatenate([verts, np.roll(verts, -1, axis=1)], -1)  # [k, 4, 4]
    return segs.reshape(-1, 4)
