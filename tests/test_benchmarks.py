"""The benchmark scripts run end to end at toy sizes and print / write what their docs promise."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def run(script: str, *args: str) -> str:
    proc = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / script), *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def test_simulator_benchmark_reports_lidar_steps_per_second():
    out = json.loads(run("simulator.py", "--steps", "200"))
    assert out["steps"] == 200 and out["maze"] == "moderate-medium"
    assert out["steps_per_s"] > 100 and out["camera_frames_per_s_batched"] > 0


def test_filter_speed_benchmark_compares_with_smcfilter_and_reports_flat_memory():
    out = json.loads(run("filter_speed.py", "--particles", "50", "--steps", "20",
                         "--long-steps", "100"))  # fmt: skip
    assert out["particles"] == 50 and out["long_run_steps"] == 100
    for key in ("ours_steps_per_s", "smcfilter_steps_per_s", "ours_bf16_emission_steps_per_s"):
        assert out[key] > 0, key
    assert math.isclose(out["speedup"], out["ours_steps_per_s"] / out["smcfilter_steps_per_s"],
                        rel_tol=0.02)  # fmt: skip
    assert out["peak_rss_mib_at_100"] <= 1.1 * out["peak_rss_mib_at_10"]
    # the emission MLP alone is a ceiling: no filter step that also runs it is faster
    assert out["emission_only_steps_per_s"] > out["ours_steps_per_s"]
    assert math.isclose(out["ceiling_speedup"],
                        out["emission_only_steps_per_s"] / out["smcfilter_steps_per_s"],
                        rel_tol=0.02)  # fmt: skip


def test_slam_accuracy_benchmark_writes_summary_plot_and_resumable_runs(tmp_path):
    args = ("--mazes", "1", "--traversals", "1", "--steps", "40", "--modes", "online",
            "--workers", "1", "--out", str(tmp_path))  # fmt: skip
    run("slam_accuracy.py", *args)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["steps"] == 40 and summary["runs_per_mode"] == 1
    assert 0 <= summary["online"]["final_mean"] < 0.05
    assert 0 <= summary["path_integration"]["final_mean"] < 0.05
    assert (tmp_path / "error_bands.png").stat().st_size > 10_000
    runs = sorted((tmp_path / "runs").glob("*.npz"))
    assert len(runs) == 1
    with np.load(runs[0]) as z:  # the trajectories and the filter's std are exported
        assert all(z[k].shape == (40, 3) for k in ("estimate", "truth", "pi_poses", "std"))
        err = np.hypot(*(z["estimate"][:, :2] - z["truth"][:, :2]).T)
        np.testing.assert_allclose(err, z["slam"], atol=1e-5)
        assert math.isclose(summary["online"]["time_avg_mean"], float(z["slam"].mean()))
        assert (z["std"] >= 0).all()
    assert summary["online"]["std_over_error_median"] > 0
    # diagnostic: the error left after a rigid alignment of each trajectory to the truth
    assert 0 <= summary["online"]["aligned_final_mean"] < 0.05
    assert 0 <= summary["online"]["aligning_rotation_abs_mean"] < 0.1
    stamp = runs[0].stat().st_mtime_ns
    run("slam_accuracy.py", *args)  # finished runs are reused, not recomputed
    assert runs[0].stat().st_mtime_ns == stamp
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    # the diagnostic: the map learned at the true poses; its runs are kept apart
    run("slam_accuracy.py", *args, "--map-poses", "true")
    oracle = json.loads((tmp_path / "summary.json").read_text())
    assert oracle["map_poses"] == "true" and summary["map_poses"] == "filter"
    assert 0 <= oracle["online"]["final_mean"] < 0.05
    assert oracle["online"]["final_mean"] != summary["online"]["final_mean"]
    assert len(list((tmp_path / "runs").glob("online_map-true_*.npz"))) == 1
    # the default seeds each maze's own actuation noise; the shared draw of the earlier
    # figures (--no-per-maze-noise) is another traversal of the same maze, kept apart
    assert summary["per_maze_noise"] and runs[0].name.startswith("online_pn_")
    run("slam_accuracy.py", *args, "--no-per-maze-noise")
    shared = json.loads((tmp_path / "summary.json").read_text())
    assert not shared["per_maze_noise"]
    f = tmp_path / "runs" / "online_m1001_t1_T40.npz"
    assert f.is_file() and runs[0].name == "online_pn_m1001_t1_T40.npz"
    with np.load(f) as a, np.load(runs[0]) as b:
        assert np.abs(a["truth"] - b["truth"]).max() > 1e-4
        assert np.array_equal(a["truth"][0], b["truth"][0])  # same start pose
    # a held-out tuning maze instead of the test mazes: its own run file and summary
    run("slam_accuracy.py", *args, "--maze-seeds", "991")
    tuned = json.loads((tmp_path / "summary.json").read_text())
    assert tuned["mazes"] == [991] and tuned["runs_per_mode"] == 1
    assert (tmp_path / "runs" / "online_pn_m991_t1_T40.npz").is_file()
    assert 0 <= tuned["online"]["final_mean"] < 0.05
    # driver seeds as a list: the 24 runs can be split between machines
    assert args[2:4] == ("--traversals", "1")
    run("slam_accuracy.py", *args[:3], "2,", *args[4:])
    two = json.loads((tmp_path / "summary.json").read_text())
    assert two["runs_per_mode"] == 1
    assert (tmp_path / "runs" / "online_pn_m1001_t2_T40.npz").is_file()
    assert two["online"]["final_mean"] != summary["online"]["final_mean"]


def test_maze_seeds_accept_test_and_tuning_mazes_and_name_the_others(capsys):
    import argparse

    sys.path.insert(0, str(REPO / "benchmarks"))
    from _common import parse_maze_seeds

    p = argparse.ArgumentParser(prog="bench")
    assert parse_maze_seeds(p, "1002,991", (1001, 1002), (991,)) == [1002, 991]
    for text, test, tuning, msg in [
        ("1002,7", (1002,), (991,), "--maze-seeds [7]: not test mazes (these are [1002]) or "
         "tuning mazes [991]"),
        ("991", (1002,), (), "--maze-seeds [991]: not test mazes (these are [1002])"),
        ("1002,x", (1002,), (), "expected comma-separated integers, got '1002,x'"),
    ]:  # fmt: skip
        with pytest.raises(SystemExit) as exc:
            parse_maze_seeds(p, text, test, tuning)
        assert exc.value.code == 2 and msg in capsys.readouterr().err


def test_slam_error_sources_splits_position_error_into_heading_and_rest(tmp_path):
    # two synthetic runs on a straight line of unit steps: path integration with a constant
    # heading error (its position error is all heading), SLAM with the true heading and a
    # constant position offset (none of it is heading)
    (tmp_path / "runs").mkdir()
    T = 11
    truth = np.stack([np.arange(T, dtype=float), np.zeros(T), np.zeros(T)], 1)
    pi = np.stack([np.arange(T) * math.cos(0.1), np.arange(T) * math.sin(0.1), np.full(T, 0.1)], 1)
    for k in (1, 2):
        np.savez(tmp_path / "runs" / f"online_m1001_t{k}_T{T}.npz", truth=truth, pi_poses=pi,
                 estimate=truth + [0.0, 0.05 * k, 0.0])  # fmt: skip
    out = json.loads(run("slam_error_sources.py", str(tmp_path), "--times", "0,5,-1"))
    assert out["runs"] == 2 and out["t"] == [0, 5, 10]
    np.testing.assert_allclose(out["slam_mean"], [0.075] * 3, atol=1e-4)
    np.testing.assert_allclose(out["slam_heading_only_mean"], [0, 0, 0], atol=1e-4)
    np.testing.assert_allclose(out["pi_heading_only_mean"], out["pi_mean"], atol=1e-4)
    np.testing.assert_allclose(out["pi_mean"], [0, 5 * 2 * math.sin(0.05), 10 * 2 * math.sin(0.05)],
                               atol=1e-4)  # fmt: skip
    assert out["pi_heading_mean"] == [0.1] * 3 and out["slam_beats_pi_fraction"] == [0, 1, 1]
    # SLAM's offset is sideways (none along the path); path integration's shorter x steps lag
    np.testing.assert_allclose(out["slam_along_track_mean"], [0, 0, 0], atol=1e-4)
    np.testing.assert_allclose(out["pi_along_track_mean"], [0, -5 * (1 - math.cos(0.1)),
                               -10 * (1 - math.cos(0.1))], atol=1e-4)  # fmt: skip
    script = str(REPO / "benchmarks" / "slam_error_sources.py")
    cmd = [sys.executable, script, str(tmp_path), "--mode", "offline"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode != 0 and "no offline_m*_t*_T*.npz runs" in proc.stderr
    # --glob reads visual_slam.py's run names; --per-run lists each run's values
    np.savez(tmp_path / "runs" / f"m1001_T{T}.npz", truth=truth, pi_poses=pi, estimate=truth)
    out = json.loads(run("slam_error_sources.py", str(tmp_path), "--glob", "m*.npz", "--times",
                         "5,-1", "--per-run"))  # fmt: skip
    assert out["runs"] == 1 and out["files"] == [f"m1001_T{T}.npz"]
    assert out["slam_per_run"] == [[0.0, 0.0]] and out["pi_heading_per_run"] == [[0.1, 0.1]]


def test_slam_trace_prints_rows_and_summary():
    lines = run("slam_trace.py", "--steps", "40", "--every", "20").strip().splitlines()
    rows = [json.loads(line) for line in lines if line.startswith("{")]
    assert [r["t"] for r in rows[:-1]] == [0, 20, 39]
    assert rows[0]["err"] < 1e-2 and len(rows[0]["std"]) == 3
    final = rows[-1]
    assert final["seed"] == 11 and 0 <= final["final_err"] < 0.05
    assert final["max_heading_err"] >= 0 and final["median_heading_std"] > 0
    # the cloud's trust in the map: flat weights at the start, when nothing is mapped
    assert rows[0]["trust"] == 0.01 and all(0.01 <= r["trust"] <= 1 for r in rows[:-1])


def test_heading_profile_finds_the_true_heading_on_the_true_walls():
    """The diagnostic of session 27: on the maze's true walls the best heading offset is the
    truth's (to one 0.01 rad step); the first scan's own step is matched by its own map."""
    lines = run("heading_profile.py", "--maze", "993", "--steps", "4", "--windows", "0:1,1:4")
    rows = [json.loads(line) for line in lines.strip().splitlines()]
    assert len(rows[0]["slam_heading_error"]) == 4 and abs(rows[0]["slam_heading_error"][0]) < 1e-3
    prof = {(r["map"], tuple(r["steps"])): r for r in rows[1:]}
    assert len(prof) == 6
    for w in [(0, 1), (1, 4)]:
        assert abs(prof["true walls", w]["best_offset"]) <= 0.011
        assert prof["true walls", w]["truth_below_best_nats"] > -1.0
    assert abs(prof["first scan", (0, 1)]["best_offset"]) <= 0.011
    assert all(r["truth_below_best_nats"] <= 0 for r in prof.values())


def test_heading_profile_young_maps_scores_the_filter_weights_on_true_pose_maps():
    """Session 28's ``--young``: the filter's heading weights on maps written at the true
    poses, per step window, next to the true walls'; maze 991's first steps are matched to
    within 0.05 rad, and the weights' heading spread is finite and below the +-0.15 grid's."""
    config = '{"ray_insert": 2.0, "ray_insert_scale": 0.3, "beam_trust": true}'
    lines = run("heading_profile.py", "--young", "3", "--mazes", "991", "--young-windows", "1:4",
                "--config", config).strip().splitlines()  # fmt: skip
    rows = {r["map"]: r for r in map(json.loads, lines)}
    assert set(rows) == {"young map", "true walls"}
    for r in rows.values():
        assert r["steps"] == [1, 4] and r["abs_best_offset"] <= 0.05
        assert abs(r["mean_best_offset"]) <= r["abs_best_offset"] + 1e-9
        assert 0.0 < r["weights_heading_std"] < 0.087  # a flat weight over +-0.15 has 0.087


def test_slam_trace_runs_the_ray_cast_emission_without_loading_the_mlp():
    lines = run("slam_trace.py", "--steps", "30", "--every", "10", "--set",
                "lidar_emission=raycast", "map_resolution=0.03").strip().splitlines()  # fmt: skip
    rows = [json.loads(line) for line in lines if line.startswith("{")]
    assert rows[-1]["config"]["lidar_emission"] == "raycast" and rows[-1]["final_err"] < 0.05
    assert rows[0]["trust"] == 0.01 and all(0.01 <= r["trust"] <= 1 for r in rows[:-1])


def test_slam_trace_maze_seed_traces_the_benchmark_run():
    """``--maze-seed``: slam_accuracy.py's traversal (its own noise draw) and shipped filter."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from slam_accuracy import _traversal

    from pyro_slam.cli import shipped_slam
    from pyro_slam.slam import path_integration

    args = ["--maze-seed", "993", "--seed", "1", "--steps", "30", "--every", "10"]
    args += ["--set", "lidar_emission=raycast", "map_resolution=0.03"]
    lines = run("slam_trace.py", *args).splitlines()
    rows = [json.loads(line) for line in lines if line.startswith("{")]
    final = rows[-1]
    assert final["maze_seed"] == 993 and final["seed"] == 1 and final["final_err"] < 0.05
    tr = _traversal(993, 1, 30, per_maze_noise=True)
    pi = path_integration(tr, shipped_slam(tr, "learned").model.transition)
    err = np.linalg.norm(np.asarray(pi)[-1, :2] - tr.poses[-1, :2])
    assert abs(final["final_err_pi"] - err) < 1e-6


