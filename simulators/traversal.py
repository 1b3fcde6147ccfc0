"""Simulate one long driven traversal of a maze and package it as a :class:`Traversal`."""

from __future__ import annotations

import warnings

import numpy as np

from simulators.camera import Camera, CameraConfig
from simulators.driver import DriverConfig, ExploringDriver, TourDriver
from simulators.maze import Maze, make_maze
from simulators.world import AGENT_RADIUS, LidarConfig, OdometryNoise, World, wrap_angle
from slamdata import Traversal

SIMULATOR_VERSION = "0.1.0"


def integrate_controls(start, controls) -> np.ndarray:
    """Dead reckoning with the rotate-then-forward model: ``[3]``, ``[T-1, 2]`` -> ``[T, 3]``."""
    controls = np.asarray(controls, dtype=np.float64)
    heading = start[2] + np.concatenate([[0.0], np.cumsum(controls[:, 0])])  # [T]
    step = controls[:, 1:2] * np.stack([np.cos(heading[1:]), np.sin(heading[1:])], -1)  # [T-1, 2]
    xy = start[:2] + np.concatenate([np.zeros((1, 2)), np.cumsum(step, 0)])  # [T, 2]
    return np.concatenate([xy, wrap_angle(heading)[:, None]], -1)


def simulate_traversal(
    maze: str | Maze = "moderate-medium",
    steps: int = 3000,
    seed: int = 1,
    images: bool = False,
    distractors: int = 0,
    noise: OdometryNoise | dict | None = None,
    noise_seed: int | tuple[int, ...] | None = None,
    lidar: LidarConfig = LidarConfig(),  # noqa: B008 (frozen dataclass)
    camera: CameraConfig = CameraConfig(),  # noqa: B008
    driver: DriverConfig = DriverConfig(),  # noqa: B008
    tour=None,
    tour_skip: float = 0.02,
    max_tour_steps: int = 20000,
    rotation: float = 0.0,
) -> Traversal:
    """Drive the scripted explorer through a maze for ``steps`` time steps.

    Args:
        maze: a scale name (generated with ``seed``) or a ready :class:`Maze`.
        steps: number of time steps ``T`` (observations); there are ``T - 1`` controls.
        seed: seeds maze, distractor layout, start pose, actuation noise and driver.
        images: also render first-person camera frames ``[T, 24, 32]``.
        distractors: number of boxes visible to the sensors but absent from ``walls``.
        noise: actuation noise, see :class:`OdometryNoise` (``None`` = calibrated defaults,
            ``0`` = noiseless).
        noise_seed: seeds the actuation noise instead of ``seed`` (see :class:`World`); the
            benchmarks pass ``(seed, maze seed)`` so that each maze gets its own noise.
        tour: positions ``[P, 2]`` to visit after the ``steps`` exploring steps (a
            :class:`TourDriver` drives there; the traversal then has more than ``steps``
            steps). Points the exploring steps passed within ``tour_skip`` are left out. Used to
            make a mapping traversal cover given places; at most ``max_tour_steps`` extra steps.
        rotation: turn the whole world (walls and poses) by this angle (rad) about the maze's
            centre, so that its walls no longer run along the world axes; the scans, controls
            and motion are unchanged (the physics does not depend on the frame).
    Returns:
        a :class:`Traversal` with LiDAR observations ``[T, B]``, commanded controls
        ``[T-1, 2]``, true poses ``[T, 3]`` and the maze walls.
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    maze = make_maze(maze, seed) if isinstance(maze, str) else maze
    world = World(maze, lidar, noise, distractors=distractors, seed=seed, noise_seed=noise_seed)
    agent = ExploringDriver(
        maze, lidar.beam_angles, seed=np.random.SeedSequence([seed, 1]), config=driver
    )
    obs, poses, controls = _drive(world, agent, steps)
    toured = None
    if tour is not None:
        toured = _drive_tour(world, maze, tour, tour_skip, max_tour_steps, poses, obs, controls)
        toured["steps"] = len(poses) - steps
    obs, poses = np.array(obs), np.array(poses)
    controls = np.array(controls).reshape(-1, 2)
    frames = None
    if images:
        cam = Camera(maze.walls, maze.corridor_width, world.distractor_segments, camera)
        frames = cam.render(poses)
    cam_cfg = camera if images else None
    args = (maze, world, agent, seed, noise_seed, lidar, cam_cfg, driver, distractors, toured)
    metadata = _metadata(*args)
    walls = maze.walls
    if rotation:
        walls, poses = _rotate(walls, poses, rotation, maze.side / 2)
        metadata["rotation"] = float(rotation)
    return Traversal(
        observations=obs.astype(np.float32),
        controls=controls,
        walls=walls,
        beam_angles=lidar.beam_angles,
        max_range=lidar.max_range,
        poses=poses,
        images=frames,
        metadata=metadata,
    )


def _drive(world: World, agent: ExploringDriver, steps: int):
    """``steps`` steps of ``agent`` in ``world``: lists of scans ``[B]``, poses ``[3]`` and the
    ``steps - 1`` controls ``[2]`` between them."""
    obs, poses, controls = [], [], []  # [T, B], [T, 3], [T-1, 2]
    for t in range(steps):
        poses.append(world.pose)
        obs.append(world.lidar())
        if t < steps - 1:
            controls.append(agent.act(obs[t], poses[t]))
            world.step(controls[t])
    return obs, poses, controls


def _rotate(walls: np.ndarray, poses: np.ndarray, angle: float, centre: float):
    """Walls ``[W, 4]`` and poses ``[T, 3]`` turned by ``angle`` about ``(centre, centre)``."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]])

    def turn(xy):
        return (xy - centre) @ rot.T + centre

    w = np.concatenate([turn(walls[:, :2]), turn(walls[:, 2:])], -1)
    p = np.concatenate([turn(poses[:, :2]), wrap_angle(poses[:, 2:] + angle)], -1)
    return w, p


