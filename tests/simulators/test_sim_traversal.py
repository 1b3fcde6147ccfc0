import json

import numpy as np
import pytest

from pyro_slam.cli import main
from pyro_slam.data import load
from simulators import DriverConfig, integrate_controls, make_maze, simulate_traversal
from simulators.plotting import plot_traversal


@pytest.fixture(scope="module")
def traversal():
    return simulate_traversal("moderate-medium", steps=3000, seed=1)


def test_traversal_fields(traversal):
    tr = traversal
    maze = make_maze("moderate-medium", 1)
    w = maze.corridor_width
    assert tr.observations.shape == (3000, 20) and tr.observations.dtype == np.float32
    assert tr.controls.shape == (2999, 2) and tr.poses.shape == (3000, 3)
    np.testing.assert_array_equal(tr.walls, maze.walls)
    np.testing.assert_allclose(tr.beam_angles, 2 * np.pi * np.arange(20) / 20)
    assert tr.max_range == 0.53 and tr.images is None
    assert 0 < tr.observations.min() and tr.observations.max() <= 0.53
    assert maze.contains(tr.poses[:, :2]).all()
    assert np.all((tr.poses[:, 2] >= -np.pi) & (tr.poses[:, 2] < np.pi))
    assert np.abs(tr.controls[:, 0]).max() <= 0.3 + 1e-6
    fwd = tr.controls[:, 1]
    assert fwd.min() >= 0 and fwd.max() <= 0.06 * w + 1e-6
    assert 0.025 * w < fwd.mean() < 0.05 * w  # ~0.03-0.06 corridor widths per step
    meta = json.loads(json.dumps(tr.metadata))
    assert meta["control_model"] == "rotate_forward"
    assert meta["maze"] == {
        "name": "moderate-medium",
        "seed": 1,
        "side": 1.0,
        "cells": 6,
        "corridor_width": w,
    }
    assert meta["sensor"]["n_beams"] == 20 and meta["noise"]["rotation_std"] > 0
    assert meta["simulator_version"] and meta["collisions"] == 0


def test_driver_covers_the_maze(traversal):
    assert traversal.metadata["coverage"] >= 0.9  # measured 0.99 mean over 30 seeds
    cells = make_maze("moderate-medium", 1).cell_of(traversal.poses[:, :2])
    assert len(np.unique(cells, axis=0)) / 36 == pytest.approx(traversal.metadata["coverage"])


def test_path_integration_drift_is_calibrated():
    errors = []
    for seed in range(4):
        tr = simulate_traversal("moderate-medium", steps=3000, seed=seed)
        dead = integrate_controls(tr.poses[0], tr.controls)
        errors.append(np.linalg.norm(dead[-1, :2] - tr.poses[-1, :2]))
    assert 0.05 < np.mean(errors) < 0.3  # paper: 0.14 +- 0.1; ours 0.15 +- 0.10 over 40 seeds


def test_noiseless_controls_integrate_to_poses():
    tr = simulate_traversal("simple-medium", steps=800, seed=2, noise=0)
    assert tr.metadata["collisions"] == 0
    np.testing.assert_allclose(
        integrate_controls(tr.poses[0], tr.controls)[:, :2], tr.poses[:, :2], atol=1e-4
    )


def test_reproducible_by_seed():
    a, b, c = (simulate_traversal("simple-small", 300, seed=s, distractors=2) for s in (4, 4, 5))
    for field in ("observations", "controls", "poses", "walls"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert a.metadata == b.metadata
    assert not np.array_equal(a.poses, c.poses)


@pytest.mark.parametrize("name", ["simple-small", "complex-large"])
def test_driver_scales_with_corridor_width(name):
    tr = simulate_traversal(name, steps=1500, seed=3)
    w = make_maze(name, 3).corridor_width
    assert tr.metadata["collisions"] == 0
    assert 0.025 * w < tr.controls[:, 1].mean() < 0.05 * w
    assert tr.metadata["coverage"] > (0.8 if name == "simple-small" else 0.1)


def test_distractor_traversal_and_roundtrip_with_images(tmp_path):
    tr = simulate_traversal("moderate-medium", steps=150, seed=6, images=True, distractors=3)
    assert tr.images.shape == (150, 24, 32) and 0 <= tr.images.min() <= tr.images.max() <= 1
    segs = np.asarray(tr.metadata["distractor_segments"])
    assert segs.shape == (12, 4)
    np.testing.assert_array_equal(tr.walls, make_maze("moderate-medium", 6).walls)
    back = load(tr.save(tmp_path / "t.npz"))
    for field in ("observations", "controls", "poses", "walls", "beam_angles", "images"):
        np.testing.assert_array_equal(getattr(back, field), getattr(tr, field))
    assert back.max_range == tr.max_range and back.metadata == tr.metadata


def test_cli_and_plot(tmp_path, capsys):
    out = tmp_path / "sim" / "trav.npz"
    assert (
        main(
            [
                "simulate",
                "--maze",
                "simple-medium",
                "--steps",
                "200",
                "--seed",
                "3",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    line = capsys.readouterr().out.strip()
    assert line.startswith("simulate: simple-medium") and "T=200" in line and "\n" not in line
    tr = load(out)
    assert tr.num_steps == 200 and tr.metadata["maze"]["seed"] == 3
    png = out.with_suffix(".png")
    assert png.read_bytes()[:4] == b"\x89PNG" and png.stat().st_size > 10_000
    assert plot_traversal(tr, tmp_path / "s.png", scan_step=0).exists()
    with pytest.raises(IndexError):
        plot_traversal(tr, tmp_path / "bad.png", scan_step=200)


def test_driver_config_is_recorded():
    tr = simulate_traversal("simple-small", 50, seed=0, driver=DriverConfig(speed=0.03))
    assert tr.metadata["driver"]["speed"] == 0.03


def test_tour_visits_the_points_a_random_walk_missed():
    from pyro_slam.planning import free_grid

    maze = make_maze("moderate-medium", 1005)
    pts = free_grid(maze)  # [25, 2]
    walk = simulate_traversal(maze, steps=400, seed=1)
    tr = simulate_traversal(maze, steps=400, seed=1, tour=pts)
    np.testing.assert_array_equal(tr.poses[:400], walk.poses)  # the walk itself is unchanged
    dist = np.linalg.norm(tr.poses[None, :, :2] - pts[:, None], axis=2).min(1)  # [25]
    seen = np.linalg.norm(walk.poses[None, :, :2] - pts[:, None], axis=2).min(1)
    assert (seen > 0.02).sum() >= 10  # the walk alone misses many points
    tour = tr.metadata["tour"]
    assert tour["reached"] == len(tour["points"]) == (seen > 0.02).sum()
    assert dist.max() <= 0.02 and dist[seen > 0.02].max() <= 0.01
    assert tr.metadata["collisions"] == 0
    assert len(tr.poses) == 400 + tour["steps"] == len(tr.controls) + 1
    assert np.abs(tr.controls[:, 0]).max() <= 0.3 + 1e-9
    assert tr.controls[:, 1].max() <= 0.05 * maze.corridor_width + 1e-12
    assert tr.observations.shape == (len(tr.poses), 20)


def test_tour_driver_rejects_an_unreachable_point():
    from simulators import TourDriver

    maze = make_maze("moderate-medium", 1005)
    maze.v_walls[1, :] = True  # wall off column 0 entirely
    drv = TourDriver(maze, [maze.cell_center(0, 0)])
    with pytest.raises(ValueError, match="cannot be reached"):
        drv.act(np.array([*maze.cell_center(3, 3), 0.0]))
