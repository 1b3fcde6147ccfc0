"""The benchmark scripts run as modules (``python -m benchmarks.NAME``) end to end at toy sizes
and print / write what their docs promise; usage errors exit with status 2."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pyro_slam.slam import presets

REPO = Path(__file__).resolve().parents[1]
# every benchmark script (benchmarks/NAME.py, run as python -m benchmarks.NAME)
SCRIPTS = (
    "aliasing",
    "compare_runs",
    "exploration",
    "filter_speed",
    "likelihood_peak",
    "navigation",
    "offline_elbo",
    "pfnet_table",
    "real_data",
    "reliability",
    "simulator",
    "slam_accuracy",
    "slam_speed",
    "visual_slam",
)


def bench(name: str, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``python -m benchmarks.NAME ARGS`` from the repository root."""
    cmd = [sys.executable, "-m", f"benchmarks.{name}", *args]
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=timeout)


def run(name: str, *args: str) -> str:
    """The stdout of a benchmark that must succeed."""
    proc = bench(name, *args)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def last_json(stdout: str):
    """The JSON object a benchmark prints last (its first line starts with ``{``)."""
    lines = stdout.rstrip().splitlines()
    start = max(i for i, line in enumerate(lines) if line.startswith("{"))
    return json.loads("\n".join(lines[start:]))


@pytest.mark.parametrize("name", SCRIPTS)
def test_every_benchmark_runs_as_a_module(name):
    assert (REPO / "benchmarks" / f"{name}.py").is_file()
    out = run(name, "--help")
    assert f"usage: python -m benchmarks.{name}" in out


def test_maze_seeds_accept_test_and_tuning_mazes_and_name_the_others(capsys):
    import argparse

    from benchmarks._common import parse_maze_seeds

    p = argparse.ArgumentParser(prog="bench")
    assert parse_maze_seeds(p, "1002,991", (1001, 1002), (991,)) == [1002, 991]
    for text, test, tuning, msg in [
        (
            "1002,7",
            (1002,),
            (991,),
            "--maze-seeds [7]: not test mazes (these are [1002]) or tuning mazes [991]",
        ),
        ("991", (1002,), (), "--maze-seeds [991]: not test mazes (these are [1002])"),
        ("1002,x", (1002,), (), "expected comma-separated integers, got '1002,x'"),
    ]:
        with pytest.raises(SystemExit) as exc:
            parse_maze_seeds(p, text, test, tuning)
        assert exc.value.code == 2 and msg in capsys.readouterr().err


def test_simulator_benchmark_reports_lidar_steps_per_second():
    out = last_json(run("simulator", "--steps", "200"))
    assert out["steps"] == 200 and out["maze"] == "moderate-medium"
    for key in ("steps_per_s", "camera_frames_per_s_batched", "simulate_traversal_steps_per_s"):
        assert math.isfinite(out[key]) and out[key] > 0, key


def test_filter_speed_benchmark_compares_with_smcfilter_and_reports_flat_memory():
    out = last_json(
        run("filter_speed", "--particles", "50", "--steps", "20", "--long-steps", "100")
    )
    assert out["particles"] == 50 and out["long_run_steps"] == 100
    for key in (
        "ours_steps_per_s",
        "smcfilter_steps_per_s",
        "ours_bf16_emission_steps_per_s",
        "emission_only_steps_per_s",
        "emission_only_bf16_steps_per_s",
    ):
        assert out[key] > 0, key
    # the ratios are those of the rates reported (up to their rounding)
    assert math.isclose(
        out["speedup"],
        out["ours_steps_per_s"] / out["smcfilter_steps_per_s"],
        rel_tol=0.02,
        abs_tol=0.01,
    )
    assert math.isclose(
        out["ceiling_speedup"],
        out["emission_only_steps_per_s"] / out["smcfilter_steps_per_s"],
        rel_tol=0.02,
        abs_tol=0.01,
    )
    # flat memory: the long run keeps no per-step history
    assert out["peak_rss_mib_at_100"] <= 1.1 * out["peak_rss_mib_at_10"]


def test_slam_accuracy_benchmark_writes_summary_plot_and_resumable_runs(tmp_path):
    from pyro_slam.slam import presets

    args = (
        "--mazes",
        "1",
        "--traversals",
        "1",
        "--steps",
        "40",
        "--modes",
        "online",
        "--workers",
        "1",
        "--out",
        str(tmp_path),
    )
    out = last_json(run("slam_accuracy", *args))
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert out == summary and summary["steps"] == 40 and summary["runs_per_mode"] == 1
    # the preset (default: the default preset) and the whole configuration it ran
    default = json.loads(json.dumps(presets.get(presets.DEFAULT).config.to_dict()))
    assert summary["preset"] == presets.DEFAULT and summary["config"] == default
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
        # the walls' frame: its error and its guide's std (the default preset observes it)
        frame_error, frame_std = float(z["frame_error"]), float(z["frame_std"])
    assert abs(frame_error) < 0.01 and 5e-5 < frame_std < 0.05  # a std (rad), not a variance
    frame = abs(frame_error) / frame_std
    assert summary["online"]["frame_std_median"] == pytest.approx(frame_std)
    assert summary["online"]["frame_error_over_std_median"] == pytest.approx(frame)
    assert summary["online"]["std_over_error_median"] > 0
    assert summary["online"]["std_over_aligned_error_median"] > 0
    # diagnostic: the error left after a rigid alignment of each trajectory to the truth
    assert 0 <= summary["online"]["aligned_final_mean"] < 0.05
    assert 0 <= summary["online"]["aligning_rotation_abs_mean"] < 0.1
    stamp = runs[0].stat().st_mtime_ns
    run("slam_accuracy", *args)  # finished runs are reused, not recomputed
    assert runs[0].stat().st_mtime_ns == stamp
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    # another configuration into the same folder stops before any run is reused or recomputed
    err = bench("slam_accuracy", *args, "--config", '{"filter": {"particles": 64}}')
    assert err.returncode == 1 and "config.json: this output folder holds runs" in err.stderr
    assert "differs in config.filter.particles" in err.stderr
    assert runs[0].stat().st_mtime_ns == stamp
    # the diagnostic: the map learned at the true poses; its runs are kept apart
    run("slam_accuracy", *args, "--map-poses", "true")
    oracle = json.loads((tmp_path / "summary.json").read_text())
    assert oracle["map_poses"] == "true" and summary["map_poses"] == "filter"
    assert 0 <= oracle["online"]["final_mean"] < 0.05
    assert oracle["online"]["final_mean"] != summary["online"]["final_mean"]
    assert len(list((tmp_path / "runs").glob("online_map-true_*.npz"))) == 1
    # the default seeds each maze's own actuation noise; the draw shared by the mazes of a
    # traversal (--no-per-maze-noise) is another traversal of the same maze, kept apart
    assert summary["per_maze_noise"] and runs[0].name.startswith("online_pn_")
    run("slam_accuracy", *args, "--no-per-maze-noise")
    shared = json.loads((tmp_path / "summary.json").read_text())
    assert not shared["per_maze_noise"]
    f = tmp_path / "runs" / "online_m1001_t1_T40.npz"
    assert f.is_file() and runs[0].name == "online_pn_m1001_t1_T40.npz"
    with np.load(f) as a, np.load(runs[0]) as b:
        assert np.abs(a["truth"] - b["truth"]).max() > 1e-4
        assert np.array_equal(a["truth"][0], b["truth"][0])  # same start pose
    # a held-out tuning maze instead of the test mazes: its own run file and summary
    run("slam_accuracy", *args, "--maze-seeds", "991")
    tuned = json.loads((tmp_path / "summary.json").read_text())
    assert tuned["mazes"] == [991] and tuned["runs_per_mode"] == 1
    assert (tmp_path / "runs" / "online_pn_m991_t1_T40.npz").is_file()
    assert 0 <= tuned["online"]["final_mean"] < 0.05
    # driver seeds as a list: the 24 runs can be split between machines
    assert args[2:4] == ("--traversals", "1")
    run("slam_accuracy", *args[:3], "2,", *args[4:])
    two = json.loads((tmp_path / "summary.json").read_text())
    assert two["runs_per_mode"] == 1
    assert (tmp_path / "runs" / "online_pn_m1001_t2_T40.npz").is_file()
    assert two["online"]["final_mean"] != summary["online"]["final_mean"]
    # the paper's model (shipped emission MLP and learned transition) into its own folder
    paper = tmp_path / "paper"
    run("slam_accuracy", *args[:-1], str(paper), "--preset", "paper")
    p = json.loads((paper / "summary.json").read_text())
    assert p["preset"] == "paper" and p["config"]["emission"]["kind"] == "mlp"
    assert p["config"]["transition"]["kind"] == "learned"
    assert 0 <= p["online"]["final_mean"] < 0.05
    assert p["online"]["final_mean"] != summary["online"]["final_mean"]