def test_ray_map_fit_scores_learned_and_oracle_maps_at_the_true_poses():
    lines = run("ray_map_fit.py", "--maze-seeds", "991", "--steps", "30", "--map-poses", "true",
                "--set", "lr_map=0.1").strip().splitlines()  # fmt: skip
    row, summary = json.loads(lines[0]), json.loads(lines[-1])
    assert row["maze"] == 991 and row["map_poses"] == "true" and row["set"] == {"lr_map": 0.1}
    for key in ("at_true", "at_estimate"):
        r = row[key]
        assert 0 < r["median_abs"] <= r["rms"] < 0.53 and abs(r["mean"]) < 0.53
    assert 0 <= row["final_err"] < 0.05 and row["pi_final_err"] >= 0
    assert summary["rms_at_true_mean"] == row["at_true"]["rms"]
    # the wall map reproduces the scans (median residual below the 0.016 grid spacing)
    oracle = json.loads(run("ray_map_fit.py", "--oracle", "--maze-seeds", "991", "--steps", "50")
                        .strip().splitlines()[0])  # fmt: skip
    assert oracle["at_true"]["median_abs"] < 0.01 and oracle["at_true"]["rms"] < 0.05


def test_slam_trace_diagnostics_pin_or_freeze_the_cache_and_score_the_frontier():
    lines = run("slam_trace.py", "--steps", "30", "--every", "10", "--map-poses", "pi",
                "--frozen-cache", "--frontier").strip().splitlines()  # fmt: skip
    rows = [json.loads(line) for line in lines if line.startswith("{")]
    final = rows[-1]
    assert final["map_poses"] == "pi" and final["frozen_cache"] and not final["oracle_map"]
    for r in rows[:-1]:
        # the residual of a 20-beam scan in [0, 0.53]; an offset within the searched +-0.3 rad
        assert 0 < r["frontier_rms"] < 0.53 and abs(r["frontier_best_offset"]) <= 0.3
        assert -1e-3 <= r["frontier_trust"] <= 1 and r["dev_pi"] >= 0
    assert 0 < final["frontier_rms"] < 0.53


