import numpy as np
import pytest

from simulators import LidarConfig, OdometryNoise, World, integrate_controls, make_maze, raycast
from simulators.world import point_segment_distance


def _segments_cross(p, q, walls) -> np.ndarray:
    """Whether segment p-q touches or crosses each wall ``[W]`` (orientation test)."""
    a, b = walls[:, :2], walls[:, 2:]

    def orient(u, v, w):
        return np.sign(
            (v[..., 0] - u[..., 0]) * (w[..., 1] - u[..., 1])
            - (v[..., 1] - u[..., 1]) * (w[..., 0] - u[..., 0])
        )

    o1, o2 = orient(p, q, a), orient(p, q, b)
    o3, o4 = orient(a, b, p), orient(a, b, q)
    return (o1 * o2 <= 0) & (o3 * o4 <= 0) & ~((o1 == 0) & (o2 == 0))  # ignore collinear


def _random_inside(world, rng, n):
    side = world.maze.side
    xy = rng.uniform(1e-3, side - 1e-3, (n, 2))
    return np.column_stack([xy, rng.uniform(-np.pi, np.pi, n)])


@pytest.mark.parametrize("name,distractors", [("moderate-medium", 0), ("complex-small", 6)])
def test_pymunk_lidar_equals_analytic_intersection(name, distractors):
    world = World(make_maze(name, 4), distractors=distractors, seed=4)
    rng = np.random.default_rng(0)
    errs, hits = [], 0
    for pose in _random_inside(world, rng, 1500):
        world.reset(pose)
        angles = pose[2] + world.lidar_config.beam_angles
        ref = raycast(world.segments, pose[None, :2], angles[None], 0.53)[0]
        pm = world.lidar_pymunk()
        errs.append(np.abs(pm - ref).max())
        hits += int(np.sum(ref < 0.53))
        np.testing.assert_array_equal(world.lidar_numpy(), ref)
    assert max(errs) < 1e-6
    assert hits > 1500 * 5  # most beams do hit something


def test_beam_layout_against_grid_walls():
    cfg = LidarConfig()
    np.testing.assert_allclose(cfg.beam_angles, 2 * np.pi * np.arange(20) / 20)
    maze = make_maze("moderate-medium", 2)
    w = maze.corridor_width
    world = World(maze, odometry_noise=0, seed=0)
    for i in range(maze.cells):
        for j in range(maze.cells):
            x, y = maze.cell_center(i, j)
            world.reset((x, y, 0.0))
            k = i + 1
            while not maze.v_walls[k, j]:
                k += 1
            assert world.lidar()[0] == pytest.approx(min(k * w - x, 0.53), abs=1e-12)
            world.reset((x, y, -np.pi / 2))  # beam 5 (+90 deg) now points along +x too
            assert world.lidar()[5] == pytest.approx(min(k * w - x, 0.53), abs=1e-12)


def test_control_semantics_rotate_then_move(open_box):
    world = World(open_box, odometry_noise=0, pose=(0.5, 0.5, 0.0))
    world.step((0.7, 0.0))
    np.testing.assert_array_equal(world.pose[:2], [0.5, 0.5])  # pure rotation: x, y unchanged
    assert world.pose[2] == pytest.approx(0.7, abs=1e-15)
    world.reset((0.5, 0.5, 0.0))
    world.step((np.pi / 2, 0.1))
    np.testing.assert_allclose(world.pose, [0.5, 0.6, np.pi / 2], atol=1e-15)
    world.step((-np.pi / 2, -0.2))  # negative offsets move backwards
    np.testing.assert_allclose(world.pose, [0.3, 0.6, 0.0], atol=1e-15)
    world.step((np.pi, 0.0))
    assert world.pose[2] == pytest.approx(-np.pi)  # wrapped into [-pi, pi)


def test_noiseless_steps_match_kinematics(open_box):
    world = World(open_box, odometry_noise=0, pose=(0.5, 0.5, 0.3))
    rng = np.random.default_rng(0)
    controls = np.column_stack([rng.uniform(-0.3, 0.3, 200), rng.uniform(0, 0.004, 200)])
    poses = [world.pose] + [world.step(u) for u in controls]
    np.testing.assert_allclose(poses, integrate_controls(poses[0], controls), atol=1e-12)


def test_collision_stops_clearance_before_wall(open_box):
    world = World(open_box, odometry_noise=0, pose=(0.5, 0.5, 0.0))
    world.step((0.0, 5.0))
    np.testing.assert_allclose(world.pose, [1 - 1e-3, 0.5, 0.0], atol=1e-12)
    assert world.collisions == 1
    world.step((0.0, 5.0))  # pressing on: no motion, no escape
    np.testing.assert_allclose(world.pose, [1 - 1e-3, 0.5, 0.0], atol=1e-12)
    world.reset((0.5, 0.5, np.pi / 4))  # oblique hit: clearance is perpendicular to the wall
    world.step((0.0, 5.0))
    assert world.pose[0] == pytest.approx(1 - 1e-3) and world.pose[1] < 1 - 1e-3


@pytest.mark.parametrize("distractors", [0, 8])
def test_random_controls_never_leave_or_cross_walls(distractors):
    maze = make_maze("moderate-small", 9)
    world = World(maze, distractors=distractors, seed=9)
    w = maze.corridor_width
    rng = np.random.default_rng(1)
    blocked = 0
    for t in range(3000):
        start = world.pose
        fwd = rng.choice([rng.uniform(0, 0.1 * w), rng.uniform(0, 3 * w), -rng.uniform(0, w)])
        world.step((rng.uniform(-np.pi, np.pi), fwd))
        end = world.pose
        assert maze.contains(end[:2]), (t, start, end)
        crossed = _segments_cross(start[:2], end[:2], world.segments)
        assert not crossed.any(), (t, start, end, world.segments[crossed])
        assert point_segment_distance(end[:2], world.segments).min() > 0
        blocked += np.linalg.norm(end[:2] - start[:2]) < abs(fwd) * 0.5
    assert world.collisions > 500 and blocked > 300  # the controls really did hit walls