def test_slam_accuracy_names_a_bad_preset_or_configuration_and_exits_2(tmp_path):
    out = ("--out", str(tmp_path))
    err = bench("slam_accuracy", "--preset", "nope", *out, timeout=60)
    assert err.returncode == 2 and "--preset: invalid choice: 'nope'" in err.stderr
    assert "raycast" in err.stderr  # the choices are listed
    for config, msg in [
        ('{"filter": {"particles": -5}}', "filter.particles must be a positive integer, got -5"),
        ('{"filter": {"particle": 5}}', "unknown field filter.particle"),
        ('{"filter": ', "not JSON"),
        ("[1]", "must be a JSON object"),
    ]:
        err = bench("slam_accuracy", "--config", config, *out, timeout=60)
        assert err.returncode == 2, err.stderr
        # one line: the parser's error naming the problem
        last = err.stderr.strip().splitlines()[-1]
        assert last.startswith("python -m benchmarks.slam_accuracy: error: --config: ")
        assert msg in last
    err = bench("slam_accuracy", "--preset", "visual", *out, timeout=60)
    assert err.returncode == 2 and "--preset visual: a camera emission" in err.stderr
    assert not (tmp_path / "runs").exists()  # nothing was started


@pytest.mark.parametrize("preset", [p.name for p in presets.PRESETS.values() if p.adapt is None])
def test_the_cli_and_the_benchmarks_choose_configurations_alike(preset):
    """One way to choose a configuration: the preset, a benchmark's own overrides, then the
    user's JSON; ``--preset X --config Y`` gives the CLI and the benchmarks the same model."""
    import argparse

    from benchmarks._common import slam_config
    from pyro_slam import cli
    from simulators import simulate_traversal

    text = '{"filter": {"particles": 7}, "emission": {"sigma": 0.07}}'
    tr = simulate_traversal("simple-small", steps=5, seed=0)
    args = argparse.Namespace(preset=preset, config=text, odometry_noise=None)
    name, config = cli._config(args, tr)
    assert name == preset
    assert config == slam_config(argparse.ArgumentParser(), preset, text)
    assert config.filter.particles == 7 and config.emission.sigma == 0.07
    base = {"filter": {"particles": 3, "lag": 5}}
    assert slam_config(argparse.ArgumentParser(), preset, text, base=base).filter.lag == 5
    assert slam_config(argparse.ArgumentParser(), preset, text, base=base).filter.particles == 7


def test_pin_cache_learns_the_map_at_the_given_poses_and_writes_the_scans_there():
    import torch

    from benchmarks._diagnostics import pin_cache
    from benchmarks.slam_accuracy import _traversal
    from pyro_slam.slam import SLAM, presets, with_overrides

    T = 12
    tr = _traversal(1001, 1, T, per_maze_noise=True)
    small = {"filter": {"particles": 16}, "training": {"particles": 4}}
    slam = SLAM(tr, with_overrides(presets.get("raycast").config, small), seed=1)
    poses = tr.poses + np.array([0.02, -0.01, 0.05])  # off the truth, off the filter's poses
    with pytest.raises(ValueError, match=r"shape \(12, 3\)"):
        pin_cache(slam, poses[:5])
    pin_cache(slam, poses, noise=1e-3, seed=0)
    slam.run("online", progress=False)
    # every store (filter and ELBO chunks) wrote the pinned poses plus 1e-3 noise
    assert bool(slam.cache.filled.all())
    z = slam.cache.z.double().numpy()  # [T, 50, 3]
    np.testing.assert_allclose(z.mean(1), poses, atol=1e-3)
    assert 5e-4 < z.std(1).mean() < 2e-3
    # scan insertion placed each scan at its pinned pose
    assert slam.mask is None
    fresh = SLAM(tr, with_overrides(presets.get("raycast").config, small), seed=1).inserter
    for t in range(T):
        valid = torch.ones_like(slam.obs[t], dtype=torch.bool)
        fresh.insert(slam.obs[t], valid, torch.as_tensor(poses[t], dtype=slam.obs.dtype))
    assert bool(fresh.inserted.any())
    for key, value in fresh.state_dict().items():
        if key != "placement":  # (the run placed each scan with its pose's variance)
            assert torch.equal(slam.inserter.state_dict()[key], value), key