def test_exploration_benchmark_same_curves_serial_and_parallel(tmp_path):
    args = ("--scales", "simple-small", "--seeds", "2", "--step-fraction", "0.02",
            "--ars-iterations", "1", "--ars-directions", "2", "--ars-mazes", "1",
            "--ars-steps", "10", "--horizon", "10")  # fmt: skip
    out = {}
    for workers in (1, 2):
        d = tmp_path / f"w{workers}"
        run("exploration.py", *args, "--workers", str(workers), "--out", str(d))
        out[workers] = json.loads((d / "exploration.json").read_text())
        assert (d / "exploration_curves.png").stat().st_size > 10_000
    a, b = out[1], out[2]
    # a re-run resumes: PEMA and the 6 finished runs are loaded, not recomputed (same timings)
    assert len(list((tmp_path / "w1" / "runs").glob("*.json"))) == 6
    assert (tmp_path / "w1" / "pema.pt").exists()
    run("exploration.py", *args, "--workers", "1", "--out", str(tmp_path / "w1"))
    again = json.loads((tmp_path / "w1" / "exploration.json").read_text())
    assert again["curves"] == a["curves"] and again["final"] == a["final"]
    assert again["ars"]["seconds"] == a["ars"]["seconds"]
    assert a["config"]["horizon"] == 10 and a["steps"] == {"simple-small": 30}
    assert a["curves"] == b["curves"]  # seeded agents: parallel runs change nothing
    for agent in ("mi", "pema", "random"):
        runs = a["curves"]["simple-small"][agent]
        assert len(runs) == 2
        for r in runs:
            assert r["steps"][0] == 0 and r["steps"][-1] == 30
            assert 0 < r["ratio"][-1] <= 1 and r["ratio"] == sorted(r["ratio"])  # never shrinks
            assert r["infogain"][-1] > 0
    # seeds split over two runs (--first-seed) and merged give the same curves and finals
    one = ("--seeds", "1", "--workers", "1")
    run("exploration.py", *args, *one, "--out", str(tmp_path / "s0"))
    run("exploration.py", *args, *one, "--first-seed", "1", "--out", str(tmp_path / "s1"))
    parts = [str(tmp_path / d / "exploration.json") for d in ("s0", "s1")]
    run("exploration.py", "--merge", *parts, "--out", str(tmp_path / "m"))
    m = json.loads((tmp_path / "m" / "exploration.json").read_text())
    assert m["seeds"] == 2 and m["curves"] == a["curves"]
    for agent in ("mi", "pema", "random"):
        fa, fm = a["final"]["simple-small"][agent], m["final"]["simple-small"][agent]
        assert fm["ratio_mean"] == pytest.approx(fa["ratio_mean"]) and fm["seeds"] == 2
        assert fm["infogain_std"] == pytest.approx(fa["infogain_std"])


