"""Trajectory data for PF-net (Karkus et al. 2018, Sec. V-A), scaled to our mazes.

Scale: a ``6 x 6``-cell maze of side 1.0 has corridors 1/6 wide, read as 1 m
(:data:`pyro_slam.pfnet.model.METRE`). The paper's motions then become: forward with probability
0.8, a distance ``U[20 cm, 80 cm]`` = ``U[0.033, 0.133]`` units, else rotate by
``U[15, 60]`` degrees (random sign); an action whose forward motion would collide is re-drawn.
The initial belief is ``N(c, diag(30 cm, 30 cm, 30 deg)^2)`` = ``diag(0.05, 0.05, 0.52 rad)``
around a centre ``c`` that is itself drawn from that Gaussian around the true start (so the
true start is distributed as ``N(c, .)`` as in the paper).

Odometry is the robot-frame increment ``(dx, dy, dtheta)`` of the *commanded* motion; the
simulator executes it with its calibrated actuation noise (3 % of the distance, 0.34 deg).

Sensors: the simulator's LiDAR (20 beams over 360 deg, range 0.53 ~ 3.2 m) and the z-depth
image ``[24, 32]`` of its first-person camera (90 deg field of view), divided by
:data:`DEPTH_SCALE` and clipped to [0, 1]. The "distractors" setting adds
:data:`N_DISTRACTORS` boxes per maze that both sensors see but the floor map lacks.

The sensor readings come from a *world* object passed to :func:`generate`; only
:class:`SimWorld` knows the simulator's API (tests use a numpy stand-in).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from tqdm.auto import tqdm

import simulators
from simulators.world import point_segment_distance

from ..geometry import wrap_angle
from .model import INIT_STD, METRE, ObsModelConfig, rasterize_floor_map

T_STEPS = 24
FORWARD_RANGE = (0.2 * METRE, 0.8 * METRE)
ROTATE_RANGE = (math.radians(15), math.radians(60))
P_FORWARD = 0.8


def relative_pose(z0: np.ndarray, z1: np.ndarray) -> np.ndarray:
    """Robot-frame increment ``(dx, dy, dtheta)`` from ``z0`` to ``z1`` (inverse of
    :func:`pyro_slam.geometry.odometry_delta`)."""
    c, s = np.cos(z0[..., 2]), np.sin(z0[..., 2])
    dx, dy = z1[..., 0] - z0[..., 0], z1[..., 1] - z0[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(z1[..., 2] - z0[..., 2])], -1)


@dataclass
class PFNetDataset:
    """A set of fixed-length trajectories with floor maps, in memory (numpy).

    Fields (``N`` trajectories, ``T`` steps, ``M`` mazes):
        poses [N, T, 3], odom [N, T-1, 3], lidar [N, T, n_beams], depth [N, T, h, w] or None,
        maze_index [N] (into ``maps`` / ``walls``), maps [M, R, R] floor rasters (walls only),
        walls: list of [W, 4], map_side, init_mean [N, 3] (fixed belief centres, used when
        ``fresh_init`` is False), beam_angles [n_beams], max_range.
    ``sensor`` selects what :meth:`batch` returns as ``obs``; ``fresh_init`` draws a new belief
    centre per call (training-time augmentation).
    """

    poses: np.ndarray
    odom: np.ndarray
    lidar: np.ndarray
    depth: np.ndarray | None
    maze_index: np.ndarray
    maps: np.ndarray
    walls: list
    map_side: float
    init_mean: np.ndarray
    beam_angles: np.ndarray
    max_range: float
    sensor: str = "lidar"
    fresh_init: bool = False
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def with_sensor(self, sensor: str, fresh_init: bool | None = None) -> PFNetDataset:
        if sensor == "depth" and self.depth is None:
            raise ValueError("this dataset has no depth images")
        fi = self.fresh_init if fresh_init is None else fresh_init
        return replace(self, sensor=sensor, fresh_init=fi)

    def obs_model_config(self, sensor: str | None = None, **kw) -> ObsModelConfig:
        """An :class:`~pyro_slam.pfnet.ObsModelConfig` matching this data's sensors."""
        cfg = dict(
            sensor=sensor or self.sensor,
            beam_angles=tuple(float(a) for a in self.beam_angles),
            max_range=self.max_range,
        )
        if self.depth is not None:
            cfg["image_shape"] = tuple(self.depth.shape[-2:])
            cfg["column_angles"] = tuple(self.meta.get("column_angles", ()))
            cfg["depth_scale"] = DEPTH_SCALE
        cfg.update(kw)
        return ObsModelConfig(**cfg)

    def subset(self, idx) -> PFNetDataset:
        idx = np.asarray(idx)
        return replace(
            self,
            poses=self.poses[idx],
            odom=self.odom[idx],
            lidar=self.lidar[idx],
            depth=None if self.depth is None else self.depth[idx],
            maze_index=self.maze_index[idx],
            init_mean=self.init_mean[idx],
        )

    def batch(self, idx, generator: torch.Generator | None = None) -> dict:
        """Tensors for trajectories ``idx`` (see :mod:`pyro_slam.pfnet` for the keys)."""
        idx = np.asarray(idx)
        poses = torch.as_tensor(self.poses[idx], dtype=torch.float32)
        obs = self.lidar[idx] if self.sensor == "lidar" else self.depth[idx]
        if self.fresh_init:
            eps = torch.randn(len(idx), 3, generator=generator) * torch.tensor(INIT_STD)
            init = poses[:, 0] + eps
            init[:, 2] = wrap_angle(init[:, 2])
        else:
            init = torch.as_tensor(self.init_mean[idx], dtype=torch.float32)
        return {
            "maps": torch.as_tensor(self.maps[self.maze_index[idx]], dtype=torch.float32)[:, None],
            "map_side": self.map_side,
            "walls": [self.walls[m] for m in self.maze_index[idx]],
            "obs": torch.as_tensor(obs, dtype=torch.float32),
            "odom": torch.as_tensor(self.odom[idx], dtype=torch.float32),
            "init_mean": init,
            "init_std": torch.tensor(INIT_STD),
            "poses": poses,
            "beam_angles": torch.as_tensor(self.beam_angles, dtype=torch.float32),
            "max_range": self.max_range,
        }

    def save(self, path) -> None:
        arrays = {k: getattr(self, k) for k in ("poses", "odom", "lidar", "maze_index", "maps")}
        arrays.update(init_mean=self.init_mean, beam_angles=self.beam_angles)
        if self.depth is not None:
            arrays["depth"] = self.depth
        arrays["walls_flat"] = np.concatenate(self.walls)
        arrays["walls_len"] = np.array([len(w) for w in self.walls])
        arrays["scalars"] = np.array([self.map_side, self.max_range])
        arrays["meta"] = np.asarray(json.dumps(self.meta))
        np.savez_compressed(path, **arrays)

    @classmethod
    def load(cls, path) -> PFNetDataset:
        with np.load(path) as f:
            d = {k: f[k] for k in f.files}
        walls = np.split(d["walls_flat"], np.cumsum(d["walls_len"])[:-1])
        return cls(
            poses=d["poses"],
            odom=d["odom"],
            lidar=d["lidar"],
            depth=d.get("depth"),
            maze_index=d["maze_index"],
            maps=d["maps"],
            walls=walls,
            map_side=float(d["scalars"][0]),
            init_mean=d["init_mean"],
            beam_angles=d["beam_angles"],
            max_range=float(d["scalars"][1]),
            meta=json.loads(str(d["meta"])) if "meta" in d else {},
        )


