import numpy as np
import pytest

from simulators import Camera, CameraConfig, World, make_maze


def test_shape_range_and_pose_dependence():
    maze = make_maze("moderate-medium", 1)
    cam = Camera(maze.walls, maze.corridor_width)
    rng = np.random.default_rng(0)
    poses = np.array([maze.random_free_pose(rng) for _ in range(50)])
    img = cam.render(poses)
    assert img.shape == (50, 24, 32) and img.dtype == np.float32
    assert img.min() >= 0 and img.max() <= 1 and img.std() > 0.05
    assert cam.render(poses[0]).shape == (1, 24, 32)
    turned = cam.render(poses + [0, 0, np.pi / 2])
    assert np.abs(turned - img).mean(axis=(1, 2)).min() > 0.01  # every pose changes on a turn
    moved = cam.render(poses + [0.02, 0.0, 0.0])
    assert np.abs(moved - img).mean() > 0.005
    np.testing.assert_array_equal(cam.render(poses), img)  # deterministic


def test_wall_height_inverse_to_distance_and_depth(open_box):
    cam = Camera(open_box.walls, open_box.corridor_width)
    near, far = (0.75, 0.5, 0.0), (0.5, 0.5, 0.0)  # facing the x = 1 wall at 0.25 and 0.5
    col = cam.column_depth([near, far])  # [2, 32]
    np.testing.assert_allclose(col[:, 14:18], [[0.25] * 4, [0.5] * 4], atol=1e-12)
    depth = cam.depth([near, far])  # [2, 24, 32]
    rows = [(depth[k, :, 16] == col[k, 16]).sum() for k in range(2)]
    f = CameraConfig().focal
    assert rows[1] == pytest.approx(f * open_box.corridor_width / 0.5, abs=1.0)
    assert 1.7 < rows[0] / rows[1] < 2.4
    assert depth[1, -1, 16] < depth[1, 12, 16]  # floor below the wall is nearer
    assert depth.min() > 0


def test_wall_faces_are_shaded_differently(open_box):
    cam = Camera(open_box.walls, open_box.corridor_width)
    headings = [0.0, np.pi / 2, np.pi, -np.pi / 2]  # each wall face at the same distance
    centre = cam.render([(0.5, 0.5, h) for h in headings])[:, 12, 16]
    assert len(np.unique(np.round(centre, 3))) == 4
    assert np.diff(np.sort(centre)).min() > 0.02


def test_distractors_are_visible_to_the_camera():
    maze = make_maze("moderate-medium", 5)
    world = World(maze, distractors=6, seed=5)
    plain = Camera(maze.walls, maze.corridor_width)
    cluttered = Camera(maze.walls, maze.corridor_width, world.distractor_segments)
    seg = world.distractor_segments[0]
    centre = seg[:2] + 0.5 * (seg[2:] - seg[:2])
    normal = np.array([seg[1] - seg[3], seg[2] - seg[0]])
    normal /= np.linalg.norm(normal)
    p = centre + 0.2 * maze.corridor_width * normal
    pose = (*p, np.arctan2(-normal[1], -normal[0]))
    assert np.abs(cluttered.render(pose) - plain.render(pose)).max() > 0.1


def test_world_camera_matches_bulk_render():
    maze = make_maze("simple-large", 2)
    world = World(maze, distractors=2, seed=2)
    cam = Camera(maze.walls, maze.corridor_width, world.distractor_segments)
    np.testing.assert_array_equal(world.camera(), cam.render(world.pose)[0])
    np.testing.assert_array_equal(world.camera(depth=True), cam.depth(world.pose)[0])