def test_navigation_benchmark_summarises_learned_truth_and_observation_targets(tmp_path):
    args = ("--mazes", "1", "--pairs-limit", "2", "--traversal-steps", "300",
            "--emission-steps", "30", "--fit-steps", "30", "--sleep-steps", "30",
            "--inverse-steps", "10", "--max-expansions", "60", "--out", str(tmp_path))  # fmt: skip
    run("navigation.py", *args)
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["pairs"] == 2 and s["budgets"][-1] == 60
    for name in ("learned", "ground_truth", "learned_obs", "ground_truth_obs"):
        curve = s[f"{name}_noiseless"]
        assert len(curve) == len(s["budgets"]) and all(0 <= v <= 1 for v in curve)
        assert curve == sorted(curve)  # success can only grow with the budget
    inv = s["inverse"]
    assert inv["targets"] == 50  # 25 grid points x 2 headings
    assert 0 <= inv["mode_far_true_scan_matches"] <= 1 - inv["mode_within_0.05"] + 1e-9
    # --cover-grid (default): the 300-step walk is followed by a tour through the grid points
    targets = json.loads((tmp_path / "targets.json").read_text())
    assert min(t["traversal_steps"] for t in targets) > 300
    runs = json.loads((tmp_path / "runs.json").read_text())
    planners = {"learned", "ground_truth", "learned_obs", "ground_truth_obs"}
    assert len(runs) == 8 and {r["planner"] for r in runs} == planners
    # the truth's inverse finds every target's exact scan; the oracle's expected failure is 0
    # on targets without an exact look-alike 0.05 away and below 1 on the others
    for t in targets:
        assert t["gt_inverse_diff"] < 1e-6
        assert (t["oracle_failure"] > 0) == (t["lookalikes_exact"] > 0) and t["oracle_failure"] < 1
    assert inv["lookalike_exact"] == np.mean([t["lookalikes_exact"] > 0 for t in targets])
    assert 0 <= s["obs_oracle_expected_failure"] <= s["obs_target_aliased_exact"]
    assert (tmp_path / "navigation.png").stat().st_size > 10_000
    assert s["resumed_mazes"] == []
    # observation runs judged in observation space too: reaching the target counts as reaching
    # its observation, so that failure ratio can only be lower
    for r in (r for r in runs if r["planner"].endswith("_obs")):
        for nz in ("noiseless", "noisy"):
            assert r[f"scan_diff_{nz}"] >= 0
            assert r[f"scan_success_{nz}"] >= r[f"success_{nz}"]
            if r[f"success_{nz}"]:  # the target is within the radius, up to the search's grid
                assert r[f"scan_diff_{nz}"] < 0.01
    assert s["obs_failure_ratio_scan_noiseless"] <= s["obs_failure_ratio"]
    by_tol = s["obs_failure_ratio_scan_noiseless_by_tol"]  # a looser tolerance forgives more
    assert list(by_tol) == ["0.0025", "0.005", "0.01"]
    assert by_tol["0.01"] == s["obs_failure_ratio_scan_noiseless"]
    assert list(by_tol.values()) == sorted(by_tol.values(), reverse=True)
    # the counts behind the ratios
    c = s["per_maze"]
    assert set(c) == {"1001", "all"} and c["all"] == c["1001"] and c["all"]["pairs"] == 2
    if c["all"]["gt_solved"]:
        assert (
            s["learned_success_on_gt_solved"]
            == c["all"]["learned_on_gt_solved"] / c["all"]["gt_solved"]
        )
    assert s["obs_failure_ratio"] == c["all"]["obs_missed"] / 2
    assert s["obs_failure_ratio_scan_noiseless"] == c["all"]["obs_missed_scan"] / 2
    assert s["ground_truth_obs_failure_ratio"] == c["all"]["gt_obs_missed"] / 2
    # a second run resumes from the finished maze: the same rows, timings included
    run("navigation.py", *args)
    assert json.loads((tmp_path / "runs.json").read_text()) == runs
    assert json.loads((tmp_path / "summary.json").read_text())["resumed_mazes"] == [1001]
    # the pairs are those maze_pairs draws for this maze whichever mazes run; a share named by
    # --maze-seeds has the same settings, so it resumes the maze as well
    sys.path.insert(0, str(REPO / "benchmarks"))
    from navigation import maze_pairs

    drawn = maze_pairs(2, 0)
    assert len(drawn[1001]) == 2 and len(maze_pairs(0, 0)[1002]) == 25 * 24  # 5 x 5 grid
    assert maze_pairs(2, 0) == drawn and maze_pairs(2, 1) != drawn
    assert {(r["start"], r["goal"]) for r in runs} == set(drawn[1001])
    run("navigation.py", *args[2:], "--maze-seeds", "1001")
    assert json.loads((tmp_path / "summary.json").read_text())["resumed_mazes"] == [1001]
    assert json.loads((tmp_path / "runs.json").read_text()) == runs
    cmd = [sys.executable, str(REPO / "benchmarks" / "navigation.py"), "--maze-seeds", "1002,7"]
    err = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert err.returncode == 2 and "--maze-seeds [7]: not test mazes" in err.stderr