DEPTH_SCALE = 0.53  # depth-image value 1.0 = z-depth 0.53 (the LiDAR range); clipped above
N_DISTRACTORS = 36  # boxes per maze in the "distractors" setting (one per cell on average)


class SimWorld:
    """Adapter from ``simulators.World`` + ``simulators.Camera`` to what :func:`generate` uses.

    Members: ``reset(pose)``, ``step(u) -> bool`` (False if the move hit something),
    ``pose``, ``lidar() -> [B]``, ``depth_images(poses [T, 3]) -> [T, h, w]`` in [0, 1],
    ``random_start(rng) -> [3]``, ``beam_angles``, ``max_range``, ``column_angles``.
    Test stand-ins implement the same members.
    """

    def __init__(self, maze, distractors: int = 0, seed: int = 0, n_beams=20, max_range=0.53):
        self.maze = maze
        self.world = simulators.World(
            maze,
            lidar=simulators.LidarConfig(n_beams=n_beams, max_range=max_range),
            distractors=distractors,
            seed=seed,
        )
        cfg = simulators.CameraConfig()
        self.camera = simulators.Camera(
            maze.walls, maze.corridor_width, self.world.distractor_segments, cfg
        )
        self.beam_angles = self.world.lidar_config.beam_angles
        self.max_range = float(max_range)
        self.column_angles = cfg.column_offsets

    def random_start(self, rng) -> np.ndarray:
        d = self.world.distractor_segments
        for _ in range(1000):
            pose = self.maze.random_free_pose(rng)
            if not len(d) or point_segment_distance(pose[:2], d).min() > 0.25 * METRE:
                return pose
        raise RuntimeError("no free start pose")

    def reset(self, pose):
        self.world.reset(pose)

    def step(self, u) -> bool:
        n = self.world.collisions
        self.world.step(np.asarray(u, dtype=float))
        return self.world.collisions == n

    @property
    def pose(self) -> np.ndarray:
        return self.world.pose

    def lidar(self) -> np.ndarray:
        return self.world.lidar()

    def depth_images(self, poses) -> np.ndarray:
        return np.clip(self.camera.depth(poses) / DEPTH_SCALE, 0.0, 1.0)


