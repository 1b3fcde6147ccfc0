"""Hand-made CARMEN logs: strict errors, lenient skipping, fuzzing, odometry pairing, writer."""

from __future__ import annotations

import gzip
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from io_helpers import flaser, odom_line, synthetic_traversal

from pyro_slam.geometry import odometry_delta
from pyro_slam.io import ParseError, odometry_poses, parse_carmen, read_carmen, write_carmen
from pyro_slam.io.carmen import carmen_to_traversal, flaser_angles
from pyro_slam.io.common import compose

GOOD = [
    "# a comment",
    "PARAM robot_front_laser_max 10.0",
    flaser([1.0, 2.0, 3.0], pose=(0.0, 0.0, 0.0), t=1.0),
    "",
    flaser([1.5, 10.0, 2.5], pose=(1.0, 0.0, 0.5), t=2.0),
    "NEFF 12.0",
    flaser([2.0, 2.0, 0.0], pose=(2.0, 1.0, 1.0), t=3.0),
]


def write(tmp_path, lines, name="log.clf"):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_small_log_fields(tmp_path):
    tr = read_carmen(write(tmp_path, GOOD))
    assert tr.observations.shape == (3, 3) and tr.max_range == 10.0
    np.testing.assert_allclose(tr.beam_angles, [-math.pi / 2, 0, math.pi / 2])
    np.testing.assert_array_equal(tr.obs_mask, [[1, 1, 1], [1, 0, 1], [1, 1, 0]])
    np.testing.assert_array_equal(tr.observations[1:, :], [[1.5, 10, 2.5], [2, 2, 10]])
    # the sensor's PARAM is applied, not ignored
    assert tr.metadata["ignored"] == {"#": 1, "blank": 1, "NEFF": 1}
    assert tr.metadata["counts"]["PARAM"] == 1
    assert tr.metadata["sensor"]["max_range_source"] == "PARAM"
    np.testing.assert_array_equal(tr.timestamps, [1, 2, 3])
    assert tr.poses is None


def test_controls_match_geometry_odometry_delta():
    """The controls follow pyro_slam.geometry.odometry_delta: z_{t+1} = delta(z_t, u_t)."""
    poses = [(0.0, 0.0, 3.0), (0.5, 0.2, -3.0), (0.1, 1.0, 1.2), (-2.0, 0.3, -1.5)]
    log = parse_carmen([flaser([1.0], pose=p, t=i) for i, p in enumerate(poses)])
    tr = carmen_to_traversal(log, max_range=5.0)
    z = torch.tensor(poses[:-1], dtype=torch.float64)
    nxt = odometry_delta(z, torch.tensor(tr.controls)).numpy()
    np.testing.assert_allclose(nxt, poses[1:], atol=1e-12)
    np.testing.assert_allclose(odometry_poses(tr), poses, atol=1e-12)


def test_invalid_readings_are_masked_not_nan(tmp_path):
    lines = [flaser(["nan", "inf", "-1", "0", "3.0", "-inf"], t=0), flaser([1] * 6, t=1)]
    tr = read_carmen(write(tmp_path, lines), max_range=8.0)
    assert np.isfinite(tr.observations).all()
    np.testing.assert_array_equal(tr.obs_mask[0], [0, 0, 0, 0, 1, 0])
    np.testing.assert_array_equal(tr.observations[0], [8, 8, 8, 8, 3, 8])


BROKEN = [  # (line, reason fragment)
    ("FLASER 3 1 2 3 0 0 0 0 0 0 5.0 host", "wrong number of fields"),
    ("FLASER 4 1 2 3 0 0 0 0 0 0 5.0 host 5.0", "num_readings=4 needs 15"),
    ("FLASER 3 1 two 3 0 0 0 0 0 0 5.0 host 5.0", "non-numeric value 'two'"),
    ("FLASER x 1 2 3 0 0 0 0 0 0 5.0 host 5.0", "num_readings must be a non-negative integer"),
    ("FLASER -3 1 2 3 0 0 0 0 0 0 5.0 host 5.0", "num_readings must be a non-negative integer"),
    ("FLASER 3 1 2 3 nan 0 0 0 0 0 5.0 host 5.0", "non-finite value in poses"),
    ("FLASER 3 1 2 3 0 0 0 0 0 0 1e999 host 5.0", "non-finite value in ipc_timestamp"),
    ("FLASER 2 1 2 0 0 0 0 0 0 5.0 host 5.0", "does not match the first FLASER's 3"),
    ("ODOM 0 0 0 0 0 0 5.0 host", "wrong number of fields for ODOM"),
    ("ODOM 0 0 zero 0 0 0 5.0 host 5.0", "non-numeric value 'zero'"),
    ("ROBOTLASER1 0 -1.57 3.14 0.01 50 0.01 0 2 1 2", "wrong number of fields"),
    ("PARAM lonely", "PARAM needs a name and a value"),
]