@pytest.mark.slow
def test_exploration_benchmark_same_curves_serial_and_parallel(tmp_path):
    args = (
        *("--scales", "simple-small", "--seeds", "2", "--step-fraction", "0.02"),
        *("--ars-iterations", "1", "--ars-directions", "2", "--ars-mazes", "1"),
        *("--ars-steps", "10", "--horizon", "10"),
    )
    out = {}
    for workers in (1, 2):
        d = tmp_path / f"w{workers}"
        run("exploration", *args, "--workers", str(workers), "--out", str(d))
        out[workers] = json.loads((d / "exploration.json").read_text())
        assert (d / "exploration_curves.png").stat().st_size > 10_000
    a, b = out[1], out[2]
    # a re-run resumes: PEMA and the 6 finished runs are loaded, not recomputed (same timings)
    assert len(list((tmp_path / "w1" / "runs").glob("*.json"))) == 6
    assert (tmp_path / "w1" / "pema.pt").exists()
    run("exploration", *args, "--workers", "1", "--out", str(tmp_path / "w1"))
    again = json.loads((tmp_path / "w1" / "exploration.json").read_text())
    assert again["curves"] == a["curves"] and again["final"] == a["final"]
    assert again["ars"]["seconds"] == a["ars"]["seconds"]
    assert a["config"]["plan"]["horizon"] == 10 and a["steps"] == {"simple-small": 30}
    assert a["config"]["plan"]["execute_steps"] == 25  # the reduced budget's
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
    run("exploration", *args, *one, "--out", str(tmp_path / "s0"))
    run("exploration", *args, *one, "--first-seed", "1", "--out", str(tmp_path / "s1"))
    parts = [str(tmp_path / d / "exploration.json") for d in ("s0", "s1")]
    run("exploration", "--merge", *parts, "--out", str(tmp_path / "m"))
    m = json.loads((tmp_path / "m" / "exploration.json").read_text())
    assert m["seeds"] == 2 and m["curves"] == a["curves"]
    for agent in ("mi", "pema", "random"):
        fa, fm = a["final"]["simple-small"][agent], m["final"]["simple-small"][agent]
        assert fm["ratio_mean"] == pytest.approx(fa["ratio_mean"]) and fm["seeds"] == 2
        assert fm["infogain_std"] == pytest.approx(fa["infogain_std"])


def test_exploration_benchmark_plan_flags_are_checked(tmp_path):
    for flags, field in (
        (("--horizon", "1"), "horizon"),
        (("--execute-steps", "-1"), "execute_steps"),
    ):
        err = bench("exploration", *flags, "--out", str(tmp_path), timeout=60)
        assert err.returncode == 2, err.stderr[-2000:]
        assert f"--horizon / --execute-steps: explore.plan.{field} must be" in err.stderr
    assert not any(tmp_path.iterdir())


def test_navigation_benchmark_summarises_learned_truth_and_observation_targets(tmp_path):
    args = (
        "--mazes",
        "1",
        "--pairs-limit",
        "2",
        "--traversal-steps",
        "300",
        "--emission-steps",
        "30",
        "--fit-steps",
        "30",
        "--sleep-steps",
        "30",
        "--inverse-steps",
        "10",
        "--max-expansions",
        "60",
        "--out",
        str(tmp_path),
    )
    out = last_json(run("navigation", *args))
    s = json.loads((tmp_path / "summary.json").read_text())
    assert "args" not in out and out["per_maze"] == s["per_maze"] and out["pairs"] == s["pairs"]
    # the headline figures come first, by name
    assert list(out)[:6] == [
        "obs_failure_ratio_obs_space",
        "obs_failure_ratio_position_unaliased",
        "unaliased_targets",
        "pose_success_ratio_known_pose_map",
        "pose_success_ratio_slam_map",
        "wall_s",
    ]
    assert s["pairs"] == 2 and s["budgets"][-1] == 60 and s["map_poses"] == "true"
    assert s["slam_preset"] is None and s["slam_config"] is None  # mapped at the true poses
    assert s["pose_success_ratio_slam_map"] is None and s["wall_s"] > 0
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
    # on targets without an exact look-alike 0.05 away and below 1 on the others; an exact
    # look-alike is a look-alike within --alias-tol too
    for t in targets:
        assert t["gt_inverse_diff"] < 1e-6
        assert (t["oracle_failure"] > 0) == (t["lookalikes_exact"] > 0) and t["oracle_failure"] < 1
        assert t["lookalikes_tol"] >= t["lookalikes_exact"]
        assert t["aliased"] == (t["lookalikes_tol"] > 0)
    assert inv["lookalike_exact"] == np.mean([t["lookalikes_exact"] > 0 for t in targets])
    assert 0 <= s["obs_oracle_expected_failure"] <= s["obs_target_aliased_exact"]
    assert (tmp_path / "navigation.png").stat().st_size > 10_000
    # one observation-target run drawn per maze: plan over the belief next to its execution
    assert (tmp_path / "plots" / "m1001_obs.png").stat().st_size > 10_000
    assert s["resumed_mazes"] == []
    # observation runs judged in observation space too: reaching the target counts as reaching
    # its observation, so that failure ratio can only be lower
    obs = [r for r in runs if r["planner"] == "learned_obs"]
    for r in (r for r in runs if r["planner"].endswith("_obs")):
        for nz in ("noiseless", "noisy"):
            assert r[f"scan_diff_{nz}"] >= 0
            assert r[f"scan_success_{nz}"] >= r[f"success_{nz}"]
            if r[f"success_{nz}"]:  # the target is within the radius, up to the search's grid
                assert r[f"scan_diff_{nz}"] < 0.01
    assert s["obs_failure_ratio_obs_space"] <= s["obs_failure_ratio_position"]
    by_tol = s["obs_failure_ratio_obs_space_by_tol"]  # a looser tolerance forgives more
    assert list(by_tol) == ["0.0025", "0.005", "0.01"]
    assert by_tol["0.01"] == s["obs_failure_ratio_obs_space"]
    assert list(by_tol.values()) == sorted(by_tol.values(), reverse=True)
    # the counts behind the ratios
    c = s["per_maze"]
    assert set(c) == {"1001", "all"} and c["all"] == c["1001"] and c["all"]["pairs"] == 2
    if c["all"]["gt_solved"]:
        assert (
            s["pose_success_ratio_known_pose_map"]
            == c["all"]["learned_on_gt_solved"] / c["all"]["gt_solved"]
        )
    assert s["obs_failure_ratio_position"] == c["all"]["obs_missed"] / 2
    assert s["obs_failure_ratio_obs_space"] == c["all"]["obs_missed_scan"] / 2
    assert s["ground_truth_obs_failure_ratio_position"] == c["all"]["gt_obs_missed"] / 2
    assert s["unaliased_targets"] == c["all"]["obs_unaliased"]
    assert s["unaliased_targets"] == sum(r["target_lookalikes_tol"] == 0 for r in obs)
    if s["unaliased_targets"]:
        assert (
            s["obs_failure_ratio_position_unaliased"]
            == c["all"]["obs_unaliased_missed"] / c["all"]["obs_unaliased"]
        )
    # a second run resumes from the finished maze: the same rows, timings included
    run("navigation", *args)
    assert json.loads((tmp_path / "runs.json").read_text()) == runs
    assert json.loads((tmp_path / "summary.json").read_text())["resumed_mazes"] == [1001]
    # the pairs are those maze_pairs draws for this maze whichever mazes run; a share named by
    # --maze-seeds has the same settings, so it resumes the maze as well
    from benchmarks.navigation import maze_pairs

    drawn = maze_pairs(2, 0)
    assert len(drawn[1001]) == 2 and len(maze_pairs(0, 0)[1002]) == 25 * 24  # 5 x 5 grid
    assert maze_pairs(2, 0) == drawn and maze_pairs(2, 1) != drawn
    assert set(drawn) == {1001, 1002, 1003, 1004, 1005, 1006, 991, 992, 993, 994, 995, 996}
    assert {(r["start"], r["goal"]) for r in runs} == set(drawn[1001])
    run("navigation", *args[2:], "--maze-seeds", "1001")
    assert json.loads((tmp_path / "summary.json").read_text())["resumed_mazes"] == [1001]
    assert json.loads((tmp_path / "runs.json").read_text()) == runs