def sample_trajectory(world, start, rng: np.random.Generator, T=T_STEPS, depth=True):
    """One collision-free trajectory of ``T`` steps from ``start`` in ``world`` (a
    :class:`SimWorld` or stand-in). A move that would collide is undone and re-drawn.

    Returns poses [T, 3], odometry [T-1, 3] (robot-frame increment of the *commanded* motion,
    so it carries the simulator's actuation noise), lidar [T, B], depth [T, h, w] or None.
    """
    world.reset(start)
    poses, scans, odom = [world.pose], [world.lidar()], []
    for _ in range(T - 1):
        prev = world.pose
        for _attempt in range(50):
            if rng.random() < P_FORWARD:
                u = (0.0, rng.uniform(*FORWARD_RANGE))
            else:
                u = (rng.choice([-1.0, 1.0]) * rng.uniform(*ROTATE_RANGE), 0.0)
            if world.step(u):
                break
            world.reset(prev)  # collision: re-draw the action
        else:  # boxed in: turn on the spot
            u = (math.pi / 2, 0.0)
            world.step(u)
        odom.append([u[1] * math.cos(u[0]), u[1] * math.sin(u[0]), u[0]])
        poses.append(world.pose)
        scans.append(world.lidar())
    poses = np.stack(poses)
    poses[:, 2] = wrap_angle(poses[:, 2])
    img = world.depth_images(poses) if depth else None
    return poses, np.asarray(odom), np.stack(scans), img


def generate(
    mazes: list,
    make_world,
    n_per_maze: int,
    seed: int = 0,
    T: int = T_STEPS,
    depth: bool = True,
    map_resolution: int = 64,
    progress: bool = False,
) -> PFNetDataset:
    """``n_per_maze`` trajectories in each of ``mazes`` (objects with ``walls`` and ``side``).

    ``make_world(maze, seed)`` returns a :class:`SimWorld` (or a stand-in with its members).
    The floor maps are rasterised from ``maze.walls`` only, so distractors never appear on them.
    """
    rng = np.random.default_rng(seed)
    P, O, L, D, idx, init = [], [], [], [], [], []
    maps, walls = [], []
    bar = tqdm(total=len(mazes) * n_per_maze, desc="trajectories", disable=not progress)
    for m, maze in enumerate(mazes):
        maps.append(rasterize_floor_map(maze.walls, maze.side, map_resolution))
        walls.append(np.asarray(maze.walls, dtype=np.float64))
        world = make_world(maze, int(rng.integers(2**31)))
        for _ in range(n_per_maze):
            p, o, s, d = sample_trajectory(world, world.random_start(rng), rng, T, depth)
            P.append(p)
            O.append(o)
            L.append(s)
            D.append(d)
            idx.append(m)
            c = p[0] + rng.normal(size=3) * np.array(INIT_STD)
            c[2] = wrap_angle(c[2])
            init.append(c)
            bar.update(1)
    bar.close()
    return PFNetDataset(
        poses=np.stack(P).astype(np.float32),
        odom=np.stack(O).astype(np.float32),
        lidar=np.stack(L).astype(np.float32),
        depth=np.stack(D).astype(np.float32) if depth else None,
        maze_index=np.asarray(idx),
        maps=np.stack(maps),
        walls=walls,
        map_side=float(mazes[0].side),
        init_mean=np.stack(init).astype(np.float32),
        beam_angles=np.asarray(world.beam_angles, dtype=np.float64),
        max_range=float(world.max_range),
        meta={"column_angles": np.asarray(world.column_angles).tolist()},
    )