def test_navigation_counts_sort_the_missed_observation_targets_by_cause():
    sys.path.insert(0, str(REPO / "benchmarks"))
    from navigation import _counts

    def row(maze, goal, planner, ok, **kw):
        return {"maze": maze, "start": 0, "goal": goal, "planner": planner,
                "success_noiseless": ok, "found": True, **kw}  # fmt: skip

    def obs(maze, goal, ok, scan_ok, found=True, inference_error=0.01, aliased=0):
        return row(maze, goal, "learned_obs", ok, scan_success_noiseless=scan_ok, found=found,
                   inference_error=inference_error, target_lookalikes_exact=aliased)  # fmt: skip

    runs = [
        *(row(1001, g, "ground_truth", g != 4) for g in range(1, 6)),  # 4 solved by the truth
        *(row(1001, g, "learned", g not in (3, 4)) for g in range(1, 6)),  # misses 3 (and 4)
        obs(1001, 1, True, True),
        obs(1001, 2, False, True, inference_error=0.3, aliased=2),  # a look-alike: reached
        *(row(1001, g, "ground_truth_obs", g not in (2, 4)) for g in range(1, 6)),
        obs(1001, 3, False, False, found=False),
        obs(1001, 4, False, False, inference_error=0.3),  # a wrong goal
        obs(1001, 5, False, False),  # right goal, ended elsewhere
        row(1002, 1, "ground_truth", True),
        row(1002, 1, "learned", True),
        obs(1002, 1, False, False, inference_error=0.2),
    ]
    c = _counts(runs)
    assert c["1001"] == {
        "pairs": 5, "gt_solved": 4, "learned_on_gt_solved": 3, "obs_missed": 4,
        "obs_missed_scan": 3, "obs_missed_scan_not_found": 1, "obs_missed_scan_wrong_goal": 1,
        "obs_missed_scan_execution": 1, "obs_target_aliased": 1, "gt_obs_missed": 2,
    }  # fmt: skip
    assert c["1002"]["obs_missed_scan_wrong_goal"] == 1 and c["1002"]["gt_solved"] == 1
    assert c["all"]["pairs"] == 6 and c["all"]["obs_missed_scan"] == 4
    assert c["all"]["learned_on_gt_solved"] == 4


def test_navigation_scan_match_finds_the_target_view_near_it_and_not_elsewhere():
    sys.path.insert(0, str(REPO / "benchmarks"))
    from navigation import _scan_match

    from pyro_slam.planning import GroundTruthEnv, free_grid
    from simulators import make_maze

    maze = make_maze("moderate-medium", 1001)
    env, pts = GroundTruthEnv(maze), free_grid(maze)
    scan = env.scan(np.array([*pts[3], 0.7]))[0].numpy()  # a target seen with heading 0.7
    # at the target, or within the 0.05 success radius, some heading sees (almost) that scan
    assert _scan_match(env, maze, pts[3], scan) < 0.01
    assert _scan_match(env, maze, pts[3] + 0.03, scan) < 0.01
    # the other grid points of this maze do not look like it
    others = [_scan_match(env, maze, q, scan, headings=72) for i, q in enumerate(pts[:8]) if i != 3]
    assert min(others) > 0.02


def test_navigation_benchmark_maps_at_slam_poses(tmp_path):
    # --map-poses slam: emission and q(M) are fitted at the pose means of online SLAM on the
    # mapping traversal; the SLAM run's error is reported per maze
    args = ("--mazes", "1", "--pairs-limit", "1", "--traversal-steps", "200", "--no-cover-grid",
            "--emission-steps", "20", "--fit-steps", "20", "--sleep-steps", "20",
            "--inverse-steps", "5", "--max-expansions", "30", "--map-poses", "slam",
            "--out", str(tmp_path))  # fmt: skip
    run("navigation.py", *args)
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["args"]["map_poses"] == "slam" and s["pairs"] == 1
    err = s["inverse"]["slam_error"]["1001"]
    # 200 steps: both estimates stay within a few cells of the truth
    assert 0 < err["mean"] <= err["max"] < 0.1 and 0 <= err["pi_final"] < 0.1
    targets = json.loads((tmp_path / "targets.json").read_text())
    assert {t["traversal_steps"] for t in targets} == {200}


def test_frontier_ceiling_reprojection_is_exact_on_straight_walls_and_beats_copy():
    import numpy as np

    sys.path.insert(0, str(REPO / "benchmarks"))
    from frontier_ceiling import read_profile, reproject

    from simulators import raycast

    # a 1 x 1 room: the polygon of a profile seen from the centre lies on the walls except
    # where a segment cuts a corner, so beams that hit a wall away from the corners are exact
    walls = np.array([[0, 0, 1, 0], [1, 0, 1, 1], [1, 1, 0, 1], [0, 1, 0, 0]], float)
    n, beams, R = 360, np.array([0.0, 0.5 * np.pi, np.pi, 1.5 * np.pi]), 2.0
    centre = np.array([[0.5, 0.5]])
    prof = raycast(walls, centre, 2 * np.pi * np.arange(n) / n, R)  # [1, n]
    pose = np.array([[0.6, 0.45, 0.0]])
    truth = raycast(walls, pose[:, :2], pose[:, 2:] + beams, R)
    np.testing.assert_allclose(reproject(prof, centre, pose, beams, R), truth, atol=1e-9)
    np.testing.assert_allclose(read_profile(prof, np.zeros(1), beams), [[0.5, 0.5, 0.5, 0.5]])
    # copying the view ignores the 0.1 / 0.05 shift
    assert np.abs(read_profile(prof, pose[:, 2], beams) - truth).max() > 0.09

    out = json.loads(run("frontier_ceiling.py", "--steps", "300"))
    lag = out["n_world=60"]["lag8"]
    assert 0.02 < lag["distance_mean"] < 0.08
    assert lag["reproject"]["rms"] < lag["copy"]["rms"]
    assert out["n_world=60"]["self"]["rms"] < out["n_world=20"]["self"]["rms"]


