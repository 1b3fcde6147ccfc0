"""2-D maze simulator (pymunk) for the DVBF-LM experiments: mazes, LiDAR, camera, driver.

Public API::

    make_maze(name, seed) -> Maze
    World(maze, lidar=LidarConfig(), odometry_noise=None, distractors=0, seed=0, noise_seed=None)
    raycast(walls, origins, angles, max_range) -> ranges
    simulate_traversal(maze="moderate-medium", steps=3000, seed=1, images=False,
                       distractors=0, noise=None, noise_seed=None) -> slamdata.Traversal
"""

from simulators.camera import Camera, CameraConfig
from simulators.driver import DriverConfig, ExploringDriver, TourDriver
from simulators.maze import SCALES, Maze, Scale, make_maze
from simulators.raycast import raycast
from simulators.traversal import SIMULATOR_VERSION, integrate_controls, simulate_traversal
from simulators.world import LidarConfig, OdometryNoise, World, wrap_angle

__all__ = [
    "SCALES",
    "SIMULATOR_VERSION",
    "Camera",
    "CameraConfig",
    "DriverConfig",
    "ExploringDriver",
    "TourDriver",
    "LidarConfig",
    "Maze",
    "OdometryNoise",
    "Scale",
    "World",
    "integrate_controls",
    "make_maze",
    "raycast",
    "simulate_traversal",
    "wrap_angle",
]