@pytest.mark.slow
def test_navigation_workers_give_the_rows_of_a_serial_run(tmp_path):
    """``--workers 2``: the mazes run in two processes, each maze's rows the same as when the
    mazes run one after the other in one process (the fits are seeded per maze)."""
    args = (
        "--maze-seeds",
        "1002,1001",
        "--pairs-limit",
        "1",
        "--traversal-steps",
        "300",
        "--emission-steps",
        "30",
        "--fit-steps",
        "30",
        "--sleep-steps",
        "30",
        "--inverse-steps",
        "10",
        "--max-expansions",
        "60",
    )
    rows = {}
    for workers in ("1", "2"):
        out = tmp_path / workers
        run("navigation", *args, "--workers", workers, "--out", str(out))
        runs = json.loads((out / "runs.json").read_text())
        rows[workers] = [{k: v for k, v in r.items() if k != "plan_s"} for r in runs]
    assert [r["maze"] for r in rows["2"]] == [1002] * 4 + [1001] * 4  # in the order asked
    assert rows["1"] == rows["2"]


@pytest.mark.parametrize(
    "args, message",
    [
        (("--maze-seeds", "1002,7"), "--maze-seeds [7]: not test mazes"),
        (("--quick", "--mazes", "3"), "--quick sets --mazes 2 and --pairs-limit 10"),
        (("--quick", "--pairs-limit", "5"), "--quick sets --mazes 2 and --pairs-limit 10"),
        (("--pairs-limit", "601"), "--pairs-limit 601: must be 0 to 600"),
        (("--mazes", "7"), "--mazes 7: must be 1 to 6"),
        (("--workers", "0"), "--workers 0: must be at least 1"),
        (("--alias-tol", "0"), "--alias-tol and --exact-tol must be positive"),
    ],
)
def test_navigation_bad_arguments_exit_2_with_one_line(args, message):
    err = bench("navigation", *args, "--out", "/nonexistent/never", timeout=60)
    assert err.returncode == 2 and message in err.stderr
    assert "Traceback" not in err.stderr


def test_navigation_headline_names_the_pose_ratio_by_the_map_planned_in():
    """The headline is :func:`~pyro_slam.planning.evaluation.success_ratios` with the pose
    targets' ratio under the name of the map the learned planner planned in."""
    from benchmarks.navigation import headline
    from pyro_slam.planning.evaluation import success_ratios

    def row(goal, planner, ok, **kw):
        return {
            "maze": 1001,
            "start": 0,
            "goal": goal,
            "planner": planner,
            "found": True,
            "success_noiseless": ok,
            **kw,
        }

    runs = [
        *(row(g, "ground_truth", True) for g in (1, 2)),
        row(1, "learned", True),
        row(2, "learned", False),
        row(1, "learned_obs", False, scan_success_noiseless=True, target_lookalikes_tol=0),
    ]
    assert success_ratios(runs)["pose_success_ratio"] == 0.5
    assert headline(runs, "slam") == {
        "obs_failure_ratio_obs_space": 0.0,
        "obs_failure_ratio_position_unaliased": 1.0,
        "unaliased_targets": 1,
        "pose_success_ratio_known_pose_map": None,
        "pose_success_ratio_slam_map": 0.5,
    }
    assert headline(runs, "true")["pose_success_ratio_known_pose_map"] == 0.5
    assert headline(runs, "true")["pose_success_ratio_slam_map"] is None


def test_navigation_benchmark_maps_at_slam_poses(tmp_path):
    # --map-poses slam: emission and q(M) are fitted at the pose means of online SLAM on the
    # mapping traversal; the SLAM run's error is reported per maze
    args = (
        "--mazes",
        "1",
        "--pairs-limit",
        "1",
        "--traversal-steps",
        "200",
        "--no-cover-grid",
        "--emission-steps",
        "20",
        "--fit-steps",
        "20",
        "--sleep-steps",
        "20",
        "--inverse-steps",
        "5",
        "--max-expansions",
        "30",
        "--map-poses",
        "slam",
        "--out",
        str(tmp_path),
    )
    run("navigation", *args)
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["args"]["map_poses"] == "slam" and s["pairs"] == 1
    # the SLAM run: the paper's model by default (--slam-preset, --slam-config)
    assert s["slam_preset"] == "paper" and s["slam_config"]["emission"]["kind"] == "mlp"
    err = s["inverse"]["slam_error"]["1001"]
    # 200 steps: both estimates stay within a few cells of the truth
    assert 0 < err["mean"] <= err["max"] < 0.1 and 0 <= err["pi_final"] < 0.1
    targets = json.loads((tmp_path / "targets.json").read_text())
    assert {t["traversal_steps"] for t in targets} == {200}
    # the SLAM run's poses are kept for the maze, under its configuration and traversal
    kept = json.loads((tmp_path / "mazes" / "slam_m1001.json").read_text())
    assert len(kept["poses"]) == 200 and kept["summary"] == err
    assert kept["key"]["slam_config"] == s["slam_config"] and kept["key"]["steps"] == 200
    err = bench("navigation", *args, "--slam-config", '{"heading": {"support": 1}}', timeout=60)
    assert err.returncode == 2 and "--slam-config: heading.support must be" in err.stderr
    err = bench("navigation", *args, "--slam-preset", "nope", timeout=60)
    assert err.returncode == 2 and "--slam-preset: invalid choice: 'nope'" in err.stderr


