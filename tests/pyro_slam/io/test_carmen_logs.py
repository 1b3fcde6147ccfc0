"""The two shipped real logs parse into sane traversals."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from io_helpers import raw_flaser_fields

from pyro_slam.geometry import wrap_angle
from pyro_slam.io import odometry_poses, read_carmen, relation_error, relations_from_reference
from pyro_slam.io.carmen import flaser_angles
from pyro_slam.io.common import compose, relative
from pyro_slam.metrics import consistency_scans, log_scan_consistency


@pytest.fixture(scope="module")
def mit(mit_path):
    return read_carmen(mit_path)


@pytest.fixture(scope="module")
def intel(intel_path):
    return read_carmen(intel_path)


def assert_all_finite(tr):
    for name in ("observations", "controls", "beam_angles", "poses", "timestamps"):
        value = getattr(tr, name)
        assert value is None or np.isfinite(value).all(), name
    assert np.isfinite(tr.max_range)


def assert_close_poses(a, b, tol):
    assert np.abs(a[:, :2] - b[:, :2]).max() < tol
    assert np.abs(wrap_angle(a[:, 2] - b[:, 2])).max() < tol


def test_mit_counts_masks_and_odometry(mit, mit_path):
    ranges, tail = raw_flaser_fields(mit_path)
    assert mit.observations.shape == (1988, 361) and mit.controls.shape == (1987, 3)
    assert mit.metadata["counts"] == {"FLASER": 1988} and mit.metadata["ignored"] == {"#": 3}
    np.testing.assert_allclose(mit.beam_angles, np.radians(np.linspace(-90, 90, 361)))
    assert mit.max_range == pytest.approx(81.91)
    assert_all_finite(mit)
    np.testing.assert_array_equal(mit.obs_mask, ranges < 81.91)
    assert (mit.observations[~mit.obs_mask] == mit.max_range).all()
    np.testing.assert_array_equal(mit.observations[mit.obs_mask], ranges[ranges < 81.91])
    # raw odometry: x y theta == odom fields in this log, so there is no reference pose
    assert mit.poses is None and mit.metadata["odometry_source"] == "FLASER odometry fields"
    assert_close_poses(odometry_poses(mit), tail[:, 3:6], 1e-6)
    np.testing.assert_array_equal(mit.timestamps, tail[:, 6])
    assert mit.metadata["control_model"] == "odometry_delta"


def test_intel_beams_follow_carmens_geometry(intel):
    # 180 readings: CARMEN's 1 deg beams from -90 deg, the last of 181 dropped
    np.testing.assert_allclose(np.degrees(intel.beam_angles), np.arange(-90.0, 90.0), atol=1e-9)
    # and they are the beams GMapping matched: its poses fit the scans better with them than
    # with the 180 readings spread evenly over 180 deg
    even = replace(intel, beam_angles=np.linspace(-np.pi / 2, np.pi / 2, 180))

    def consistency(tr):
        return log_scan_consistency(tr, tr.poses, consistency_scans(tr))["mean"]

    assert consistency(intel) < consistency(even) - 0.001


@pytest.mark.parametrize(
    "n, first, step, last",
    [(181, -90, 1, 90), (361, -90, 0.5, 90), (360, -90, 0.5, 89.5), (401, -50, 0.25, 50)],
)
def test_flaser_angles_of_carmens_beam_counts(n, first, step, last):
    a = np.degrees(flaser_angles(n))
    assert a[0] == pytest.approx(first) and a[-1] == pytest.approx(last)
    np.testing.assert_allclose(np.diff(a), step)


def test_flaser_angles_spread_over_a_logged_field_of_view():
    a = np.degrees(flaser_angles(180, 100.0))
    assert a[0] == pytest.approx(-50) and a[-1] == pytest.approx(50)
    np.testing.assert_allclose(np.degrees(flaser_angles(7)), np.linspace(-90, 90, 7))


def test_mit_beam_stride_and_max_range_argument(mit_path):
    tr = read_carmen(mit_path, beam_stride=2, max_range=30.0)
    assert tr.observations.shape == (1988, 181)
    np.testing.assert_allclose(np.diff(np.degrees(tr.beam_angles)), 1.0)
    assert tr.max_range == 30.0 and tr.observations.max() == 30.0
    assert tr.metadata["sensor"]["max_range_source"] == "argument"


def test_intel_reference_poses_and_reanchored_odometry(intel, intel_path):
    ranges, tail = raw_flaser_fields(intel_path)
    assert intel.observations.shape == (910, 180)
    assert intel.metadata["counts"] == {"FLASER": 910, "ODOM": 14541}
    assert intel.metadata["ignored"] == {"NEFF": 910}
    assert intel.max_range == pytest.approx(81.83)
    assert_all_finite(intel)
    np.testing.assert_array_equal(intel.obs_mask, ranges < 81.83)
    # FLASER poses are GMapping's corrected poses: kept as the reference
    assert_close_poses(intel.poses, tail[:, :3], 1e-9)
    assert intel.metadata["odometry_anchors"] == 910
    assert intel.metadata["timestamps_clamped"] == 4  # ipc_timestamp steps back 4 times
    assert (np.diff(intel.timestamps) >= 0).all()
    # odometry: from the corrected pose at t, the control reaches the ODOM line logged at the
    # time of scan t+1 (the one right before that FLASER line)
    before = odom_before_each_flaser(intel_path)
    assert_close_poses(compose(intel.poses[:-1], intel.controls), before[1:], 1e-6)
    assert_close_poses(odometry_poses(intel), integrate_ref(intel), 1e-6)


def odom_before_each_flaser(path):
    out, last = [], None
    for line in path.read_text().splitlines():
        tok = line.split()
        if tok[0] == "ODOM":
            last = [float(v) for v in tok[1:4]]
        elif tok[0] == "FLASER":
            out.append(last)
    return np.array(out)


def integrate_ref(tr):
    poses = [tr.poses[0]]
    for u in tr.controls:
        poses.append(compose(poses[-1], u))
    return np.array(poses)


def test_intel_prefer_flaser_fields(intel_path):
    tr = read_carmen(intel_path, prefer="flaser")
    assert tr.poses is None  # the FLASER odometry fields equal the logged (corrected) poses
    _, tail = raw_flaser_fields(intel_path)
    np.testing.assert_allclose(tr.controls, relative(tail[:-1, 3:6], tail[1:, 3:6]), atol=1e-12)


def test_intel_relation_metric_on_reference_and_odometry(intel):
    rel = relations_from_reference(intel.timestamps, intel.poses, n_random=200, max_steps=20)
    exact = relation_error(intel.timestamps, intel.poses, rel)
    assert exact["trans_mean"] < 1e-9 and exact["rot_mean_deg"] < 1e-9
    assert exact["n_skipped"] == 0 and exact["n_used"] == len(rel)
    odo = relation_error(intel.timestamps, odometry_poses(intel), rel)
    assert 0.01 < odo["trans_mean"] < 5.0  # raw odometry drifts, but not absurdly
