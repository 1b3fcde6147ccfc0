"""Trajectory metrics on constructed trajectories with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pyro_slam.data import Traversal
from pyro_slam.io import odometry_poses
from pyro_slam.metrics import (
    aligned_error,
    ate,
    calibration,
    coverage,
    distance_travelled,
    frame_error,
    localisation_error,
    relative_error,
    std_over_error,
    summary,
    write_trajectory_tum,
)
from simulators import integrate_controls, simulate_traversal

# unit square walked counter-clockwise: 1 unit per step, headings along the path
SQUARE = np.array([[0, 0, 0], [1, 0, math.pi / 2], [1, 1, math.pi], [0, 1, -math.pi / 2]], float)


def test_localisation_error_is_euclidean_in_xy():
    est = SQUARE + np.array([[0, 0, 1], [3, 4, 0], [-0.6, 0.8, 2], [0, -2, 0]])
    np.testing.assert_allclose(localisation_error(est, SQUARE), [0, 5, 1, 2])
    np.testing.assert_allclose(localisation_error(est[:, :2], SQUARE), [0, 5, 1, 2])  # [T, 2]
    with pytest.raises(ValueError, match="lengths differ: 3 vs 4"):
        localisation_error(est[:3], SQUARE)


def test_distance_and_relative_error():
    np.testing.assert_allclose(distance_travelled(SQUARE), [0, 1, 2, 3])
    est = SQUARE + np.array([0.3, 0.4, 0.0])  # constant 0.5 offset
    np.testing.assert_allclose(relative_error(est, SQUARE), [0, 0.5, 0.25, 0.5 / 3])
    still = np.zeros((3, 3))  # no motion: relative error defined as 0, never NaN
    np.testing.assert_array_equal(relative_error(still + 1, still), [0, 0, 0])


def test_ate_constant_offset_and_alignment():
    est = SQUARE + np.array([0.3, 0.4, 0.7])  # heading errors do not count
    r = ate(est, SQUARE)
    assert r["rmse"] == pytest.approx(0.5) and r["mean"] == pytest.approx(0.5)
    assert r["max"] == pytest.approx(0.5) and r["std"] == pytest.approx(0, abs=1e-12)
    # a rigid motion of the whole trajectory is removed by alignment (not by default)
    c, s = math.cos(0.3), math.sin(0.3)
    moved = SQUARE.copy()
    moved[:, :2] = SQUARE[:, :2] @ np.array([[c, s], [-s, c]]) + [2.0, -1.0]
    moved[:, 2] += 0.3
    assert ate(moved, SQUARE)["rmse"] > 1
    assert ate(moved, SQUARE, align=True)["rmse"] == pytest.approx(0, abs=1e-9)


def test_aligned_error_removes_a_rigid_turn_and_reports_its_angle():
    """A trajectory turned by 0.3 rad about its start (a map rotated as a whole) has a plain
    error growing along the path, no aligned error, and an aligning rotation of -0.3."""
    c, s = math.cos(0.3), math.sin(0.3)
    turned = SQUARE.copy()
    turned[:, :2] = SQUARE[:, :2] @ np.array([[c, s], [-s, c]])  # rows: R(0.3) p
    turned[:, 2] += 0.3
    err, rot = aligned_error(turned, SQUARE)
    assert localisation_error(turned, SQUARE)[2] == pytest.approx(2 * math.sqrt(2) * math.sin(0.15))
    np.testing.assert_allclose(err, 0, atol=1e-9)
    assert rot == pytest.approx(-0.3)
    # a shape error survives the alignment: one corner 0.4 off
    bent = SQUARE.copy()
    bent[2, :2] += [0.4, 0.0]
    err, rot = aligned_error(bent, SQUARE)
    assert err[2] > 0.2 and abs(rot) < 0.2


def test_std_over_error_is_the_time_averaged_position_std_over_the_mean_error():
    std = np.array([[0.3, 0.4, 9.0], [0.6, 0.8, 9.0]])  # position std 0.5 and 1 (heading ignored)
    assert std_over_error(std, np.array([1.0, 2.0])) == pytest.approx(0.75 / 1.5)
    assert std_over_error(std, np.array([0.25, 0.25])) == pytest.approx(3.0)  # underconfident
    assert std_over_error(std, np.zeros(2)) == pytest.approx(0.75 / 1e-12)  # no error: no NaN


def test_a_calibrated_gaussian_reads_1_13_and_covers_0_865():
    """Errors drawn from the posterior itself (isotropic, per-axis std 0.01): the position std
    (the hypot of the per-axis stds) over the mean distance is sqrt(2) / sqrt(pi / 2), not 1,
    and the 2-sigma ellipse holds 1 - exp(-2) of the steps."""
    rng = np.random.default_rng(0)
    std = np.full((20_000, 3), 0.01)
    true = np.zeros((20_000, 3))
    est = true + rng.normal(0.0, 0.01, true.shape)
    err = localisation_error(est, true)
    assert std_over_error(std, err) == pytest.approx(math.sqrt(4 / math.pi), abs=0.01)
    assert coverage(std, est, true) == pytest.approx(1 - math.exp(-2), abs=0.01)


def test_calibration_compares_the_spread_with_the_raw_and_the_aligned_error():
    """A trajectory turned about its start has a raw error but no shape error: a spread that
    matches the raw error is calibrated against it and looks underconfident after alignment."""
    c, s = math.cos(0.3), math.sin(0.3)
    turned = SQUARE.copy()
    turned[:, :2] = SQUARE[:, :2] @ np.array([[c, s], [-s, c]])
    turned[:, :2] += [0.01, 0.0]  # a little shape error for the aligned ratio's denominator
    turned[0, :2] = 0.0
    err = localisation_error(turned, SQUARE)
    std = np.repeat(err[:, None], 3, 1) / np.sqrt(2)  # position std = error at every step
    std[:, 2] = 1.0
    r = calibration(std, turned, SQUARE)
    assert r["std_over_error"] == pytest.approx(1.0)
    aligned = aligned_error(turned, SQUARE)[0]
    assert r["std_over_aligned_error"] == pytest.approx(err.mean() / aligned.mean())
    assert r["std_over_aligned_error"] > 5


def test_frame_error_is_the_difference_modulo_a_quarter_turn():
    q = math.pi / 2
    assert frame_error(0.1) == pytest.approx(0.1)
    assert frame_error(0.1 + 3 * q) == pytest.approx(0.1)  # the walls look alike every quarter
    assert frame_error(0.3, 0.5) == pytest.approx(-0.2)
    assert frame_error(q - 0.1, 0.0) == pytest.approx(-0.1)
    assert frame_error(q / 2) == pytest.approx(-q / 2)  # half-open: [-pi / 4, pi / 4)
    assert isinstance(frame_error(0.1), float)


def test_ate_statistics_match_numpy():
    rng = np.random.default_rng(0)
    true = np.cumsum(rng.normal(size=(50, 3)), 0)
    est = true + rng.normal(scale=0.2, size=(50, 3))
    e = np.linalg.norm(est[:, :2] - true[:, :2], axis=1)
    r = ate(est, true)
    assert r["rmse"] == pytest.approx(np.sqrt(np.mean(e**2)))
    assert r["mean"] == pytest.approx(e.mean()) and r["max"] == pytest.approx(e.max())
    assert r["std"] == pytest.approx(e.std())
    s = summary(est, true)
    assert s["final_error"] == pytest.approx(e[-1]) and s["mean_error"] == pytest.approx(e.mean())
    d = distance_travelled(true)[-1]
    assert s["distance_travelled"] == pytest.approx(d)
    assert s["final_relative_error"] == pytest.approx(e[-1] / d)
    assert s["ate_unaligned"] == pytest.approx(r)


def test_odometry_poses_rotate_forward_matches_simulator():
    tr = simulate_traversal("simple-small", steps=30, seed=2, noise=0)
    odo = odometry_poses(tr)
    np.testing.assert_allclose(odo, integrate_controls(tr.poses[0], tr.controls), atol=1e-12)
    np.testing.assert_allclose(odo[:, :2], tr.poses[:, :2], atol=1e-9)  # noiseless driving


def test_odometry_poses_odometry_delta():
    # robot-frame steps: forward 1 then turn left 90 degrees, four times: back to the start
    u = np.tile([1.0, 0.0, math.pi / 2], (4, 1))
    tr = Traversal(
        observations=np.ones((5, 2)),
        controls=u,
        walls=np.zeros((0, 4)),
        beam_angles=np.array([0.0, math.pi]),
        max_range=5.0,
        poses=np.zeros((5, 3)),
        metadata={"control_model": "odometry_delta"},
    )
    odo = odometry_poses(tr)
    np.testing.assert_allclose(odo[:, :2], [[0, 0], [1, 0], [1, 1], [0, 1], [0, 0]], atol=1e-12)
    np.testing.assert_allclose(np.cos(odo[:, 2]), [1, 0, -1, 0, 1], atol=1e-12)
    # a log's raw odometry starts where its odometry did; SLAM's frame starts at start_pose
    tr.metadata["odometry_origin"] = [5.0, 5.0, math.pi / 2]
    tr.poses = np.tile([1.0, 2.0, 0.0], (5, 1))
    np.testing.assert_allclose(odometry_poses(tr)[1], [5, 6, -math.pi], atol=1e-12)
    np.testing.assert_allclose(tr.start_pose, [1, 2, 0])
    np.testing.assert_allclose(odometry_poses(tr, tr.start_pose)[1], [2, 2, math.pi / 2])


def test_tum_export_roundtrips_through_evo(tmp_path):
    from evo.tools import file_interface

    path = tmp_path / "traj.tum"
    write_trajectory_tum(path, SQUARE, stamps=np.arange(4) * 0.5)
    traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_allclose(traj.timestamps, [0, 0.5, 1, 1.5])
    np.testing.assert_allclose(traj.positions_xyz[:, :2], SQUARE[:, :2], atol=1e-9)
    q = traj.orientations_quat_wxyz  # yaw-only rotations
    yaw = 2 * np.arctan2(q[:, 3], q[:, 0])
    np.testing.assert_allclose(np.cos(yaw - SQUARE[:, 2]), 1, atol=1e-9)


def test_ate_aligned_and_unaligned():
    """``summary`` reports the ATE as it is (``ate_unaligned``) and after the rigid SE(2)
    alignment (``ate_aligned``, as ``evo_ape -a``, equal to evo's own alignment), the latter
    also for a straight-line path, where evo's 3-D alignment has no unique rotation."""
    rng = np.random.default_rng(1)
    true = np.column_stack([np.cumsum(rng.normal(size=(40, 2)), 0), rng.normal(size=40)])
    c, s = math.cos(0.4), math.sin(0.4)
    est = true.copy()
    est[:, :2] = true[:, :2] @ np.array([[c, s], [-s, c]]) + [3.0, -2.0]
    est[:, :2] += rng.normal(scale=0.01, size=(40, 2))
    out = summary(est, true)
    e = localisation_error(est, true)
    assert out["ate_unaligned"]["rmse"] == pytest.approx(np.sqrt(np.mean(e**2)))
    assert out["ate_aligned"]["rmse"] < 0.02 < 1 < out["ate_unaligned"]["rmse"]
    evo_aligned = aligned_error(est, true)[0]
    assert out["ate_aligned"]["rmse"] == pytest.approx(np.sqrt(np.mean(evo_aligned**2)))
    line = np.column_stack([np.linspace(0, 5, 20), np.zeros(20), np.zeros(20)])
    shifted = line + [1.0, 2.0, 0.0]
    straight = summary(shifted, line)
    assert straight["ate_aligned"]["rmse"] == pytest.approx(0, abs=1e-9)
    assert straight["ate_unaligned"]["rmse"] == pytest.approx(math.sqrt(5))
