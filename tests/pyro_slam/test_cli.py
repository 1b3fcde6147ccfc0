"""The ``pyro-slam`` command line: simulate -> slam -> resume, and bad input."""

import json

import numpy as np
import pytest

from pyro_slam import cli
from pyro_slam.data import load

TINY = json.dumps(
    {"filter": {"particles": 16}, "training": {"particles": 4, "chunks": 2, "chunk_length": 4}}
)


@pytest.fixture(scope="module")
def traversal(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "tr.npz"
    rc = cli.main(
        ["simulate", "--maze", "simple-small", "--steps", "30", "--seed", "3", "--out", str(out)]
    )
    assert rc == 0 and out.is_file() and out.with_suffix(".png").is_file()
    return out


def test_slam_writes_outputs_and_metrics(traversal, tmp_path, capsys):
    out = tmp_path / "run"
    rc = cli.main(["slam", str(traversal), "--out", str(out), "--config", TINY, "--seed", "1"])
    assert rc == 0
    for name in (
        "metrics.json",
        "slam.png",
        "error.png",
        "checkpoint.pt",
        "posterior.npz",
        "map.pgm",
        "map.yaml",
    ):
        assert (out / name).is_file(), name
    report = json.loads((out / "metrics.json").read_text())
    assert report["steps"] == 30 and report["mode"] == "online"
    # the default preset, with the overrides applied
    assert report["preset"] == "raycast" and report["config"]["filter"]["particles"] == 16
    assert report["config"]["emission"]["kind"] == "raycast"
    s, p = report["slam"], report["path_integration"]
    # a 30-step run cannot drift far: both errors are small and finite
    assert 0 <= s["final_error"] < 0.2 and 0 <= p["final_error"] < 0.2
    assert np.isfinite(s["ate"]["rmse"])
    post = np.load(out / "posterior.npz")
    assert post["pose_mean"].shape == (30, 3) and np.isfinite(post["pose_mean"]).all()
    tum = np.loadtxt(out / "trajectory_slam.tum")
    assert tum.shape == (30, 8)
    # the traversal's true poses, for evo_ape against trajectory_slam.tum
    true = np.loadtxt(out / "trajectory_true.tum")
    poses = load(traversal).poses
    np.testing.assert_allclose(true[:, 1:3], poses[:, :2], atol=1e-8)
    np.testing.assert_allclose(2 * np.arctan2(true[:, 6], true[:, 7]), poses[:, 2], atol=1e-8)
    assert "final error SLAM" in capsys.readouterr().out


def test_resume_of_finished_run_keeps_result(traversal, tmp_path):
    out = tmp_path / "run"
    args = ["slam", str(traversal), "--out", str(out), "--config", TINY]
    assert cli.main(args) == 0
    first = np.load(out / "posterior.npz")["pose_mean"]
    assert cli.main(args + ["--resume"]) == 0
    np.testing.assert_array_equal(np.load(out / "posterior.npz")["pose_mean"], first)


def test_a_run_never_replaces_another_runs_folder(traversal, tmp_path, capsys):
    """A second run into a finished run's folder is refused before any work and leaves every
    file as it was; --overwrite replaces the run (and removes its stale outputs); --resume with
    other settings is refused naming what differs."""
    out = tmp_path / "run"
    args = ["slam", str(traversal), "--out", str(out), "--config", TINY]
    assert cli.main(args) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert cli.main(args) == 2
    assert "not empty" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    other = '{"filter": {"particles": 8}}'
    assert cli.main(["slam", str(traversal), "--out", str(out), "--config", other, "--resume"]) == 2
    assert "filter.particles (16 in the checkpoint, 8 now)" in capsys.readouterr().err
    assert cli.main(args + ["--resume", "--mode", "offline"]) == 2
    assert "online run, not offline" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    (out / "map.png").write_bytes(b"stale")  # an output a simulated run does not write
    assert cli.main(args + ["--overwrite"]) == 0
    assert not (out / "map.png").exists() and (out / "metrics.json").is_file()
    mode = (out / "metrics.json").stat().st_mode & 0o777
    assert mode == 0o644 or mode & 0o600 == 0o600 and not mode & 0o022, oct(mode)


def test_bad_inputs_exit_2_with_message(traversal, tmp_path, capsys):
    assert cli.main(["slam", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "a")]) == 2
    assert "missing.npz" in capsys.readouterr().err
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file")
    assert cli.main(["slam", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "bad.npz" in capsys.readouterr().err
    out = str(tmp_path / "c")
    rc = cli.main(["slam", str(traversal), "--out", out, "--config", '{"nope": 1}'])
    assert rc == 2 and "nope" in capsys.readouterr().err
    bad_value = '{"filter": {"particles": -5}}'
    rc = cli.main(["slam", str(traversal), "--out", out, "--config", bad_value])
    assert rc == 2 and "filter.particles must be a positive integer" in capsys.readouterr().err
    rc = cli.main(["slam", str(traversal), "--out", str(tmp_path / "r"), "--resume"])
    assert rc == 2 and "checkpoint" in capsys.readouterr().err


@pytest.mark.slow
def test_demo_end_to_end(tmp_path):
    """`make demo` at reduced length: simulation, SLAM, plots and metrics (slow suite)."""
    out = tmp_path / "out"
    assert cli.main(["demo", "--out", str(out), "--steps", "400"]) == 0
    report = json.loads((out / "metrics.json").read_text())
    assert report["steps"] == 400
    for name in ("traversal.npz", "traversal.png", "slam.png", "error.png"):
        assert (out / name).is_file()
    # SLAM stays within a corridor width of the truth over 400 steps
    assert report["slam"]["final_error"] < 1 / 6


def test_slam_help_lists_the_presets(capsys):
    with pytest.raises(SystemExit):
        cli.main(["slam", "--help"])
    out = capsys.readouterr().out
    assert "--preset" in out
    for name in ("paper", "raycast", "manhattan", "visual", "real"):
        assert name in out


def test_paper_preset_runs_the_pretrained_emission_mlp(traversal, tmp_path):
    """``--preset paper``: the shipped emission MLP (a D_m = 10 chart map), the shipped learned
    transition scaled as the preset says."""
    out = tmp_path / "run"
    args = ["slam", str(traversal), "--out", str(out), "--preset", "paper", "--config", TINY]
    assert cli.main(args) == 0
    report = json.loads((out / "metrics.json").read_text())
    assert report["preset"] == "paper" and report["config"]["emission"]["kind"] == "mlp"
    assert report["config"]["transition"]["scale"] == [3.0, 3.0, 0.2]
    assert np.load(out / "posterior.npz")["map_loc"].shape[-1] == 10
    assert 0 <= report["slam"]["final_error"] < 0.2


def test_slam_with_the_ray_emission_writes_an_occupancy_map(traversal, tmp_path, capsys):
    """The default preset (ray-cast emission): no emission network is loaded, the map has one
    feature per cell, and asking for an emission network as well is an input error."""
    out = tmp_path / "run"
    cfg = TINY
    assert cli.main(["slam", str(traversal), "--out", str(out), "--config", cfg]) == 0
    post = np.load(out / "posterior.npz")
    assert post["map_loc"].shape[-1] == 1 and (out / "slam.png").is_file()
    report = json.loads((out / "metrics.json").read_text())
    assert 0 <= report["slam"]["final_error"] < 0.2
    capsys.readouterr()
    args = ["slam", str(traversal), "--out", str(tmp_path / "r2"), "--config", cfg]
    assert cli.main(args + ["--emission", "pyro_slam/pretrained/emission_lidar20.pt"]) == 2
    assert "raycast" in capsys.readouterr().err