@pytest.mark.parametrize("bad, reason", BROKEN)
def test_strict_mode_names_file_line_and_reason(tmp_path, bad, reason):
    path = write(tmp_path, [*GOOD[:3], bad, *GOOD[3:]])
    with pytest.raises(ParseError) as err:
        read_carmen(path)
    assert err.value.lineno == 4 and reason in err.value.reason
    assert str(err.value).startswith(f"{path}:4: ")
    assert isinstance(err.value, ValueError)


def test_lenient_mode_skips_and_counts(tmp_path):
    bad = [b for b, _ in BROKEN]
    lines = [GOOD[2], *bad[:6], GOOD[4], *bad[6:], GOOD[6]]
    tr = read_carmen(write(tmp_path, lines), lenient=True)
    assert tr.num_steps == 3
    assert tr.metadata["skipped_lines"] == len(BROKEN)
    reasons = tr.metadata["skip_reasons"]
    assert len(reasons) == 5 and reasons[0].endswith(
        ":2: " + "wrong number of fields: "
        "num_readings=3 needs 14 fields (n readings "
        "+ 6 pose + 3 time/host), got 13"
    )


@pytest.mark.parametrize("lines", [[], ["# only a comment", "", "ODOM 0 0 0 0 0 0 1 h 1"]])
def test_log_without_scans_is_an_error_naming_the_file(tmp_path, lines):
    path = write(tmp_path, lines, "empty.clf")
    for lenient in (False, True):
        with pytest.raises(ParseError, match="empty.clf: no scans"):
            read_carmen(path, lenient=lenient)


def test_gzip_and_undecodable_bytes(tmp_path):
    path = tmp_path / "log.clf.gz"
    with gzip.open(path, "wt") as f:
        f.write("\n".join(GOOD) + "\n")
    assert read_carmen(path).num_steps == 3
    raw = tmp_path / "bytes.clf"
    raw.write_bytes(("\n".join(GOOD[2:]) + "\nFLASER 3 1 \xff\xfe 3\n").encode("latin-1"))
    with pytest.raises(ParseError, match="bytes.clf:6: "):
        read_carmen(raw)
    assert read_carmen(raw, lenient=True).metadata["skipped_lines"] == 1
    corrupt = tmp_path / "corrupt.clf.gz"
    corrupt.write_bytes(path.read_bytes()[:-12])
    with pytest.raises(ParseError, match="corrupt.clf.gz: cannot read"):
        read_carmen(corrupt)


def test_param_field_of_view(tmp_path):
    tr = read_carmen(write(tmp_path, ["PARAM laser_front_laser_fov 90", *GOOD[2:]]))
    np.testing.assert_allclose(np.degrees(tr.beam_angles), [-45, 0, 45])


def test_odom_lines_interpolated_to_scan_times():
    """ODOM at 10 Hz, scans in between: odometry is interpolated, controls chain them."""

    def truth(t):  # a smooth arc
        return np.array([np.sin(t), 1 - np.cos(t), t])

    odom = [odom_line(truth(t), t) for t in np.arange(0, 2.01, 0.1)]
    scans = [(i * 4 + 1, flaser([1.0], pose=(9, 9, 0), t=0.05 + 0.4 * i)) for i in range(5)]
    lines = list(odom)
    for pos, line in reversed(scans):
        lines.insert(pos, line)
    tr = carmen_to_traversal(parse_carmen(lines), max_range=5.0)
    at = np.array([0.05 + 0.4 * i for i in range(5)])
    lo, hi = np.stack([truth(t - 0.05) for t in at]), np.stack([truth(t + 0.05) for t in at])
    expected = (lo + hi) / 2
    np.testing.assert_allclose(odometry_poses(tr), expected, atol=1e-9)
    assert tr.metadata["odometry_source"].startswith("ODOM lines (interp")
    assert tr.poses is not None  # logged (9, 9, 0) differs from odometry -> kept as reference
    near = carmen_to_traversal(parse_carmen(lines), max_range=5.0, pairing="nearest")
    assert near.metadata["odometry_max_time_gap"] == pytest.approx(0.05)
    flaser_odom = carmen_to_traversal(parse_carmen(lines), max_range=5.0, prefer="flaser")
    assert np.abs(flaser_odom.controls).max() == 0 and flaser_odom.poses is None