def test_visual_slam_benchmark_summarises_mazes_and_resumes(tmp_path):
    from pyro_slam.metrics import localisation_error

    args = ("--mazes", "2", "--steps", "60", "--pretrain-steps", "5", "--pretrain-traversal",
            "100", "--workers", "2", "--config", '{"offline_svi_steps": 10}', "--out",
            str(tmp_path))  # fmt: skip
    run("visual_slam.py", *args)
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["steps"] == 60 and s["mazes"] == [1001, 1002]
    for key in ("offline", "path_integration"):
        per = s[key]["per_maze"]
        assert len(per) == 2 and all(0 <= v < 1 for v in per)
        assert s[key]["final_mean"] == pytest.approx(sum(per) / 2)
    assert len(s["online_sweep"]["per_maze"]) == 2 and s["online_sweep"]["final_mean"] < 1
    for png in ("error_bands.png", "reconstructions.png"):
        assert (tmp_path / png).stat().st_size > 10_000
    runs = sorted((tmp_path / "runs").glob("*.npz"))
    stamps = [f.stat().st_mtime_ns for f in runs]
    assert len(runs) == 2 and s["per_maze_noise"]  # by default each maze draws its own noise
    assert all("_pn" in f.name for f in runs)
    # each run exports its trajectories [T, 3]: the errors are recomputed from them, and the
    # online sweep offline SLAM starts from is kept apart from the final pass
    with np.load(runs[0]) as z:
        assert z["estimate"].shape == z["truth"].shape == z["pi_poses"].shape == (60, 3)
        assert z["sweep"].shape == (60, 3) and not np.allclose(z["sweep"], z["estimate"])
        np.testing.assert_allclose(localisation_error(z["estimate"], z["truth"]), z["slam"],
                                   atol=1e-5)  # fmt: skip
        np.testing.assert_allclose(localisation_error(z["pi_poses"], z["truth"]), z["pi"],
                                   atol=1e-5)  # fmt: skip
    run("visual_slam.py", *args)  # resumes: the finished runs are not recomputed
    assert [f.stat().st_mtime_ns for f in runs] == stamps
    assert json.loads((tmp_path / "summary.json").read_text())["offline"] == s["offline"]
    # the diagnostic: the map learned at the true poses, stored apart; the emission is reused;
    # --maze-seeds picks one maze (here a held-out tuning maze)
    # --odometry-scale: the traversal is driven with scaled actuation noise, stored apart
    run("visual_slam.py", *args[:-2], "--maze-seeds", "997", "--map-poses", "true",
        "--workers", "1", "--odometry-scale", "0.5", "--out", str(tmp_path))  # fmt: skip
    o = json.loads((tmp_path / "summary.json").read_text())
    assert o["map_poses"] == "true" and s["map_poses"] == "filter" and o["mazes"] == [997]
    # the default: the paper's path-integration level (the calibrated scale), in the names
    assert o["odometry_scale"] == 0.5 and s["odometry_scale"] == 0.57
    assert all("_od0.57_pn" in f.name for f in runs)
    assert 0 <= o["offline"]["per_maze"][0] < 1
    (f,) = (tmp_path / "runs").glob("m997_map-true_*.npz")
    assert f.name == "m997_map-true_od0.5_pn_T60.npz"
    sys.path.insert(0, str(REPO / "benchmarks"))
    from visual_slam import _traversal

    with np.load(f) as z:
        kw = {"images": False, "per_maze_noise": True}
        np.testing.assert_allclose(z["truth"], _traversal(997, 1, 60, 0.5, **kw).poses, atol=1e-6)
        assert np.abs(z["truth"] - _traversal(997, 1, 60, **kw).poses).max() > 1e-4
    # another configuration into the same folder stops before anything is recomputed or lost
    cmd = [sys.executable, str(REPO / "benchmarks" / "visual_slam.py"), *args[:-4]]
    other = '{"offline_svi_steps": 11}'
    err = subprocess.run([*cmd, "--config", other, "--out", str(tmp_path)], capture_output=True,
                         text=True)  # fmt: skip
    assert err.returncode == 1 and "config.json: this output folder holds runs" in err.stderr
    assert "differs in offline_svi_steps" in err.stderr
    assert [f.stat().st_mtime_ns for f in runs] == stamps
    cmd = [sys.executable, str(REPO / "benchmarks" / "visual_slam.py"), "--maze-seeds", "1002,7"]
    err = subprocess.run([*cmd, "--out", str(tmp_path)], capture_output=True, text=True)
    assert err.returncode == 2 and "--maze-seeds [7]: not test mazes" in err.stderr
    assert "or tuning mazes [997, 998]" in err.stderr
    err = subprocess.run([*cmd[:2], "--odometry-scale", "0"], capture_output=True, text=True)
    assert err.returncode == 2 and "--odometry-scale must be > 0, got 0.0" in err.stderr


def test_visual_slam_calibrates_the_odometry_noise_to_the_papers_path_integration():
    sys.path.insert(0, str(REPO / "benchmarks"))
    from visual_slam import PAPER_PI, _traversal, calibrate_odometry, scaled_config

    from pyro_slam.slam import SLAMConfig

    res = calibrate_odometry(400, seeds=(900, 901, 902), rounds=1, per_maze_noise=True)
    assert res["target"] == PAPER_PI == 0.11 and res["mazes"] == [900, 901, 902]
    base, refined = res["points"]
    assert base["scale"] == 1.0 and refined["scale"] == round(PAPER_PI / base["mean"], 2)
    best = min(res["points"], key=lambda q: abs(q["mean"] - PAPER_PI))
    assert res["at_scale"] == best and res["scale_for_target"] == best["scale"]
    # path integration drifts about in proportion to the noise
    ratio = refined["mean"] / base["mean"]
    assert 0.5 * refined["scale"] < ratio < 1.5 * refined["scale"]
    cfg = scaled_config(SLAMConfig(transition_sigma=(1e-3, 2e-3, 8e-3)), 0.5)
    assert cfg.transition_sigma == pytest.approx((5e-4, 1e-3, 4e-3))
    # per-maze noise: the mazes' heading drifts differ; with the shared noise they do not
    # (the rotation noise is added whatever the controls)

    def drift(maze, per_maze):
        tr = _traversal(maze, 1, 300, images=False, per_maze_noise=per_maze)
        return tr.metadata["noise_seed"], np.diff(tr.poses[:, 2]) - tr.controls[:, 0]

    (seed_a, a), (_, b) = drift(900, False), drift(901, False)
    assert seed_a is None and np.allclose(np.angle(np.exp(1j * (a - b))), 0, atol=1e-6)
    (seed_a, a), (_, b) = drift(900, True), drift(901, True)
    assert seed_a == [1, 900] and not np.allclose(np.angle(np.exp(1j * (a - b))), 0, atol=1e-3)