def test_navigation_reuses_kept_slam_poses_only_for_the_same_run(tmp_path):
    """``_slam_poses`` returns the poses kept in ``OUT/mazes/slam_m<seed>.json`` when the SLAM
    configuration and the traversal match, without running SLAM."""
    from types import SimpleNamespace

    from benchmarks.navigation import _slam_poses
    from pyro_slam.slam import presets
    from simulators import make_maze

    args = SimpleNamespace(out=tmp_path, traversal_steps=50, slam=presets.get("paper").config)
    (tmp_path / "mazes").mkdir()
    key = {"slam_config": args.slam.to_dict(), "steps": 50, "seed": 1, "cover_grid": False}
    fake = np.full((50, 3), 0.25)
    f = tmp_path / "mazes" / "slam_m991.json"
    f.write_text(
        json.dumps(
            {"key": json.loads(json.dumps(key)), "poses": fake.tolist(), "summary": {"mean": -1.0}}
        )
    )
    tr, poses, summary = _slam_poses(make_maze("moderate-medium", 991), 991, None, args)
    assert len(tr.poses) == 50 and np.array_equal(poses, fake) and summary == {"mean": -1.0}


@pytest.mark.slow
def test_visual_slam_benchmark_summarises_mazes_and_resumes(tmp_path):
    from pyro_slam.metrics import localisation_error

    args = (
        "--mazes",
        "2",
        "--steps",
        "60",
        "--pretrain-steps",
        "5",
        "--pretrain-traversal",
        "100",
        "--workers",
        "2",
        "--config",
        '{"offline": {"svi_steps": 10}}',
        "--out",
        str(tmp_path),
    )
    out = last_json(run("visual_slam", *args))
    s = json.loads((tmp_path / "summary.json").read_text())
    assert out == s and s["steps"] == 60 and s["mazes"] == [1001, 1002]
    # the preset (default: visual) and the whole configuration it ran, with the overrides and
    # the kinematic sigma_T scaled with the actuation noise (--odometry-scale, default 0.57)
    assert s["preset"] == "visual" and s["config"]["emission"]["kind"] == "image_mlp"
    assert s["config"]["offline"] == {"rounds": 2, "svi_steps": 10, "estimate": "forward"}
    sigma = np.array([5e-4, 5e-4, 8e-3])
    assert s["config"]["transition"]["sigma"] == pytest.approx(0.57 * sigma)
    recorded = json.loads((tmp_path / "config.json").read_text())["config"]  # before the scaling
    assert recorded["transition"]["sigma"] == pytest.approx(sigma)
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
        np.testing.assert_allclose(
            localisation_error(z["estimate"], z["truth"]), z["slam"], atol=1e-5
        )
        np.testing.assert_allclose(
            localisation_error(z["pi_poses"], z["truth"]), z["pi"], atol=1e-5
        )
    run("visual_slam", *args)  # resumes: the finished runs are not recomputed
    assert [f.stat().st_mtime_ns for f in runs] == stamps
    assert json.loads((tmp_path / "summary.json").read_text())["offline"] == s["offline"]
    # the diagnostic: the map learned at the true poses, stored apart; the emission is reused;
    # --maze-seeds picks one maze (here a held-out tuning maze)
    # --odometry-scale: the traversal is driven with scaled actuation noise, stored apart
    run(
        "visual_slam",
        *args[:-2],
        "--maze-seeds",
        "997",
        "--map-poses",
        "true",
        "--workers",
        "1",
        "--odometry-scale",
        "0.5",
        "--out",
        str(tmp_path),
    )
    o = json.loads((tmp_path / "summary.json").read_text())
    assert o["map_poses"] == "true" and s["map_poses"] == "filter" and o["mazes"] == [997]
    # the default: the paper's path-integration level (the calibrated scale), in the names
    assert o["odometry_scale"] == 0.5 and s["odometry_scale"] == 0.57
    assert all("_od0.57_pn" in f.name for f in runs)
    assert 0 <= o["offline"]["per_maze"][0] < 1
    (f,) = (tmp_path / "runs").glob("m997_map-true_*.npz")
    assert f.name == "m997_map-true_od0.5_pn_T60.npz"
    from benchmarks.visual_slam import _traversal

    with np.load(f) as z:
        kw = {"images": False, "per_maze_noise": True}
        np.testing.assert_allclose(z["truth"], _traversal(997, 1, 60, 0.5, **kw).poses, atol=1e-6)
        assert np.abs(z["truth"] - _traversal(997, 1, 60, **kw).poses).max() > 1e-4
    # another configuration into the same folder stops before anything is recomputed or lost
    other = '{"offline": {"svi_steps": 11}}'
    err = bench("visual_slam", *args[:-4], "--config", other, "--out", str(tmp_path))
    assert err.returncode == 1 and "config.json: this output folder holds runs" in err.stderr
    assert "differs in config.offline.svi_steps" in err.stderr
    err = bench("visual_slam", *args[:-4], "--preset", "visual-raycast", "--out", str(tmp_path))
    assert err.returncode == 1 and "config.emission.kind" in err.stderr
    assert [f.stat().st_mtime_ns for f in runs] == stamps
    err = bench("visual_slam", "--maze-seeds", "1002,7", "--out", str(tmp_path))
    assert err.returncode == 2 and "--maze-seeds [7]: not test mazes" in err.stderr
    assert "or tuning mazes [997, 998]" in err.stderr
    err = bench("visual_slam", "--odometry-scale", "0")
    assert err.returncode == 2 and "--odometry-scale must be > 0, got 0.0" in err.stderr
    # a LiDAR preset or a bad override is a usage error
    err = bench("visual_slam", "--preset", "raycast")
    assert err.returncode == 2 and "--preset raycast: a LiDAR emission" in err.stderr
    err = bench("visual_slam", "--config", '{"training": {"chunks": 0}}')
    assert err.returncode == 2 and "training.chunks must be a positive integer" in err.stderr


def test_visual_slam_calibrates_the_odometry_noise_to_the_papers_path_integration():
    from benchmarks.visual_slam import PAPER_PI, _traversal, calibrate_odometry, scaled_config
    from pyro_slam.slam import SLAMConfig, with_overrides

    res = calibrate_odometry(400, seeds=(900, 901, 902), rounds=1, per_maze_noise=True)
    assert res["target"] == PAPER_PI == 0.11 and res["mazes"] == [900, 901, 902]
    base, refined = res["points"]
    assert base["scale"] == 1.0 and refined["scale"] == round(PAPER_PI / base["mean"], 2)
    best = min(res["points"], key=lambda q: abs(q["mean"] - PAPER_PI))
    assert res["at_scale"] == best and res["scale_for_target"] == best["scale"]
    # path integration drifts about in proportion to the noise
    ratio = refined["mean"] / base["mean"]
    assert 0.5 * refined["scale"] < ratio < 1.5 * refined["scale"]
    base = with_overrides(SLAMConfig(), {"transition": {"sigma": [1e-3, 2e-3, 8e-3]}})
    cfg = scaled_config(base, 0.5)
    assert cfg.transition.sigma == pytest.approx((5e-4, 1e-3, 4e-3))
    assert cfg.transition.scale == base.transition.scale and cfg.filter == base.filter
    # per-maze noise: the mazes' heading drifts differ; with the shared noise they do not
    # (the rotation noise is added whatever the controls)

    def drift(maze, per_maze):
        tr = _traversal(maze, 1, 300, images=False, per_maze_noise=per_maze)
        return tr.metadata["noise_seed"], np.diff(tr.poses[:, 2]) - tr.controls[:, 0]

    (seed_a, a), (_, b) = drift(900, False), drift(901, False)
    assert seed_a is None and np.allclose(np.angle(np.exp(1j * (a - b))), 0, atol=1e-6)
    (seed_a, a), (_, b) = drift(900, True), drift(901, True)
    assert seed_a == [1, 900] and not np.allclose(np.angle(np.exp(1j * (a - b))), 0, atol=1e-3)