def test_gmapping_style_reanchored_odometry():
    """ODOM right after a scan, repeating its (corrected) pose with a bogus time, restarts the
    odometry chain: the control starts at the corrected pose."""
    corrected = [(0.0, 0.0, 0.0), (1.1, 0.1, 0.05), (2.0, 0.3, 0.1)]
    lines = []
    for i, pose in enumerate(corrected):
        if i:  # odometry since the last anchor: 1 m forward from the previous corrected pose
            prev = np.array(corrected[i - 1])
            lines.append(odom_line(compose(prev, np.array([0.5, 0, 0])), i + 0.5))
            lines.append(odom_line(compose(prev, np.array([1.0, 0, 0])), i + 1.0))
        lines += [flaser([1.0], pose=pose, t=i + 1.0), odom_line(pose, 0), "NEFF 3"]
    tr = carmen_to_traversal(parse_carmen(lines), max_range=5.0)
    np.testing.assert_allclose(tr.controls, [[1, 0, 0], [1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(tr.poses, corrected)
    assert tr.metadata["odometry_anchors"] == 3


def test_robotlaser1(tmp_path):
    def line(r, robot, t):
        n, rem = len(r), [0.5] * len(r)
        laser = (robot[0] + 0.1, robot[1], robot[2] + 0.2)
        fields = [0, -1.0, 2.0, 0.5, 4.0, 0.01, 0, n, *r, n, *rem, *laser, *robot, 0, 0, 0, 0, 0]
        return "ROBOTLASER1 " + " ".join(map(str, fields)) + f" {t} host {t}"

    path = write(tmp_path, [line([1, 2, 3, 4, 5], (0, 0, 0), 1.0), line([1] * 5, (1, 0, 0), 2.0)])
    tr = read_carmen(path)
    np.testing.assert_allclose(tr.beam_angles, np.array([-1.0, -0.5, 0, 0.5, 1.0]) + 0.2)
    assert tr.max_range == 4.0 and tr.metadata["sensor"]["max_range_source"].startswith("ROBOT")
    np.testing.assert_array_equal(tr.obs_mask[0], [1, 1, 1, 0, 0])
    np.testing.assert_allclose(tr.controls, [[1, 0, 0]])


def test_write_read_round_trip(tmp_path):
    tr = synthetic_traversal()
    back = read_carmen(write_carmen(tr, tmp_path / "rt.clf"))
    np.testing.assert_array_equal(back.observations, tr.observations)
    np.testing.assert_array_equal(back.obs_mask, tr.obs_mask)
    np.testing.assert_allclose(back.beam_angles, tr.beam_angles, atol=1e-12)
    np.testing.assert_allclose(back.controls, tr.controls, atol=1e-12)
    np.testing.assert_allclose(back.poses, tr.poses, atol=1e-12)
    np.testing.assert_array_equal(back.timestamps, tr.timestamps)
    np.testing.assert_allclose(odometry_poses(back), odometry_poses(tr), atol=1e-12)
    assert back.max_range == tr.max_range


@pytest.mark.parametrize("n", [180, 361])
def test_round_trip_keeps_carmens_beam_geometry(tmp_path, n):
    # CARMEN's 180 beams (-90 to +89 deg) are not symmetric: written without a field of view
    tr = synthetic_traversal()
    B = tr.observations.shape[1]
    tr = replace(
        tr,
        observations=np.resize(tr.observations, (tr.num_steps, n)),
        obs_mask=np.resize(tr.obs_mask, (tr.num_steps, n)),
        beam_angles=flaser_angles(n),
    )
    path = write_carmen(tr, tmp_path / "rt.clf")
    assert ("laser_front_laser_fov" in path.read_text()) == (n == 361) and B != n
    np.testing.assert_allclose(read_carmen(path).beam_angles, flaser_angles(n), atol=1e-12)
    with pytest.raises(ValueError, match="evenly spaced"):
        write_carmen(replace(tr, beam_angles=flaser_angles(n) + 0.01), tmp_path / "no.clf")


def test_round_trip_of_a_real_log_slice(tmp_path, mit_path):
    tr = read_carmen(mit_path).slice(0, 40)
    back = read_carmen(write_carmen(tr, tmp_path / "mit40.clf"))
    np.testing.assert_array_equal(back.observations, tr.observations)
    np.testing.assert_array_equal(back.obs_mask, tr.obs_mask)
    np.testing.assert_allclose(back.controls, tr.controls, atol=1e-9)
    np.testing.assert_allclose(back.beam_angles, tr.beam_angles, atol=1e-12)


def test_writer_rejects_asymmetric_beams(tmp_path):
    tr = synthetic_traversal()
    tr.beam_angles = np.linspace(0, 1, tr.num_beams)
    with pytest.raises(ValueError, match="symmetric"):
        write_carmen(tr, tmp_path / "x.clf")


# --- fuzzing ------------------------------------------------------------------------------------

NASTY = [
    "nan",
    "-inf",
    "inf",
    "1e999",
    "-1e999",
    "1e308",
    "9" * 400,
    "1_0",
    "٣",
    "１２",
    "",
    "x",
    "-",
    ".",
    "e5",
    "0x10",
    "\x00",
    "🤖",
    "FLASER",
    "ODOM",
    "-0",
    "+.5e-3",
    "1e308",
    "-1e308",
    "1e15",
    "-1e15",
    "1e16",
    "2147483648",
    "0",
    "1",
]
TEMPLATES = [
    flaser([1.0, 2.0, 3.0], pose=(0.5, 0.5, 0.1), t=2.5),
    odom_line((1, 2, 3), 2.6),
    "ROBOTLASER1 0 -1.57 3.14 1.57 50 0.01 0 3 1 2 3 0 0 0 0 0 0 0 0 0 0 0 0 3 h 3",
    "PARAM laser_front_laser_fov 90",
]


@st.composite
def fuzzed_line(draw):
    if draw(st.booleans()):
        return draw(st.text(max_size=60))
    tokens = draw(st.sampled_from(TEMPLATES)).split()
    for _ in range(draw(st.integers(0, 3))):
        op = draw(st.sampled_from(["replace", "insert", "truncate"]))
        i = draw(st.integers(0, max(len(tokens) - 1, 0)))
        tok = draw(st.one_of(st.sampled_from(NASTY), st.text(max_size=8)))
        if op == "replace" and tokens:
            tokens[i] = tok
        elif op == "insert":
            tokens.insert(i, tok)
        else:
            tokens = tokens[:i]
    return " ".join(tokens)


FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def check_traversal(tr):
    for a in (tr.observations, tr.controls, tr.beam_angles, tr.timestamps):
        assert np.isfinite(a).all()
    assert tr.poses is None or np.isfinite(tr.poses).all()


ROBOT = [TEMPLATES[2], TEMPLATES[2].replace(" 3 h 3", " 4 h 4")]
BASES = st.sampled_from([[GOOD[2], GOOD[4]], ROBOT])


@FUZZ
@given(BASES, st.lists(fuzzed_line(), min_size=1, max_size=4))
def test_fuzz_strict_raises_only_parse_error(base, bad):
    lines = [base[0], *bad, base[1]]
    try:
        tr = carmen_to_traversal(parse_carmen(lines))
    except ParseError as e:
        assert str(e).startswith("<lines>")
        return
    check_traversal(tr)


@FUZZ
@given(BASES, st.lists(fuzzed_line(), min_size=1, max_size=4))
def test_fuzz_lenient_never_crashes(base, bad):
    log = parse_carmen([base[0], *bad, base[1]], lenient=True)
    tr = carmen_to_traversal(log)
    check_traversal(tr)
    assert tr.num_steps >= 1 and log.skipped <= len(bad)


def test_reanchored_segment_without_odometry_means_no_motion():
    lines = [
        flaser([1.0], pose=(0, 0, 0), t=1.0),
        odom_line((0, 0, 0), 0),
        odom_line((0.5, 0, 0), 2.0),
        flaser([1.0], pose=(0.4, 0, 0), t=2.0),
        odom_line((0.4, 0, 0), 0),
        flaser([1.0], pose=(0.4, 0, 0), t=3.0),  # no ODOM since the last anchor
    ]
    tr = carmen_to_traversal(parse_carmen(lines), max_range=5.0)
    np.testing.assert_allclose(tr.controls, [[0.5, 0, 0], [0, 0, 0]], atol=1e-12)
    assert tr.metadata["odometry_fallbacks"] == 2  # also scan 0: no ODOM before it