def _drive_tour(world, maze, tour, skip: float, max_steps: int, poses, obs, controls) -> dict:
    """Drive a :class:`TourDriver` from the world's pose through the points of ``tour [P, 2]``
    that the path ``poses`` did not pass within ``skip``, appending to ``poses``, ``obs`` and
    ``controls``; returns the tour's record for the metadata."""
    tour = np.asarray(tour, dtype=np.float64).reshape(-1, 2)
    seen = np.linalg.norm(np.asarray(poses)[None, :, :2] - tour[:, None], axis=2).min(1)
    missed = tour[seen > skip]  # [P', 2]
    guide = TourDriver(maze, missed)
    for _ in range(max_steps):
        u = guide.act(world.pose)
        if u is None:
            break
        controls.append(u)
        world.step(u)
        poses.append(world.pose)
        obs.append(world.lidar())
    if not guide.done:
        warnings.warn(
            f"tour: {len(guide.reached)} of {len(missed)} points reached "
            f"within max_tour_steps={max_steps}",
            stacklevel=3,
        )
    return {"points": missed.tolist(), "reached": len(guide.reached), "skip": skip}


def _metadata(maze, world, agent, seed, noise_seed, lidar, camera, driver, distractors, toured):
    """The traversal's metadata: simulator, seeds, maze, sensors, noise, driver, tour."""
    return {
        "simulator": "simulators (pymunk maze)",
        "simulator_version": SIMULATOR_VERSION,
        "seed": int(seed),
        "noise_seed": None if noise_seed is None else np.atleast_1d(noise_seed).tolist(),
        "maze": {
            "name": maze.name,
            "seed": maze.seed,
            "side": maze.side,
            "cells": maze.cells,
            "corridor_width": maze.corridor_width,
        },
        "sensor": {
            "type": "lidar",
            "n_beams": lidar.n_beams,
            "max_range": lidar.max_range,
            "method": lidar.method,
            "range_noise": lidar.range_noise,
            "short_prob": lidar.short_prob,
            "dropout_prob": lidar.dropout_prob,
        },
        "camera": None if camera is None else camera.to_dict(),
        "noise": world.noise.to_dict(),
        "control_model": "rotate_forward",
        "agent": {"radius": AGENT_RADIUS, "clearance": world.clearance},
        "driver": driver.to_dict(),
        "distractors": int(distractors),
        "distractor_segments": world.distractor_segments.tolist(),
        "collisions": world.collisions,
        "coverage": agent.coverage(),
        "tour": toured,
    }