def test_visual_slam_probe_scores_the_image_on_a_heading_grid(tmp_path):
    args = ("--maze", "1002", "--steps", "60", "--every", "20", "--pretrain-steps", "5",
            "--pretrain-traversal", "100", "--out", str(tmp_path))  # fmt: skip
    run("visual_slam_probe.py", *args)
    out = json.loads((tmp_path / "probe_m1002.json").read_text())
    H = len(out["heading_offsets"])
    assert H == 41 and out["heading_offsets"][20] == 0.0
    assert [r["t"] for r in out["probes"]] == [20, 40] and len(out["trust"]) == 60
    assert out["late_probes"] == 1 and 0 <= out["late_truth_preferred"] <= 1
    for r in out["probes"]:
        lt, le = np.array(r["loglik_true_position"]), np.array(r["loglik_estimated_position"])
        assert lt.shape == le.shape == (H,) and np.isfinite(lt).all() and np.isfinite(le).all()
        assert r["best_heading_offset_at_truth"] == out["heading_offsets"][int(lt.argmax())]
        assert 0 <= r["error"] < 0.1 and 0 <= r["heading_error"] < 0.5
        assert all(0 < s < 0.1 for s in r["cloud_std"])
    assert all(0 <= q <= 1 for q in out["trust_mean_per_quarter"])
    assert out["odometry_windows"] >= 0 and out["odometry_windows_max_gap"] >= 0


def test_revisit_stats_tells_a_heading_that_follows_odometry_and_the_first_visits():
    sys.path.insert(0, str(REPO / "benchmarks"))
    from visual_slam_probe import revisit_stats

    T = 1000
    s = np.linspace(0, 1, T)
    truth = np.stack([0.5 + 0.3 * np.cos(4 * np.pi * s), 0.5 + 0.3 * np.sin(4 * np.pi * s),
                      4 * np.pi * s + np.pi / 2], 1)  # fmt: skip  # two laps of one circle
    pi = truth.copy()
    pi[:, 2] += np.linspace(0, 0.5, T)  # odometry's heading drifts 0.05 rad per 100 steps
    est = truth.copy()
    est[:, 2] += np.linspace(0, 0.5, T)  # ... and the estimate's with it
    est[:, 0] += np.where(np.arange(T) < 500, 0.01, 0.04)  # the first lap's error 0.01
    out = revisit_stats(est, truth, pi, turn=0.04, tail=400)
    assert out["odometry_windows"] == 9 and out["odometry_windows_max_gap"] < 1e-9
    # the second lap's steps (600, 700, 800, 900) revisit the first lap's places at t < 500
    assert out["revisits"] == 4 and out["first_visit_steps"][1] < 500
    assert out["first_visit_error_max"] == pytest.approx(0.01)
    assert out["revisit_heading_error"][1] == pytest.approx(0.5 * 900 / 999, abs=1e-3)
    est[:, 2] = truth[:, 2]  # a heading that does not follow odometry
    assert revisit_stats(est, truth, pi, turn=0.04)["odometry_windows_max_gap"] > 0.04
    cmd = [sys.executable, str(REPO / "benchmarks" / "visual_slam_probe.py"), "--maze", "7"]
    err = subprocess.run(cmd, capture_output=True, text=True)
    assert err.returncode == 2 and "--maze 7: not a test maze" in err.stderr


def test_compare_runs_pairs_the_runs_both_outputs_share(tmp_path):
    T = 50
    for out, finals in (("a", [0.02, 0.04, 0.10]), ("b", [0.03, 0.06, 0.08, 0.5])):
        (tmp_path / out / "runs").mkdir(parents=True)
        for i, f in enumerate(finals):
            slam = np.linspace(0, f, T)
            np.savez(tmp_path / out / "runs" / f"offline_m{1001 + i}_t1_T{T}.npz", slam=slam,
                     pi=np.full(T, 0.07))  # fmt: skip
    out = json.loads(run("compare_runs.py", str(tmp_path / "a"), str(tmp_path / "b"),
                         "--glob", "offline_*.npz"))  # fmt: skip
    assert out["runs"] == 3 and out["a"]["all_runs"] == 3 and out["b"]["all_runs"] == 4
    assert out["a"]["final_mean"] == pytest.approx(0.16 / 3)
    assert out["a"]["runs_under_0.05"] == 2 and out["a"]["runs_beating_pi"] == 2
    assert out["b"]["final_mean"] == pytest.approx(0.17 / 3)  # the shared runs only
    d = np.array([-0.01, -0.02, 0.02])
    assert out["paired_final"]["mean"] == pytest.approx(d.mean())
    assert out["paired_final"]["se"] == pytest.approx(d.std(ddof=1) / np.sqrt(3))
    assert out["paired_final"]["a_lower"] == 2
    assert out["paired_time_avg"]["mean"] == pytest.approx(d.mean() / 2)
    cmd = [sys.executable, str(REPO / "benchmarks" / "compare_runs.py"), str(tmp_path / "a")]
    err = subprocess.run([*cmd, str(tmp_path / "b"), "--glob", "online_*.npz"],
                         capture_output=True, text=True)  # fmt: skip
    assert err.returncode == 2 and "no runs matching 'online_*.npz'" in err.stderr