def test_compare_runs_pairs_the_runs_both_outputs_share(tmp_path):
    T = 50
    for out, finals in (("a", [0.02, 0.04, 0.10]), ("b", [0.03, 0.06, 0.08, 0.5])):
        (tmp_path / out / "runs").mkdir(parents=True)
        for i, f in enumerate(finals):
            slam = np.linspace(0, f, T)
            np.savez(
                tmp_path / out / "runs" / f"offline_m{1001 + i}_t1_T{T}.npz",
                slam=slam,
                pi=np.full(T, 0.07),
            )
    out = last_json(
        run("compare_runs", str(tmp_path / "a"), str(tmp_path / "b"), "--glob", "offline_*.npz")
    )
    assert out["runs"] == 3 and out["a"]["all_runs"] == 3 and out["b"]["all_runs"] == 4
    assert out["a"]["final_mean"] == pytest.approx(0.16 / 3)
    assert out["a"]["runs_under_0.05"] == 2 and out["a"]["runs_beating_pi"] == 2
    assert out["b"]["final_mean"] == pytest.approx(0.17 / 3)  # the shared runs only
    d = np.array([-0.01, -0.02, 0.02])
    assert out["paired_final"]["mean"] == pytest.approx(d.mean())
    assert out["paired_final"]["se"] == pytest.approx(d.std(ddof=1) / np.sqrt(3))
    assert out["paired_final"]["a_lower"] == 2
    assert out["paired_time_avg"]["mean"] == pytest.approx(d.mean() / 2)
    err = bench("compare_runs", str(tmp_path / "a"), str(tmp_path / "b"), "--glob", "online_*.npz")
    assert err.returncode == 2 and "no runs matching 'online_*.npz'" in err.stderr


def test_aliasing_summary_splits_moved_and_kept_points_and_a_bad_sensor_exits_2():
    """The per-target look-alikes (:func:`pyro_slam.planning.evaluation.aliasing`) are
    summarised per maze and over all; a sensor that is not BEAMSxRANGE is a usage error."""
    from benchmarks.aliasing import _summary

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
    err = bench("aliasing", "--sensors", "20-0.5", timeout=60)
    assert err.returncode == 2 and "sensor '20-0.5': expected BEAMSxRANGE" in err.stderr


def test_reliability_runs_the_preset_with_fewer_particles_and_reports_bad_input(tmp_path):
    from benchmarks.reliability import SMALL, bad_input_cases, nan_free
    from pyro_slam.slam import presets, with_overrides

    config = with_overrides(presets.get("raycast").config, SMALL)
    assert config.filter.particles == 64 and config.training.chunks == 4
    out = nan_free(config, seeds=1, steps=12)
    assert out == {"runs": 1, "steps": 12, "all_finite": True, "finite": [True]}
    cases = bad_input_cases(tmp_path)
    assert len(cases) == 10 and all(c["raised"] for c in cases)


def test_pfnet_table_smoke_prints_the_rmse_table_as_json(tmp_path):
    out = last_json(run("pfnet_table", "--smoke", "--no-progress", "--out", str(tmp_path)))
    rm = out["rmse_cm"]
    assert rm == json.loads((tmp_path / "pfnet_table.json").read_text())["rmse_cm"]
    assert "Beam-model PF, K=300|walls only|lidar" in rm and "LSTM network|distractors|depth" in rm
    assert all(math.isfinite(v) and v > 0 for v in rm.values())


def test_real_data_rows_over_seeds_are_means_with_std_and_the_worst_seed():
    from benchmarks.real_data import over_seeds, seed_table

    def row(sc, path, reason=None):
        c = {"mean": sc, "points": 100, "cap": 1.0} | ({"reason": reason} if reason else {})
        return {"scan_consistency": c, "path_length_m": path, "seconds_per_scan": 0.5}

    runs = {0: row(0.04, 10.0), 1: row(0.08, 12.0), 2: row(0.06, 14.0)}
    out = over_seeds(runs, ("scan_consistency", "mean"))
    assert out["scan_consistency"]["mean"] == pytest.approx(0.06)  # the rows' keys, as means
    assert out["path_length_m"] == pytest.approx(12.0)
    assert out["scan_consistency"]["points"] == 100 and out["scan_consistency"]["cap"] == 1.0
    assert isinstance(out["scan_consistency"]["points"], int)  # a shared count stays a count
    assert out["std"]["path_length_m"] == pytest.approx(2.0)  # sample std
    assert out["std"]["scan_consistency"]["mean"] == pytest.approx(0.02)
    assert out["worst"]["seed"] == 1 and out["worst"]["value"] == 0.08
    assert out["worst"]["by"] == "scan_consistency.mean"
    assert out["worst"]["per_seed"] == {"0": 0.04, "1": 0.08, "2": 0.06}
    assert out["seeds"] == [0, 1, 2]
    one = over_seeds({3: row(0.05, 9.0)}, ("scan_consistency", "mean"))
    assert one["path_length_m"] == 9.0 and one["std"]["path_length_m"] == 0.0
    assert one["worst"]["seed"] == 3
    # a figure undefined in one run (a short log) is undefined over the seeds
    short = over_seeds({0: row(0.05, 9.0), 1: row(None, 9.0, "too short")}, ("x",))
    assert short["scan_consistency"]["mean"] is None and short["scan_consistency"]["reason"] is None
    assert short["worst"] == {
        "seed": None,
        "by": "x",
        "value": None,
        "per_seed": {"0": None, "1": None},
    }
    table = seed_table({"mit-csail": {"DVBF-LM": out}, "intel": {}})
    assert table == [
        "mit-csail DVBF-LM, 3 seeds: scan consistency 0.06 ± 0.02 m, path 12 ± 2 m, "
        "s/scan 0.5 ± 0; worst scan_consistency.mean 0.08 (seed 1)"
    ]


