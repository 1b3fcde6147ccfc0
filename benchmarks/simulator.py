"""Simulator throughput: LiDAR stepping (World.step + 20-beam read) and camera frames/s.

Usage: ``python -m benchmarks.simulator [--steps 5000] [--maze moderate-medium]``; prints JSON.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from simulators import Camera, LidarConfig, World, make_maze, simulate_traversal


def _rate(n: int, fn) -> float:
    start = time.perf_counter()
    fn()
    return n / (time.perf_counter() - start)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.simulator", description=__doc__)
    parser.add_argument("--maze", default="moderate-medium")
    parser.add_argument("--steps", type=int, default=5000)
    args = parser.parse_args(argv)
    maze = make_maze(args.maze, 1)
    rng = np.random.default_rng(0)
    controls = np.stack(
        [
            rng.uniform(-0.3, 0.3, args.steps),
            rng.uniform(0, 0.06, args.steps) * maze.corridor_width,
        ],
        -1,
    ).tolist()
    result = {"maze": args.maze, "steps": args.steps}
    for method in ("numpy", "pymunk"):
        world = World(maze, LidarConfig(method=method), seed=1)

        def run(world=world):
            for u in controls:
                world.step(u)
                world.lidar()

        result[f"steps_per_s_{method}"] = round(_rate(args.steps, run), 1)
    result["steps_per_s"] = result[f"steps_per_s_{LidarConfig().method}"]
    world = World(maze, seed=1)
    poses = np.array([world.step(u) for u in controls])  # [N, 3]
    camera = Camera(maze.walls, maze.corridor_width)
    result["camera_frames_per_s_batched"] = round(
        _rate(len(poses), lambda: camera.render(poses)), 1
    )
    n = min(1000, len(poses))
    result["camera_frames_per_s_single"] = round(
        _rate(n, lambda: [camera.render(p) for p in poses[:n]]), 1
    )
    result["simulate_traversal_steps_per_s"] = round(
        _rate(3000, lambda: simulate_traversal(args.maze, 3000, seed=1)), 1
    )
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