def _square_loop(T: int, side: float = 0.5):
    """A true path around a square (closing on itself) and odometry with a heading bias."""
    s = np.linspace(0.0, 4 * side, T)  # arc length
    leg = np.minimum(s // side, 3).astype(int)  # [T] which side
    u = s - leg * side
    corners = np.array([[0, 0], [side, 0], [side, side], [0, side]], dtype=float)
    dirs = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]], dtype=float)
    xy = corners[leg] + u[:, None] * dirs[leg]
    truth = np.concatenate([xy, (leg * np.pi / 2)[:, None]], 1)
    # odometry: the true body-frame steps, integrated with a heading error of 5e-4 rad per step
    d = np.diff(truth, axis=0)
    c, si = np.cos(truth[:-1, 2]), np.sin(truth[:-1, 2])
    body = np.stack([c * d[:, 0] + si * d[:, 1], -si * d[:, 0] + c * d[:, 1]], 1)
    h = truth[0, 2] + np.concatenate([[0.0], np.cumsum(d[:, 2] + 5e-4)])
    steps = np.stack([np.cos(h[:-1]) * body[:, 0] - np.sin(h[:-1]) * body[:, 1],
                      np.sin(h[:-1]) * body[:, 0] + np.cos(h[:-1]) * body[:, 1]], 1)  # fmt: skip
    odo = np.concatenate([truth[:1, :2] + np.concatenate([[[0, 0]], np.cumsum(steps, 0)]),
                          h[:, None]], 1)  # fmt: skip
    return truth, odo


def test_slam_pose_graph_spreads_a_loop_closure_back_along_the_odometry(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))
    from slam_pose_graph import loop_closures, pose_graph

    from pyro_slam.metrics import localisation_error

    truth, odo = _square_loop(400)
    # a filter that follows odometry, then relocalises on the map at the start when the loop
    # closes (its last 10 steps lie within 0.05 of the start): the estimate jumps there
    est = odo.copy()
    est[-20:] = truth[-20:]
    pairs = loop_closures(est, radius=0.05, gap=300)
    assert len(pairs) == 10 and (pairs[:, 1] >= 390).all() and (pairs[:, 0] == 0).all()
    kw = dict(radius=0.05, gap=300, sigma_odometry=(1e-4, 1e-4, 5e-4), sigma_loop=(0.002, 0.01))
    graph, n = pose_graph(est, odo, **kw)
    assert n == len(pairs)
    err = {k: localisation_error(x, truth) for k, x in (("est", est), ("graph", graph))}
    # the closure bends the whole loop back: mid-way the graph is far closer than the odometry
    assert err["est"][200] > 0.03 and err["graph"][200] < 0.25 * err["est"][200]
    assert err["graph"].mean() < 0.25 * err["est"].mean() and err["graph"][-1] < 0.005
    np.testing.assert_allclose(graph[0], est[0], atol=1e-9)  # the start pose is fixed
    # no loop closures: the graph is the odometry
    same, n0 = pose_graph(odo, odo, gap=1000)
    assert n0 == 0 and np.allclose(same, odo, atol=1e-9)
    with pytest.raises(ValueError, match=r"want \[T, 3\]"):
        pose_graph(est[:, :2], odo[:, :2])
    # the script summarises the runs it finds
    (tmp_path / "runs").mkdir()
    np.savez(
        tmp_path / "runs" / "online_m1001_t1_T400.npz", truth=truth, estimate=est, pi_poses=odo
    )
    args = ("--radius", "0.05", "--sigma-odometry", "1e-4,1e-4,5e-4", "--sigma-loop", "0.002,0.01")
    out = json.loads(run("slam_pose_graph.py", str(tmp_path), *args))
    assert out["runs"] == 1 and out["loop_closures_mean"] == len(pairs)
    assert out["pose_graph_time_avg_mean"] < 0.25 * out["slam_time_avg_mean"]
    assert out["slam_final_mean"] < 1e-6 and out["pi_final_mean"] > 0.05
    # a run without its exported trajectories is named, not a KeyError
    np.savez(tmp_path / "runs" / "online_m1002_t1_T400.npz", truth=truth, pi_poses=odo)
    script = str(REPO / "benchmarks" / "slam_pose_graph.py")
    proc = subprocess.run([sys.executable, script, str(tmp_path)], capture_output=True, text=True)
    assert proc.returncode != 0 and "online_m1002_t1_T400.npz: no ['estimate']" in proc.stderr


def test_aliasing_counts_exact_look_alikes_and_the_ideal_failure():
    """In an empty square room every pose but the centre has three exact look-alikes (the
    room's rotations), so an ideal inverse picks the right one of four: it fails 3/4 of the
    time; the centre is unique. A longer range does not help in an empty room, and a sensor
    that is not BEAMSxRANGE is a usage error."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from aliasing import _summary, aliasing

    from simulators import LidarConfig
    from simulators.maze import Maze

    n = 6
    h, v = np.zeros((n, n + 1), bool), np.zeros((n + 1, n), bool)
    h[:, [0, n]], v[[0, n], :] = True, True
    room = Maze("room", 0, n, 1 / n, h, v)
    tposes = np.array([[0.3, 0.4, 0.7], [0.5, 0.5, 0.2], [0.2, 0.2, -1.0]])
    r = aliasing(room, tposes, LidarConfig(), tols=[1e-6], spacing=0.01)[1e-6]
    assert r["lookalikes"] == [3, 0, 3]
    assert r["ideal_failure"] == pytest.approx([0.75, 0.0, 0.75])
    r = aliasing(room, tposes[:1], LidarConfig(n_beams=40, max_range=1.5), [1e-6], 0.01)
    assert r[1e-6]["lookalikes"] == [3]
    # the summary splits the targets by whether free_grid moved their point to a cell centre
    per_maze = {
        "1": {"lookalikes": [3, 0], "ideal_failure": [0.75, 0.0], "moved": [True, False]},
        "2": {"lookalikes": [1, 0], "ideal_failure": [0.5, 0.0], "moved": [True, True]},
    }
    s = _summary(per_maze)
    assert s["targets"] == 4 and s["aliased"] == 0.5 and s["ideal_failure"] == 0.3125
    assert s["kept"] == {"targets": 1, "aliased": 0.0, "ideal_failure": 0.0}
    assert s["moved_to_cell_centre"]["ideal_failure"] == pytest.approx(1.25 / 3)
    assert s["per_maze"]["2"]["aliased"] == 0.5
    cmd = [sys.executable, str(REPO / "benchmarks" / "aliasing.py"), "--sensors", "20-0.5"]
    err = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert err.returncode == 2 and "sensor '20-0.5': expected BEAMSxRANGE" in err.stderr