def test_actuation_noise_is_seeded_and_drifts(open_box):
    controls = [(0.05, 0.002)] * 100

    def run(seed, noise=None):
        world = World(open_box, odometry_noise=noise, seed=seed, pose=(0.5, 0.5, 0.0))
        return np.array([world.step(u) for u in controls])

    np.testing.assert_array_equal(run(3), run(3))
    assert not np.array_equal(run(3), run(4))
    dead = integrate_controls(np.array([0.5, 0.5, 0.0]), controls)[1:]
    assert np.abs(run(3) - dead).max() > 1e-3
    np.testing.assert_allclose(run(3, noise=0), dead, atol=1e-12)
    assert OdometryNoise.coerce({"rotation_std": 0.1}).forward_std == OdometryNoise().forward_std
    with pytest.raises(TypeError):
        OdometryNoise.coerce("loud")


def test_noise_seed_gives_worlds_with_one_seed_their_own_noise(open_box):
    controls = [(0.05, 0.002)] * 50

    def run(seed, noise_seed=None, start=None):
        world = World(open_box, seed=seed, noise_seed=noise_seed, pose=start)
        return world.pose.copy(), np.array([world.step(u) for u in controls])

    start, base = run(3)
    start_a, a = run(3, noise_seed=(3, 1001))
    np.testing.assert_array_equal(start_a, start)  # the start pose still follows seed
    assert np.abs(a - base).max() > 1e-3  # the noise does not
    np.testing.assert_array_equal(run(3, noise_seed=(3, 1001))[1], a)
    assert not np.array_equal(run(3, noise_seed=(3, 1002))[1], a)
    # the noise follows noise_seed alone: another seed, same start, same noise_seed
    np.testing.assert_array_equal(run(4, noise_seed=(3, 1001), start=start)[1], a)


def test_distractors_seen_by_lidar_but_not_in_floor_map():
    maze = make_maze("moderate-medium", 5)
    world = World(maze, distractors=6, seed=5)
    assert world.distractor_segments.shape == (24, 4)
    np.testing.assert_array_equal(maze.walls, make_maze("moderate-medium", 5).walls)
    for seg in world.distractor_segments:
        assert not np.any(np.all(np.isclose(maze.walls, seg), axis=1))
    seen = 0
    for seg in world.distractor_segments[::4]:  # look at each box from 0.1 corridor away
        centre = seg[:2] + 0.5 * (seg[2:] - seg[:2])
        normal = np.array([seg[1] - seg[3], seg[2] - seg[0]])
        normal /= np.linalg.norm(normal)
        for sign in (1, -1):
            p = centre + sign * 0.1 * maze.corridor_width * normal
            heading = np.arctan2(-sign * normal[1], -sign * normal[0])
            if (
                not maze.contains(p)
                or point_segment_distance(p, world.distractor_segments).min() < 0.01
            ):
                continue
            world.reset((*p, heading))
            floor_only = raycast(
                maze.walls, p[None], (heading + world.lidar_config.beam_angles)[None], 0.53
            )[0]
            r = world.lidar()
            assert r[0] < floor_only[0]
            assert r[0] == pytest.approx(0.1 * maze.corridor_width, rel=1e-9)
            seen += 1
    assert seen >= 6


def test_noisy_lidar_adds_gaussian_noise_short_returns_and_dropouts():
    """``LidarConfig`` noise: Gaussian of std ``range_noise * max_range``, a fraction of random
    short returns (below the true range) and of max-range dropouts; noise-free by default."""
    import numpy as np

    from simulators.world import LidarConfig

    exact = np.full((20000, 4), 0.3)
    rng = np.random.default_rng(0)
    assert LidarConfig().corrupt(exact, rng) is exact
    cfg = LidarConfig(range_noise=0.01, short_prob=0.05, dropout_prob=0.03)
    r = cfg.corrupt(exact, rng)
    drop = r == cfg.max_range
    short = r < 0.3 - 5 * 0.01 * cfg.max_range
    gauss = ~drop & ~short
    assert abs(drop.mean() - 0.03) < 0.005 and abs(short.mean() - 0.05 * 0.83) < 0.01
    assert abs((r[gauss] - 0.3).std() - 0.01 * cfg.max_range) < 2e-4
    assert ((r >= 0) & (r <= cfg.max_range)).all()
    import pytest

    with pytest.raises(ValueError, match="range_noise"):
        LidarConfig(range_noise=-0.1)


def test_rotated_world_keeps_scans_and_controls_and_turns_walls_and_poses():
    import numpy as np

    from simulators import raycast, simulate_traversal

    a = simulate_traversal("simple-small", steps=40, seed=2)
    b = simulate_traversal("simple-small", steps=40, seed=2, rotation=0.3)
    np.testing.assert_array_equal(a.observations, b.observations)
    np.testing.assert_array_equal(a.controls, b.controls)
    assert b.metadata["rotation"] == 0.3
    wall = b.walls[:, 2:] - b.walls[:, :2]
    angles = np.mod(np.arctan2(wall[:, 1], wall[:, 0]), np.pi / 2)
    np.testing.assert_allclose(angles, 0.3, atol=1e-9)  # every wall turned by 0.3
    ang = b.poses[:, 2:3] + b.beam_angles[None]
    np.testing.assert_allclose(
        raycast(b.walls, b.poses[:, :2], ang, b.max_range), b.observations, atol=1e-6
    )