@pytest.mark.slow
@pytest.mark.skipif(
    not (REPO.parent / "shared" / "data" / "intel.gfs.log").is_file(),
    reason="the real laser logs (../shared/data) are not here",
)
def test_real_data_runs_the_real_preset_on_both_logs(tmp_path):
    args = ("--steps", "30", "--no-mrpt", "--img", str(tmp_path / "img"), "--out", str(tmp_path))
    fast = ("--config", '{"offline": {"svi_steps": 5}}')
    out = last_json(run("real_data", *args, *fast, "--seeds", "2"))
    assert out == json.loads((tmp_path / "real_data.json").read_text())
    assert out["preset"] == "real" and out["steps"] == 30
    # the preset is adapted per log: every k-th beam of the 361 (CARMEN) and 180 (Intel)
    assert out["config"]["mit-csail"]["beam_stride"] == 8
    assert out["config"]["intel"]["beam_stride"] == 4
    for log in ("mit-csail", "intel"):
        assert out[log]["DVBF-LM"]["path_length_m"] > 0
        assert (tmp_path / "img" / f"real_{log}.png").is_file()
    assert "ate_aligned" in out["intel"]["DVBF-LM"]
    # the headline figures come first and are read off the per-log rows
    head = list(out)[:8]
    assert head[:2] == ["intel_relation_error_trans_m", "intel_odometry_relation_error_trans_m"]
    intel, csail = out["intel"], out["mit-csail"]
    assert out["intel_relation_error_trans_m"] == intel["DVBF-LM"]["relation_error"]["trans_mean"]
    assert out["csail_scan_consistency_mean_m"] == csail["DVBF-LM"]["scan_consistency"]["mean"]
    assert out["csail_mrpt_scan_consistency_mean_m"] is None  # --no-mrpt
    assert csail["odometry"]["path_length_m"] == 0  # CSAIL's robot stands still at first
    assert out["csail_path_ratio"] is None
    ratio = intel["DVBF-LM"]["path_length_m"] / intel["odometry"]["path_length_m"]
    assert out["intel_path_ratio"] == pytest.approx(ratio)
    # offline SLAM on Intel, the log with reference poses
    offline = intel["DVBF-LM offline"]
    ratio = offline["path_length_m"] / intel["odometry"]["path_length_m"]
    assert out["intel_offline_path_ratio"] == pytest.approx(ratio)
    assert out["intel_offline_relation_error_trans_m"] == offline["relation_error"]["trans_mean"]
    assert "DVBF-LM offline" not in csail
    per_scan = [out[log]["DVBF-LM"]["seconds_per_scan"] for log in ("intel", "mit-csail")]
    assert min(per_scan) <= out["ms_per_scan"] / 1000 <= max(per_scan)
    # every DVBF-LM row over seeds 0 and 1: means, their spread and the worst seed
    assert out["seeds"] == 2 and csail["DVBF-LM"]["seeds"] == offline["seeds"] == [0, 1]
    worst = csail["DVBF-LM"]["worst"]
    assert (
        out["csail_scan_consistency_worst_m"] == worst["value"] == max(worst["per_seed"].values())
    )
    assert out["csail_scan_consistency_worst_m"] >= out["csail_scan_consistency_mean_m"]
    assert offline["worst"]["by"] == "relation_error.trans_mean"
    # the benchmark's scan consistency is the one pyro-slam slam writes for the same run
    for seed in (0, 1):
        row = json.loads((tmp_path / "runs" / f"mit-csail_online_seed{seed}.json").read_text())
        run_dir = tmp_path / f"mit-csail_dvbf_seed{seed}"
        written = json.loads((run_dir / "metrics.json").read_text())["scan_consistency"]["slam"]
        assert row["scan_consistency"] == written and written["beam_stride"] == 2
    # each (log, mode, seed) run is kept: a run with a third seed runs that seed alone
    kept = tmp_path / "runs" / "intel_offline_seed0.json"
    stamp = kept.stat().st_mtime_ns
    more = last_json(run("real_data", *args, *fast, "--seeds", "3"))
    assert (
        kept.stat().st_mtime_ns == stamp
        and (tmp_path / "runs" / "intel_offline_seed2.json").is_file()
    )
    assert more["seeds"] == 3 and more["intel"]["DVBF-LM"]["worst"]["per_seed"].keys() == {
        "0",
        "1",
        "2",
    }
    assert (
        more["intel"]["DVBF-LM"]["worst"]["per_seed"]["1"]
        == intel["DVBF-LM"]["worst"]["per_seed"]["1"]
    )
    other = bench("real_data", *args, "--seeds", "2", timeout=60)  # another configuration
    assert other.returncode == 1 and "another configuration" in other.stderr
    err = bench("real_data", *args, "--config", '{"filter": {"proposal": "best"}}', timeout=60)
    assert err.returncode == 2 and "filter.proposal must be one of" in err.stderr


def test_slam_speed_times_presets_and_another_commit_side_by_side():
    """Steps per second per preset and mode, a profile breakdown that sums to one, and the same
    traversal timed with another commit's ``pyro-slam slam`` (here HEAD itself, through its
    --config format)."""
    args = [
        "--presets",
        "raycast",
        "--modes",
        "online",
        "--steps",
        "40",
        "--profile-steps",
        "20",
        "--threads",
        "1",
        "--against",
        "HEAD",
        "--against-config",
        '{"filter": {"particles": 128}}',
    ]
    out = last_json(run("slam_speed", *args))
    row = out["presets"]["raycast"]
    assert out["steps"] == 40 and row["online"]["steps_per_s"] > 0
    parts = row["breakdown_online"]
    assert set(parts) == {"filter", "svi", "insertion", "other"}
    assert abs(sum(parts.values()) - 1) < 0.01 and parts["filter"] > 0 and parts["svi"] > 0
    against = out["against"]
    assert against["rev"] == "HEAD" and against["online"]["wall_s"] > 0
    assert against["online"]["speedup"] == pytest.approx(
        against["online"]["wall_s"] / row["online"]["wall_s"], rel=0.05
    )
    bad = bench("slam_speed", "--presets", "nope")
    assert bad.returncode == 2 and "nope" in bad.stderr


def test_slam_speed_times_pyros_smcfilter_on_the_same_run():
    """``--smc``: the online run with Pyro's SMCFilter as the filter (the same model, proposal
    and weights) next to ours, timed and scored alike (30 steps stay well within 0.1 of the
    truth), with the heading factor too."""
    args = [
        "--presets",
        "manhattan",
        "--modes",
        "online",
        "--steps",
        "30",
        "--profile-steps",
        "10",
        "--threads",
        "1",
        "--smc",
    ]
    row = last_json(run("slam_speed", *args))["presets"]["manhattan"]
    for key in ("online", "online_smc"):
        assert row[key]["steps_per_s"] > 0 and 0 <= row[key]["final_error"] < 0.1


