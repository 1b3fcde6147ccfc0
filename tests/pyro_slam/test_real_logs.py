"""DVBF-LM on metric real-log traversals: beam subsampling, range clipping, odometry noise, the
``real`` preset, scan consistency, and ``pyro-slam slam LOG.clf`` end to end (synthetic room)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from synthetic_logs import box_ranges, room_log

from pyro_slam import cli, metrics
from pyro_slam.io import odometry_poses, read_any, read_map, write_carmen
from pyro_slam.io.common import relative
from pyro_slam.slam import (
    SLAM,
    ConfigError,
    SLAMConfig,
    build_model,
    from_dict,
    prepare_traversal,
    presets,
    with_overrides,
)
from pyro_slam.slam.heading import odometry_heading_noise
from pyro_slam.slam.presets import REAL_LOG, odometry_sigma

NOISE = (REAL_LOG.odometry_noise, REAL_LOG.heading_noise)  # the real-log noise fractions

# a light filter and SVI batch for the short logs here
SMALL = {"filter": {"particles": 16}, "training": {"particles": 4, "chunk_length": 4, "chunks": 2}}


def test_subsample_beams_keeps_mask_and_angles():
    tr, _ = room_log(T=4)
    sub = tr.subsample_beams(8)
    assert sub.num_beams == 46
    np.testing.assert_array_equal(sub.obs_mask, tr.obs_mask[:, ::8])
    np.testing.assert_array_equal(sub.beam_angles, tr.beam_angles[::8])
    assert sub.metadata["sensor"]["beam_stride"] == 8
    assert tr.subsample_beams(1) is tr
    with pytest.raises(ValueError):
        tr.subsample_beams(0)


def test_clip_ranges_clips_valid_readings_only():
    tr, _ = room_log(T=4)
    clipped = tr.clip_ranges(3.0)
    valid = tr.obs_mask
    assert clipped.observations[valid].max() <= 3.0
    np.testing.assert_array_equal(clipped.observations[~valid], tr.observations[~valid])
    near = valid & (tr.observations < 3.0)
    np.testing.assert_array_equal(clipped.observations[near], tr.observations[near])
    assert tr.valid_ranges().max() < 81.91


def test_odometry_sigma_scales_with_motion():
    u = np.tile([0.2, 0.0, 0.1], (50, 1))
    sx, sy, sh = odometry_sigma(u, trans_frac=0.1, rot_frac=0.1, floor=1e-4)
    assert sx == sy == pytest.approx(0.02)
    assert sh == pytest.approx(0.1 * (0.1 + 0.2))
    assert odometry_sigma(np.zeros((5, 3)), floor=0.01) == (0.01, 0.01, 0.01)


def drifting_room_log(drift: float, T: int = 1000, seed: int = 0, bias: float = 0.0):
    """The room log, turning back and forth, with a heading random walk of step std ``drift``
    (rad) and a heading bias of ``bias`` rad per step in its odometry."""
    tr, poses = room_log(T=T)
    poses[:, 2] = 0.4 * np.sin(np.arange(T) / 15.0)
    obs = np.stack([box_ranges(p, tr.beam_angles) for p in poses])
    u = relative(poses[:-1], poses[1:])
    u[:, 2] += np.random.default_rng(seed).normal(size=len(u)) * drift + bias
    return replace(tr, observations=obs, obs_mask=None, controls=u)


@pytest.mark.parametrize("drift", [0.02, 0.04])
def test_real_preset_reads_the_odometrys_heading_noise_from_the_walls(drift):
    """The scans' wall directions show odometry's heading drift: the real preset's heading
    sigma_T is that drift (not a share of the motion), x/y keep the share of the step."""
    tr = drifting_room_log(drift)
    cfg = presets.get("real").for_traversal(tr)
    assert cfg.transition.sigma[2] == pytest.approx(drift, rel=0.25)
    assert cfg.transition.sigma[:2] == pytest.approx(odometry_sigma(tr.controls, *NOISE)[:2])
    assert odometry_heading_noise(tr, cfg) == pytest.approx(cfg.transition.sigma[2])
    # without the heading factor there are no wall directions to read it from
    no_walls = replace(cfg, heading=None)
    assert odometry_heading_noise(tr, no_walls) is None
    assert presets.adapt_real_log(tr, no_walls).transition.sigma == pytest.approx(
        odometry_sigma(tr.controls, *NOISE)
    )


def test_a_heading_bias_in_the_odometry_widens_the_transition():
    """The transition's noise has mean 0: odometry that turns 0.01 rad too far at every step
    needs a heading std that covers 0.08 rad over 8 steps."""
    tr = drifting_room_log(0.0, bias=0.01)
    assert presets.get("real").for_traversal(tr).transition.sigma[2] > 0.02


def test_exact_odometry_shows_no_heading_drift():
    tr = drifting_room_log(0.0)
    # a slope of exactly 0 (no drift at all) reads as None, rounding may leave a tiny one
    assert (odometry_heading_noise(tr, presets.get("real").config) or 0.0) < 1e-4
    assert presets.get("real").for_traversal(tr).transition.sigma[2] == presets.ODOMETRY_FLOOR


def test_real_preset_adapts_to_the_log_and_sizes_the_model():
    tr, poses = room_log()
    cfg = presets.get("real").for_traversal(tr)
    assert cfg.beam_stride == 8 and cfg.emission.resolution == 0.05
    assert cfg.range_clip == pytest.approx(np.percentile(tr.valid_ranges(), 99), abs=0.01)
    assert cfg.transition.sigma == pytest.approx(odometry_sigma(tr.controls, *NOISE))
    assert with_overrides(cfg, {"beam_stride": 4}).beam_stride == 4  # overrides win
    assert presets.adapt_real_log(tr, cfg, target_beams=100).beam_stride == 4
    prepared = prepare_traversal(tr, cfg)
    assert prepared.num_beams == 46
    model, _ = build_model(prepared, cfg)
    assert model.emission.max_range == pytest.approx(cfg.range_clip)
    assert model.beam_angles.shape == (46,)
    x0, x1, y0, y1 = model.grid.extent()
    path = odometry_poses(prepared)[:, :2]
    assert x0 == pytest.approx(path[:, 0].min() - cfg.range_clip)
    assert y1 == pytest.approx(path[:, 1].max() + cfg.range_clip)
    assert (x1 - x0) / (model.grid.cells[0] - 1) == pytest.approx(0.05, rel=0.05)
    # the simulator's defaults are unchanged
    assert SLAMConfig().beam_stride == 1 and SLAMConfig().range_clip is None


def test_slam_runs_on_subsampled_metric_log():
    tr, _ = room_log(T=12)
    cfg = with_overrides(presets.get("real").for_traversal(tr), SMALL)
    slam = SLAM(tr, cfg, seed=0)
    assert slam.obs.shape == (12, 46) and slam.mask.shape == (12, 46)
    res = slam.run("online", progress=False)
    assert res["mean"].shape == (12, 3) and np.isfinite(res["mean"]).all()
    # 12 short steps from a known start: SLAM stays near the odometry
    odo = odometry_poses(tr)
    assert np.abs(res["mean"][:, :2] - odo[:, :2]).max() < 1.0


def test_real_preset_corrects_a_biased_odometry_in_a_room():
    """The ``real`` preset (the end-point emission) on a room log whose odometry overstates
    each step by 8 % and turns 0.01 rad too far per step: odometry ends 0.73 m off, SLAM within
    0.15 m at every step (measured 0.10; with the transition's x/y std at 5 % of the step
    instead of 8 % it ends 0.165 m off), its final std of the order of its error."""
    tr, poses = room_log(T=24)
    u = tr.controls.copy()
    u[:, 0] *= 1.08
    u[:, 2] += 0.01
    tr = replace(tr, controls=u)
    cfg = with_overrides(presets.get("real").for_traversal(tr), {"filter": {"particles": 32}})
    res = SLAM(tr, cfg, seed=0).run("online", progress=False)

    def error(xy):  # [T] from the true path, both from their first pose (heading 0 there)
        return np.linalg.norm(xy - xy[:1] - (poses[:, :2] - poses[:1, :2]), axis=1)

    assert error(odometry_poses(tr)[:, :2]).max() > 0.7
    err = error(res["mean"][:, :2])
    assert err.max() < 0.15
    std = float(np.linalg.norm(res["std"][-1, :2]))
    assert err[-1] < 3 * std and std < 0.15


def test_scan_consistency_prefers_the_true_poses():
    tr, poses = room_log(T=40)
    tr.poses = poses
    good = metrics.scan_consistency(tr, poses, exclude=5)
    bent = poses.copy()
    bent[20:, 2] += 0.1  # a heading error half way: later scans no longer line up
    bad = metrics.scan_consistency(tr, bent, exclude=5)
    assert good["mean"] < 0.05 < bad["mean"]
    assert good["points"] == int(tr.obs_mask.sum())
    xy, t = metrics.scan_points(tr, poses, max_range=4.0)
    assert len(xy) == len(t) and np.all(np.linalg.norm(xy - poses[t, :2], axis=1) < 4.0)


def test_cli_slam_on_carmen_log(tmp_path, capsys):
    tr, poses = room_log(T=24)  # scans 20 steps apart score each other
    log = write_carmen(tr, tmp_path / "room.clf")
    out = tmp_path / "run"
    rc = cli.main(
        [
            "slam",
            str(log),
            "--out",
            str(out),
            "--config",
            json.dumps({"filter": SMALL["filter"]}),  # (the real-log preset takes no SVI steps)
            "--odometry-noise",
            "0.2",
        ]
    )
    assert rc == 0
    for name in ("metrics.json", "map.png", "slam.png", "trajectory_slam.tum", "posterior.npz"):
        assert (out / name).is_file(), name
    assert not (out / "trajectory_true.tum").exists()  # the log has no reference poses
    report = json.loads((out / "metrics.json").read_text())
    config = report["config"]
    assert report["preset"] == "real" and config["beam_stride"] == 8
    assert config["emission"]["resolution"] == 0.05 and config["filter"]["particles"] == 16
    sigma = odometry_sigma(tr.controls, 0.2, NOISE[1])  # --odometry-noise sets x and y
    np.testing.assert_allclose(config["transition"]["sigma"], sigma, rtol=1e-4)
    assert report["scan_consistency"]["slam"]["mean"] >= 0
    assert "scan consistency" in capsys.readouterr().out
    # the exported map spans the room the beams saw (10 x 6 m plus its margin), not the
    # sensor's 81.91 m "no return" range around the path
    grid = read_map(out / "map.yaml")
    h, w = grid.image.shape
    assert w * grid.resolution <= 10.5 and h * grid.resolution <= 6.5


def test_scan_points_leave_out_clipped_readings():
    tr, poses = room_log(T=6)
    clipped = tr.clip_ranges(4.0)
    xy, t = metrics.scan_points(clipped, poses)
    n_short = int((tr.obs_mask & (tr.observations < 4.0)).sum())
    assert len(xy) == n_short  # readings clipped to 4 m are not wall points


def test_slam_from_python_adapts_a_preset_to_the_log_as_the_cli_does(tmp_path):
    """``SLAM(tr, "real")`` and ``SLAM(tr, presets.get("real"))`` run with the configuration
    ``pyro-slam slam LOG`` chooses; the preset's unadapted ``.config`` on a log warns."""
    tr, _ = room_log(T=6)
    log = write_carmen(tr, tmp_path / "room.clf")
    out = tmp_path / "run"
    assert cli.main(["slam", str(log), "--out", str(out)]) == 0
    cli_config = from_dict(json.loads((out / "metrics.json").read_text())["config"])
    tr = read_any(log)
    assert SLAM(tr, "real").cfg == cli_config
    assert SLAM(tr, presets.get("real")).cfg == cli_config
    assert SLAM(tr).cfg == cli_config  # the default for a real log
    with pytest.warns(UserWarning, match="not adapted to this log"):
        SLAM(tr, presets.get("real").config)
    with pytest.raises(ValueError, match="unknown preset 'rael'"):
        SLAM(tr, "rael")
    with pytest.raises(ConfigError, match="preset name"):
        SLAM(tr, {"filter": {"particles": 8}})