def test_navigation_benchmark_defaults_are_the_benchmark_preset():
    """The navigation benchmark's defaults are :data:`NAVIGATION_BENCHMARK`'s (its figures ran
    with them)."""
    from benchmarks.navigation import _parser
    from pyro_slam.planning import NAVIGATION_BENCHMARK

    args = _parser().parse_args([])
    for name in ("max_expansions", "traversal_steps", "fit_steps", "emission_steps", "n_world"):
        assert getattr(args, name) == getattr(NAVIGATION_BENCHMARK, name), name
    assert (args.max_std, args.hit_margin) == (
        NAVIGATION_BENCHMARK.max_std,
        NAVIGATION_BENCHMARK.hit_margin,
    )
    assert NAVIGATION_BENCHMARK.max_expansions == 1200


@pytest.mark.skipif(
    not (REPO.parent / "shared" / "data" / "intel.gfs.log").is_file(),
    reason="the real laser logs (../shared/data) are not here",
)
def test_offline_elbo_is_the_objective_on_the_whole_log_and_leaves_the_run_alone():
    """The whole-log ELBO of ``benchmarks.offline_elbo``: its KL is the map's analytic KL from
    the prior, the same random numbers give the same estimate at every call, and the run's
    cache and generator are left as they were (so the SVI steps between two evaluations are
    the run's own). A belief moved off the data scores lower."""
    import pyro
    import torch

    from benchmarks.offline_elbo import LOGS, traversal_elbo
    from benchmarks.real_data import DATA, log_config, noisy_odometry
    from pyro_slam.io import read_any
    from pyro_slam.slam import loop
    from pyro_slam.slam.runner import SLAM

    tr = noisy_odometry(read_any(DATA / LOGS["intel"])).slice(0, 40)
    slam = SLAM(tr, log_config(tr), seed=0, threads=1)
    c, st, data = slam.components, slam.state, slam.data
    with slam.scope():
        loop.online_sweep(c, st, data, progress=False)
        cache, gen = st.cache.z.clone(), st.gen.get_state()
        a, b = traversal_elbo(slam, 2), traversal_elbo(slam, 2)
        assert a == b and a["elbo"] == pytest.approx(a["data"] - a["kl"])
        assert torch.equal(st.cache.z, cache) and torch.equal(st.gen.get_state(), gen)
        torch.rand(3, generator=st.gen)  # the run's generators move on, as SVI steps move them
        torch.rand(3)
        assert traversal_elbo(slam, 2) == a
        assert c.elbo.cache is st.cache
        m = c.map_belief()
        kl = (0.5 * (m.loc**2 + m.scale**2 - 1) - m.scale.log()).sum()
        assert a["kl"] == pytest.approx(float(kl), rel=1e-4) and a["kl"] > 100
        pyro.param("map_loc").data.mul_(-1)  # walls where the scans saw free space
        assert traversal_elbo(slam, 2)["data"] < a["data"] - 1000


@pytest.mark.skipif(
    not (REPO.parent / "shared" / "data" / "intel.gfs.log").is_file(),
    reason="the real laser logs (../shared/data) are not here",
)
def test_likelihood_peak_finds_the_pose_the_map_was_fused_at():
    """``benchmarks.likelihood_peak``: under a map fused at Intel's reference poses the model's
    likelihood peaks within centimetres of them, and under the map fused at the poses moved
    8 cm along x the peak moves with it."""
    import torch

    from benchmarks.likelihood_peak import fused_at_reference, likelihood_peak
    from benchmarks.real_data import DATA, log_config, noisy_odometry
    from pyro_slam.io import read_any
    from pyro_slam.slam.runner import SLAM

    tr = noisy_odometry(read_any(DATA / "intel.gfs.log")).slice(0, 60)
    ref = torch.as_tensor(np.asarray(tr.poses), dtype=torch.float32)
    shift = torch.tensor([0.08, 0.0, 0.0])
    offsets = {}
    for moved in (False, True):
        slam = SLAM(tr, log_config(tr), seed=0, threads=1)
        fused_at_reference(slam, ref + shift if moved else ref)
        peaks = [likelihood_peak(slam, t, ref[t], 0.02, 0.01) - ref[t] for t in range(10, 60, 10)]
        offsets[moved] = torch.stack(peaks)  # [5, 3]
    assert offsets[False][:, :2].norm(dim=-1).max() < 0.05
    assert offsets[False][:, 2].abs().max() < 0.025
    moved = (offsets[True] - offsets[False]).mean(0)  # [3]
    assert moved[0] == pytest.approx(0.08, abs=0.02) and abs(moved[1]) < 0.02


@pytest.mark.skipif(
    not (REPO.parent / "shared" / "data" / "intel.gfs.log").is_file(),
    reason="the real laser logs (../shared/data) are not here",
)
def test_localisation_follows_the_fused_map_and_leaves_it_unchanged():
    """``benchmarks.likelihood_peak``'s localisation floor: the filter localises on the map as
    fused (nothing inserted), so a map fused at the poses moved 8 cm along x moves the smoothed
    trajectory 8 cm along x."""
    import torch

    from benchmarks.likelihood_peak import fused_at_reference, localise
    from benchmarks.real_data import DATA, log_config, noisy_odometry
    from pyro_slam.io import read_any
    from pyro_slam.slam.runner import SLAM

    tr = noisy_odometry(read_any(DATA / "intel.gfs.log")).slice(0, 60)
    ref = torch.as_tensor(np.asarray(tr.poses), dtype=torch.float32)
    means = {}
    for moved in (False, True):
        slam = SLAM(tr, log_config(tr), seed=0, threads=1)
        fused_at_reference(slam, ref + torch.tensor([0.08, 0.0, 0.0]) if moved else ref)
        before = slam.map_belief().loc.clone()
        means[moved] = localise(slam)["mean"]  # [60, 3]
        assert torch.equal(slam.map_belief().loc, before)
    moved = (means[True] - means[False])[20:, :2].mean(0)  # [2]
    assert moved[0] == pytest.approx(0.08, abs=0.02) and abs(moved[1]) < 0.02


def test_mrpt_runs_in_a_relative_output_folder(tmp_path, monkeypatch):
    """``real_data``'s MRPT row with ``--out`` given relative to the working directory (its
    tools run inside the row's folder, so the files are named from there)."""
    from benchmarks.real_data import mrpt_available, run_mrpt

    if mrpt_available() is not None:
        pytest.skip(mrpt_available())
    sys.path.insert(0, str(REPO / "tests" / "pyro_slam" / "support"))
    from synthetic_logs import room_log

    tr, poses = room_log(T=12)
    monkeypatch.chdir(tmp_path)
    est, wall = run_mrpt(tr, Path("out") / "room_mrpt")
    assert est.shape == (12, 3) and np.isfinite(est).all() and wall > 0
    assert (tmp_path / "out" / "room_mrpt" / "log.rawlog").is_file()
