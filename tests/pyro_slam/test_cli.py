"""The ``pyro-slam`` command line: simulate -> slam -> resume -> navigate, pretrain, help, and
bad input."""

import argparse
import contextlib
import errno
import hashlib
import itertools
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from pyro_slam import cli, pretrained
from pyro_slam.data import load
from pyro_slam.planning import GroundTruthEnv, plan
from pyro_slam.runtime import package_version
from pyro_slam.slam import SLAM, SLAMConfig, checkpoint, outputs, presets, runner
from simulators import make_maze

REPO = Path(__file__).resolve().parents[2]
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
    # what the run was: its seed, input, preset and the package's version
    assert report["seed"] == 1 and report["input"] == str(traversal.resolve())
    assert report["version"] == package_version() != "unknown"
    # the default preset, with the overrides applied
    assert report["preset"] == presets.DEFAULT and report["config"]["filter"]["particles"] == 16
    assert report["config"]["emission"]["kind"] == "raycast"
    s, p = report["slam"], report["path_integration"]
    # a 30-step run cannot drift far: both errors are small and finite
    assert 0 <= s["final_error"] < 0.2 and 0 <= p["final_error"] < 0.2
    assert np.isfinite(s["ate_unaligned"]["rmse"]) and np.isfinite(s["ate_aligned"]["rmse"])
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


def test_resumed_run_keeps_the_total_wall_time(traversal, tmp_path, monkeypatch):
    """``timing.json``'s ``wall_time_s`` of a resumed run is the run's wall time over all its
    sessions (kept in the checkpoint), not the last session's; ``resumed`` says it was resumed.
    (Clocks that advance 1000 seconds, then one second, per reading make the sessions' times
    tell apart.)"""

    def clock(step):  # a clock that advances ``step`` seconds per reading
        ticks = itertools.count(0, step)
        monkeypatch.setattr(
            runner, "time", SimpleNamespace(perf_counter=lambda: float(next(ticks)))
        )

    clock(1000)  # the first session: slow
    out = tmp_path / "run"
    args = ["slam", str(traversal), "--out", str(out), "--config", TINY, "--checkpoint-every", "10"]
    save = SLAM.save

    def save_then_stop(self, path):  # SIGINT right after the first checkpoint
        save(self, path)
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(SLAM, "save", save_then_stop)
        assert cli.main(args) == 130
    saved = checkpoint.read(out / ".partial" / "checkpoint.pt")["state"]["wall_time_s"]
    assert saved >= 1000
    clock(1)  # the second: fast
    assert cli.main([*args, "--resume"]) == 0
    again = json.loads((out / "timing.json").read_text())
    assert again["resumed"] is True
    assert saved < again["wall_time_s"] < saved + 100, again  # the first session's in it


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
    """``--preset paper``: the shipped emission MLP (a D_m = 10 chart map) and the shipped learned
    transition, with the one ``sigma_T`` scale the model has everywhere (training and filtering)."""
    out = tmp_path / "run"
    args = ["slam", str(traversal), "--out", str(out), "--preset", "paper", "--config", TINY]
    assert cli.main(args) == 0
    report = json.loads((out / "metrics.json").read_text())
    assert report["preset"] == "paper" and report["config"]["emission"]["kind"] == "mlp"
    assert report["config"]["transition"]["kind"] == "learned"
    assert report["config"]["transition"]["scale"] == list(SLAMConfig().transition.scale)
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


# ------------------------------------------------------------------------ overwrite, resume
def _run_files(folder: Path) -> dict[str, str]:
    """The files of the run in ``folder`` (its hidden entries, a run's own, left out)."""
    return {k: v for k, v in _files(folder).items() if not k.startswith(".")}


def _files(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (hidden ones too) and its SHA-256."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _no_space(*_args, **_kw):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def _diverge(*_args, **_kw):
    raise FloatingPointError("SVI loss became nan")


def test_overwrite_keeps_previous_run_on_bad_input(traversal, tmp_path, capsys, monkeypatch):
    """``--overwrite`` with a bad ``--config``, a bad input file or a bad network file fails
    before it touches the previous run: every file of it is unchanged, byte for byte, and no
    other file appears; so does a run that fails before it wrote an output. A good run then
    replaces it."""
    out = tmp_path / "run"
    args = ["slam", str(traversal), "--out", str(out), "--config", TINY]
    assert cli.main(args) == 0
    before = _files(out)
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"not a zip file")
    garbage = tmp_path / "net.pt"
    garbage.write_bytes(b"garbage" * 10)
    paper = [*args, "--preset", "paper", "--overwrite"]
    bad = [
        ([*args[:4], "--config", '{"filter_partcles": 64}', "--overwrite"], "filter_partcles"),
        (["slam", str(corrupt), *args[2:], "--overwrite"], "corrupt.npz"),
        ([*paper, "--emission", str(garbage)], "net.pt"),
        ([*paper, "--transition", str(garbage)], "net.pt"),
    ]
    capsys.readouterr()
    for argv, named in bad:
        assert cli.main(argv) == 2, argv
        assert named in capsys.readouterr().err
        assert _files(out) == before, argv
    # a failure after the input was read: a one-line error, the previous run untouched
    with monkeypatch.context() as m:
        m.setattr(SLAM, "run", _diverge)
        assert cli.main([*args, "--overwrite"]) == 2
    assert "SLAM diverged" in capsys.readouterr().err
    assert _files(out) == before
    assert cli.main([*args, "--overwrite", "--seed", "5"]) == 0
    assert json.loads((out / "metrics.json").read_text())["seed"] == 5
    assert sorted(_files(out)) == sorted(before)  # the same outputs, none left behind


SIGNAL_AT_FIRST_CHECKPOINT = textwrap.dedent(
    """
    import os, signal, sys
    import torch
    torch.set_num_threads(1)
    # a process started in the background may inherit SIGINT ignored: restore Python's own
    signal.signal(signal.SIGINT, signal.default_int_handler)
    from pyro_slam import cli
    from pyro_slam.slam import SLAM
    save = SLAM.save
    def save_and_signal(self, path):
        save(self, path)
        os.kill(os.getpid(), getattr(signal, os.environ["SIGNAL"]))
    SLAM.save = save_and_signal
    sys.exit(cli.main(sys.argv[1:]))
    """
)


def _signalled_run(argv: list[str], name: str) -> subprocess.CompletedProcess:
    """``pyro-slam ARGV`` in a new process that sends itself the signal ``name`` right after
    its first checkpoint."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1", "SIGNAL": name}
    script = [sys.executable, "-c", SIGNAL_AT_FIRST_CHECKPOINT, *argv]
    return subprocess.run(script, env=env, capture_output=True)


# the default preset (its transition noise follows the cloud's trust in the map), shrunk; the
# first checkpoint (step 5) follows an SVI step (step 4), so the map has changed since the last
# weighing: the trust must come from the checkpoint, not be recomputed
RESUME_CONFIG = {"filter": {"particles": 32}, "training": {"particles": 4, "chunks": 2}}
RESUME_OFFLINE = {"offline": {"rounds": 1, "svi_steps": 6}}  # (only an offline run reads it)


def _assert_resume_is_byte_identical(traversal, tmp_path, mode):
    config = json.dumps({**RESUME_CONFIG, **(RESUME_OFFLINE if mode == "offline" else {})})
    args = [str(traversal), "--mode", mode, "--config", config, "--checkpoint-every", "5"]
    ref, killed = tmp_path / "uninterrupted", tmp_path / "killed"
    assert cli.main(["slam", *args, "--out", str(ref)]) == 0
    proc = _signalled_run(["slam", *args, "--out", str(killed)], "SIGKILL")
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()[-2000:]
    # killed at step 5: no run in the folder yet, the run so far inside it (and its lock)
    assert sorted(_files(killed)) == [".lock", ".partial/checkpoint.pt"]
    # a fresh run object that knows only the checkpoint file
    assert cli.main(["slam", *args, "--out", str(killed), "--resume"]) == 0
    for name in ("trajectory_slam.tum", "map.pgm"):
        assert (killed / name).read_bytes() == (ref / name).read_bytes(), name
    a, b = np.load(ref / "posterior.npz"), np.load(killed / "posterior.npz")
    for key in a.files:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_resume_is_byte_identical_online(traversal, tmp_path):
    """An online run SIGKILLed right after its first checkpoint and resumed in a new process
    ends with exactly the trajectory, posterior and map of an uninterrupted run."""
    _assert_resume_is_byte_identical(traversal, tmp_path, "online")


def test_resume_is_byte_identical_offline(traversal, tmp_path):
    """The same for offline SLAM, killed inside the online sweep it starts with."""
    _assert_resume_is_byte_identical(traversal, tmp_path, "offline")


# ------------------------------------------------------------------------------ failing runs
ABSURD_LR = json.dumps(
    {**json.loads(TINY), "training": {**json.loads(TINY)["training"], "lr": 1e30}}
)


def test_overwrite_survives_late_failure(traversal, tmp_path, capsys):
    """A new ``--overwrite`` run that fails late leaves the previous run byte for byte: the
    filter diverging (an absurd learning rate, after the first checkpoint) is one line naming
    ``training.lr``; SIGINT and SIGTERM right after the first checkpoint keep the run so far
    in the folder's ``.partial``, and ``--resume`` finishes it and only then replaces the
    previous one."""
    out = tmp_path / "run"
    args = ["slam", str(traversal), "--out", str(out), "--config", TINY]
    assert cli.main(args) == 0
    before, folder = _files(out), _files(tmp_path)
    capsys.readouterr()
    late = ["--overwrite", "--checkpoint-every", "5"]
    assert cli.main([*args[:4], "--config", ABSURD_LR, *late]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(err) == 1 and "SLAM diverged" in err[0] and "training.lr 1e+30" in err[0]
    assert _files(tmp_path) == folder  # nothing left beside it either
    partial = out / ".partial"
    for name, rc in (("SIGINT", 130), ("SIGTERM", 143)):
        proc = _signalled_run([*args, *late, "--seed", "5"], name)
        err = proc.stderr.decode()
        assert proc.returncode == rc, err[-2000:]
        assert "Traceback" not in err and f"interrupted ({name})" in err
        assert _run_files(out) == before, name
        assert (partial / "checkpoint.pt").is_file(), name  # the run so far, for --resume
    assert cli.main([*args, "--seed", "5", "--checkpoint-every", "5", "--resume"]) == 0
    assert json.loads((out / "metrics.json").read_text())["seed"] == 5
    assert not partial.exists() and sorted(_files(out)) == sorted(before)


def test_full_disk_keeps_previous_run(traversal, tmp_path, capsys, monkeypatch):
    """A write failing for a full disk (ENOSPC) while the outputs are written: one line naming
    the file, the previous run unchanged, the finished checkpoint kept for ``--resume``."""
    out = tmp_path / "run"
    args = ["slam", str(traversal), "--out", str(out), "--config", TINY]
    assert cli.main(args) == 0
    before = _files(out)

    def full(_tr, _res, _grid, path):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    with monkeypatch.context() as m:
        m.setattr(outputs.plotting, "plot_slam", full)
        assert cli.main([*args, "--overwrite", "--seed", "2"]) == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and "slam.png" in err and str(out) in err
    assert _run_files(out) == before
    assert cli.main([*args, "--seed", "2", "--resume"]) == 0
    assert json.loads((out / "metrics.json").read_text())["seed"] == 2


def test_failed_run_leaves_no_empty_folder(traversal, tmp_path, capsys, monkeypatch):
    """A run into a new folder (with new parents) that fails, at any point, leaves nothing."""
    out = tmp_path / "new" / "run"
    late = ["--out", str(out), "--checkpoint-every", "5"]
    assert cli.main(["slam", str(traversal), *late, "--config", ABSURD_LR]) == 2
    assert cli.main(["slam", str(tmp_path / "missing.npz"), *late]) == 2
    with monkeypatch.context() as m:
        m.setattr(SLAM, "run", _diverge)
        assert cli.main(["demo", *late, "--steps", "20"]) == 2
    assert "SLAM diverged" in capsys.readouterr().err
    with monkeypatch.context() as m:
        m.setattr(cli, "simulate_traversal", _no_space)
        assert cli.main(["simulate", "--out", str(out / "t.npz"), "--steps", "20"]) == 2
    assert list(tmp_path.iterdir()) == []


def test_simulate_failure_keeps_previous_files(traversal, tmp_path, capsys, monkeypatch):
    """``simulate`` onto a previous traversal and plot that fails writing the traversal (a
    full disk) leaves both files as they were: the new plot is moved in only with it."""
    out = tmp_path / "t.npz"
    sim = ["simulate", "--maze", "simple-small", "--steps", "20", "--out", str(out)]
    assert cli.main(sim) == 0
    before = _files(tmp_path)

    with monkeypatch.context() as m:
        m.setattr(cli.Traversal, "save", _no_space)
        assert cli.main([*sim, "--seed", "4"]) == 2
    assert "No space left on device" in capsys.readouterr().err
    assert _files(tmp_path) == before


def test_run_slam_into_a_path_replaces_it_whole(traversal, tmp_path):
    """``run_slam`` given a folder's path (as the benchmarks call it) writes the run there,
    and a second run replaces the first one's outputs but keeps the folder's other files."""
    out = tmp_path / "api"
    config = presets.configure(None, load(traversal), TINY)[1]
    outputs.run_slam(load(traversal), out, "online", config, progress=False, seed=1)
    (out / "notes.txt").write_text("mine")
    (out / "map.png").write_bytes(b"stale")  # an output this (simulated) run does not write
    report = outputs.run_slam(load(traversal), out, "online", config, progress=False, seed=2)
    assert report["seed"] == 2 == json.loads((out / "metrics.json").read_text())["seed"]
    assert (out / "notes.txt").read_text() == "mine" and not (out / "map.png").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["api"]


HOLD_THE_FOLDER = textwrap.dedent(
    """
    import sys
    from pyro_slam.slam.outputs import run_folder
    with run_folder(sys.argv[1], overwrite=True):
        print("holding", flush=True)
        sys.stdin.read()
    """
)


@contextlib.contextmanager
def _held(folder: Path):
    """The block runs while another process holds ``folder`` as its run folder (which it
    then leaves cleanly)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD_THE_FOLDER, str(folder)],
        env=env,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
    )
    try:
        assert holder.stdout.readline() == b"holding\n"
        yield
    finally:
        holder.communicate(b"")
    assert holder.returncode == 0


def test_concurrent_runs_refused(traversal, tmp_path, capsys):
    """While another process runs into a folder, a second run into it is refused before any
    work, naming the folder; once the first has finished, it runs."""
    out = tmp_path / "run"
    args = ["slam", str(traversal), "--out", str(out), "--config", TINY]
    with _held(out):
        assert cli.main(args) == 2
        err = capsys.readouterr().err
        assert "another run is writing into it" in err and str(out) in err
        assert cli.main([*args, "--overwrite"]) == 2
    assert cli.main(args) == 0


def test_resume_refuses_other_walls(traversal, tmp_path, capsys):
    """``--resume`` with an input whose walls differ (here: enlarge the map) is refused
    naming the data set's walls, not continued with a map of another size."""
    out = tmp_path / "run"
    assert cli.main(["slam", str(traversal), "--out", str(out), "--config", TINY]) == 0
    arrays = dict(np.load(traversal))
    walls = arrays["walls"].copy()
    walls[0] -= 0.5  # one wall moved outside the maze: a larger map grid
    other = tmp_path / "other.npz"
    np.savez(other, **{**arrays, "walls": walls})
    before = _files(out)
    assert cli.main(["slam", str(other), "--out", str(out), "--config", TINY, "--resume"]) == 2
    assert "walls" in capsys.readouterr().err
    assert _files(out) == before


def _no_work(*_a, **_kw):
    pytest.fail("the command started working before refusing its input")


def _exit_status(argv: list[str]) -> int:
    """``cli.main(argv)``'s exit status, also where argparse exits."""
    try:
        return cli.main(argv)
    except SystemExit as e:
        return e.code


def test_huge_sizes_refused_fast(traversal, tmp_path, capsys, monkeypatch):
    """A size or number that cannot mean anything is refused before any work (nothing is
    simulated, no SLAM is set up, nothing is written), exit status 2, naming the option or
    field and its limit."""
    monkeypatch.setattr(cli, "simulate_traversal", _no_work)
    monkeypatch.setattr(outputs, "SLAM", _no_work)
    o = str(tmp_path / "o")
    slam = ["slam", str(traversal), "--out", o, "--config"]
    cases = [
        (["simulate", "--steps", "1000000000", "--out", f"{o}.npz"], "--steps", "at most"),
        (["demo", "--steps", "1000000000", "--out", o], "--steps", "at most"),
        (["simulate", "--seed", str(2**32), "--out", f"{o}.npz"], "--seed", "at most"),
        (["slam", str(traversal), "--out", o, "--seed", str(2**40)], "--seed", "at most"),
        (["simulate", "--distractors", "10000000", "--out", f"{o}.npz"], "--distract", "at most"),
        ([*slam, '{"emission": {"resolution": 1e308}}'], "emission.resolution", "at most"),
        ([*slam, '{"beam_stride": 1000}'], "beam_stride 1000", "at most 19"),
        ([*slam, '{"range_clip": 1e308}'], "range_clip", "at most"),
        ([*slam, '{"transition": {"sigma": [0.1, 0.1, 0.1]}}'], "transition.sigma", "learned"),
    ]
    for argv, field, limit in cases:
        assert _exit_status(argv) == 2, argv
        err = capsys.readouterr().err
        assert field in err and limit in err, (argv, err)
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------ pretrain
PRETRAIN_FAST = ["--steps", "60", "--emission-steps", "2", "--transition-epochs", "1"]


def test_pretrain_refuses_to_write_into_the_package(tmp_path, monkeypatch, capsys):
    """``pretrain`` writes into the installed package only with ``--into-package``; by default
    into ``pretrained/`` in the current folder, and never over network files without
    ``--overwrite``; the networks it writes load. (The package's folder is a copy here, so that
    a failure cannot replace the shipped networks.)"""
    package = tmp_path / "package" / "pretrained"
    package.mkdir(parents=True)
    for name in (pretrained.EMISSION_FILE, pretrained.TRANSITION_FILE):
        (package / name).write_bytes((pretrained.PRETRAINED / name).read_bytes())
    monkeypatch.setattr(pretrained, "PRETRAINED", package)
    shipped = _files(package)
    for out in (package, package / "sub", package / ".." / "pretrained"):
        assert cli.main(["pretrain", "--out", str(out), "--overwrite", *PRETRAIN_FAST]) == 2
        assert "--into-package" in capsys.readouterr().err
    assert _files(package) == shipped
    monkeypatch.chdir(tmp_path)
    assert cli.main(["pretrain", *PRETRAIN_FAST]) == 0
    out = tmp_path / "pretrained"
    written = {p.name: p.read_bytes() for p in out.iterdir()}
    assert sorted(written) == sorted([pretrained.EMISSION_FILE, pretrained.TRANSITION_FILE])
    capsys.readouterr()
    assert cli.main(["pretrain", *PRETRAIN_FAST, "--seed", "3"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == written
    pretrained.load_transition(out / pretrained.TRANSITION_FILE)
    assert cli.main(["pretrain", *PRETRAIN_FAST, "--seed", "3", "--overwrite"]) == 0
    assert {p.name: p.read_bytes() for p in out.iterdir()} != written


# ------------------------------------------------------------------------------ navigate
@pytest.fixture(scope="module")
def mapped(tmp_path_factory):
    """A finished SLAM run over a 300-step traversal of a small maze."""
    root = tmp_path_factory.mktemp("mapped")
    tr = root / "tr.npz"
    sim = ["simulate", "--maze", "simple-small", "--steps", "300", "--seed", "2", "--no-plot"]
    assert cli.main([*sim, "--out", str(tr)]) == 0
    assert cli.main(["slam", str(tr), "--out", str(root / "run"), "--config", TINY]) == 0
    return tr, root / "run"


def test_navigate_from_a_slam_run_plans_in_its_map(mapped, tmp_path, capsys):
    """``navigate --from OUT`` plans in the map a finished SLAM run left (its own traversal's
    maze executes the plan) and reaches a goal it has mapped; exit status 1 when no plan is
    found ("found": false)."""
    tr_path, run = mapped
    poses = np.load(tr_path)["poses"]
    start, goal = poses[0], poses[60, :2]  # a place the robot passed, inside the mapped corridor
    out = tmp_path / "nav.png"
    argv = [
        "navigate",
        "--from",
        str(run),
        "--out",
        str(out),
        "--max-expansions",
        "1500",
        "--start",
        *map(str, start),
        "--goal",
        *map(str, goal),
    ]
    capsys.readouterr()
    assert cli.main(argv) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["found"] and report["final_error"] < 0.05 and out.is_file()
    assert cli.main([*argv, "--max-expansions", "1"]) == 2  # the plot exists: no --overwrite
    assert "--overwrite" in capsys.readouterr().err
    assert cli.main([*argv, "--max-expansions", "1", "--overwrite"]) == 1
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["found"] is False


def test_navigate_reads_a_given_traversal(mapped, tmp_path, capsys):
    """``navigate --traversal FILE`` maps and plans in the traversal's own maze; a maze option
    that contradicts it is refused, naming it."""
    tr_path, _ = mapped
    argv = [
        "navigate",
        "--traversal",
        str(tr_path),
        "--out",
        str(tmp_path / "n.png"),
        "--fit-steps",
        "20",
        "--max-expansions",
        "20",
    ]
    rc = cli.main(argv)
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rc == (0 if report["found"] else 1)
    assert cli.main([*argv, "--maze-seed", "7", "--overwrite"]) == 2
    assert "--maze-seed 7" in capsys.readouterr().err


def test_navigate_refuses_other_maze(mapped, tmp_path, capsys):
    """``navigate --from RUN --traversal FILE`` with a traversal of another maze than the run
    mapped is refused before any planning, naming the walls and the run."""
    _, run = mapped
    other = tmp_path / "other.npz"
    sim = ["simulate", "--maze", "simple-small", "--steps", "300", "--seed", "9", "--no-plot"]
    assert cli.main([*sim, "--out", str(other)]) == 0
    out = tmp_path / "n.png"
    argv = ["navigate", "--from", str(run), "--traversal", str(other), "--out", str(out)]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "'walls' differs from the maze the run --from" in err and str(run) in err
    assert not out.exists()


# ------------------------------------------------------------------------------ help
def _subparsers(parser: argparse.ArgumentParser) -> dict:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices


def test_checkpoint_interval_and_real_log_numbers_have_one_default():
    """``--checkpoint-every`` and :class:`SLAM` / :func:`run_slam` share
    :data:`~pyro_slam.slam.checkpoint.CHECKPOINT_EVERY`; ``--odometry-noise``'s help and
    :func:`~pyro_slam.slam.presets.adapt_real_log` read :data:`~pyro_slam.slam.presets.REAL_LOG`."""
    import inspect

    every = checkpoint.CHECKPOINT_EVERY
    slam = _subparsers(cli.build_parser())["slam"]
    action = next(a for a in slam._actions if "--checkpoint-every" in a.option_strings)
    assert action.default == every
    assert inspect.signature(SLAM).parameters["checkpoint_every"].default == every
    assert inspect.signature(outputs.run_slam).parameters["checkpoint_every"].default == every
    noise = next(a for a in slam._actions if "--odometry-noise" in a.option_strings)
    assert f"default {presets.REAL_LOG.odometry_noise:g}" in noise.help
    adapt = inspect.signature(presets.adapt_real_log).parameters
    for name in ("target_beams", "range_quantile", "odometry_noise", "heading_noise"):
        assert adapt[name].default == getattr(presets.REAL_LOG, name), name


def test_every_option_has_help_and_shows_its_default(capsys):
    """Walk the parser: every option and argument of every sub-command has help text, shows
    its default (or says in words what happens without one), every sub-command has a
    description and a ``--seed``; ``--version`` prints the package's version."""
    parser = cli.build_parser()
    subs = _subparsers(parser)
    assert set(subs) == {"simulate", "slam", "demo", "navigate", "pretrain"}
    for name, sub in subs.items():
        assert sub.description and len(sub.description) > 40, name
        assert any("--seed" in a.option_strings for a in sub._actions), name
        text = " ".join(sub.format_help().split())
        for action in sub._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            what = f"{name} {action.option_strings or action.dest}"
            assert action.help and len(action.help) > 8, what
            if action.default is None and action.nargs != 0 and action.option_strings:
                assert "default" in action.help, what  # said in words
            elif action.option_strings:
                shown = f"(default: {action.default})"
                assert " ".join(shown.split()) in text, what
    with pytest.raises(SystemExit) as info:
        cli.main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.strip() == f"pyro-slam {package_version()}"


def test_version_answers_without_importing_torch():
    """``pyro-slam --version`` (the console script and ``python -m pyro_slam.cli``) prints the
    version before the command line's imports load torch."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    script = (
        "import sys\nsys.argv = ['/usr/bin/pyro-slam', '--version']\n"
        "try:\n    from pyro_slam.cli import main\nexcept SystemExit as e:\n"
        "    print('exit', e.code, 'torch' in sys.modules)\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", script], env=env, cwd=REPO, capture_output=True, text=True
    )
    assert run.stdout.split("\n")[:2] == [f"pyro-slam {package_version()}", "exit 0 False"]
    run = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "pyro_slam.cli", "--version"],
        env=env,
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0 and run.stdout.strip() == f"pyro-slam {package_version()}"
    imported = [line.rsplit("|", 1)[-1].strip() for line in run.stderr.splitlines()]
    assert "pyro_slam.version" in imported and "torch" not in imported


def test_option_not_applying_to_preset_is_refused(traversal, tmp_path, capsys):
    """``--odometry-noise`` adapts the real-log preset; with a preset that does not use it
    (the simulator's default, or one named) it is refused naming the option and the preset,
    not silently ignored."""
    args = ["slam", str(traversal), "--config", TINY, "--odometry-noise", "0.2"]
    assert cli.main([*args, "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert "--odometry-noise" in err and f"'{presets.DEFAULT}'" in err and "'real'" in err
    assert cli.main([*args, "--preset", "raycast", "--out", str(tmp_path / "b")]) == 2
    assert "not to the preset 'raycast'" in capsys.readouterr().err
    assert not (tmp_path / "a" / "metrics.json").exists()


def test_goal_outside_map_refused(traversal, tmp_path, capsys):
    """A navigation goal, start or target pose outside the maze is refused before any map is
    fitted or searched, naming the option and the map's extent; :func:`plan` refuses it too."""
    base = ["navigate", "--traversal", str(traversal), "--out", str(tmp_path / "n.png")]
    for option, values in (
        ("--goal", ["5", "5"]),
        ("--start", ["1e308", "1e308", "0"]),
        ("--target-scan-from-pose", ["-1", "0.5", "0"]),
    ):
        assert cli.main([*base, option, *values]) == 2, option
        err = capsys.readouterr().err
        assert f"error: {option} " in err and "outside the map" in err, err
    assert not (tmp_path / "n.png").exists()
    env = GroundTruthEnv(make_maze("simple-small", 1))
    with pytest.raises(ValueError, match="goal 5 5: outside the map"):
        plan(env, np.array([0.1, 0.1, 0.0]), np.array([5.0, 5.0]))


def test_out_on_mount_point_and_dot(traversal, tmp_path, monkeypatch):
    """``--out`` on a mount point (which cannot be renamed: here every rename of the folder
    itself fails with EBUSY, as the kernel answers for a mount) and ``--out .`` both run,
    again with ``--overwrite`` and ``--resume``: the run is moved in file by file."""
    mount = tmp_path / "mounted"
    mount.mkdir()
    real_replace, real_rename = os.replace, os.rename

    def refuse_the_mount(fn):
        def move(src, dst, *a, **kw):
            if {os.path.realpath(src), os.path.realpath(dst)} & {str(mount), str(tmp_path)}:
                raise OSError(errno.EBUSY, os.strerror(errno.EBUSY), str(src))
            return fn(src, dst, *a, **kw)

        return move

    monkeypatch.setattr(os, "replace", refuse_the_mount(real_replace))
    monkeypatch.setattr(os, "rename", refuse_the_mount(real_rename))
    args = ["slam", str(traversal), "--config", TINY, "--checkpoint-every", "5"]
    for extra in ([], ["--overwrite", "--seed", "2"], ["--resume", "--seed", "2"]):
        assert cli.main([*args, "--out", str(mount), *extra]) == 0, extra
        assert json.loads((mount / "metrics.json").read_text())["seed"] == (2 if extra else 0)
    assert sorted(p.name for p in mount.iterdir() if p.name.startswith(".")) == []
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    assert cli.main([*args, "--out", "."]) == 0
    assert (here / "trajectory_slam.tum").is_file() and (here / "map.pgm").is_file()
    assert cli.main([*args, "--out", ".", "--overwrite", "--seed", "3"]) == 0
    assert json.loads((here / "metrics.json").read_text())["seed"] == 3


def test_symlinked_out_keeps_link_and_lock(traversal, tmp_path, capsys):
    """``--out ALIAS``, a symbolic link to a folder: the run is written into the folder and
    the link stays a link; while another process holds the folder, a run into the alias is
    refused; a lock file planted as a link is refused, and what it points to is not
    created."""
    real, alias = tmp_path / "real", tmp_path / "alias"
    real.mkdir()
    alias.symlink_to(real, target_is_directory=True)
    args = ["slam", str(traversal), "--config", TINY]
    assert cli.main([*args, "--out", str(alias)]) == 0
    assert alias.is_symlink() and (real / "metrics.json").is_file()
    assert cli.main([*args, "--out", str(alias), "--overwrite", "--seed", "4"]) == 0
    assert alias.is_symlink() and json.loads((real / "metrics.json").read_text())["seed"] == 4
    with _held(real):
        capsys.readouterr()
        assert cli.main([*args, "--out", str(alias), "--overwrite"]) == 2
        assert "another run is writing into it" in capsys.readouterr().err
    planted = tmp_path / "elsewhere" / "created"
    (real / ".lock").symlink_to(planted)
    assert cli.main([*args, "--out", str(alias), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert "is a symbolic link" in err and ".lock" in err
    assert not planted.exists() and not planted.parent.exists()
    assert json.loads((real / "metrics.json").read_text())["seed"] == 4


def test_unused_config_field_refused(traversal, tmp_path, capsys):
    """A ``--config`` field that nothing in the run reads is refused before any work, naming
    the field and what ignores it: ``offline.*`` in an online run, ``filter.lag`` in an
    offline one, the ray march's settings
    with the paper's emission MLP, ``training.lr_emission`` where no emission is learned; the
    same fields where they are read run."""
    out = tmp_path / "run"
    cases = [
        ([], {"offline": {"rounds": 1}}, "offline.rounds", "--mode online"),
        (["--mode", "offline"], {"filter": {"lag": 5}}, "filter.lag", "--mode offline"),
        (["--preset", "paper"], {"emission": {"ray_spacing": 1.0}}, "emission.ray_spacing", "mlp"),
        (["--preset", "paper"], {"emission": {"march_tolerance": 1e-6}}, "march_tolerance", "rays"),
        ([], {"training": {"lr_emission": 0.01}}, "training.lr_emission", "frozen"),
        ([], {"transition": {"sigma": [0.1, 0.1, 0.1]}}, "transition.sigma", "learned"),
    ]
    for extra, changes, field, why in cases:
        config = json.dumps({**json.loads(TINY), **changes})
        argv = ["slam", str(traversal), "--out", str(out), "--config", config, *extra]
        assert cli.main(argv) == 2, changes
        err = capsys.readouterr().err
        assert field in err and why in err and "ignored" in err, err
        assert not out.exists()
    used = {**json.loads(TINY), "offline": {"rounds": 1, "svi_steps": 2}}
    argv = ["slam", str(traversal), "--out", str(out), "--mode", "offline"]
    assert cli.main([*argv, "--config", json.dumps(used), "--steps", "12"]) == 0
    config = json.loads((out / "metrics.json").read_text())["config"]
    assert config["offline"]["rounds"] == 1 and config["offline"]["svi_steps"] == 2


def test_metrics_record_the_transition_that_ran(traversal, tmp_path, capsys):
    """``metrics.json`` records the transition that ran: a learned network handed to a
    configuration of the kinematic kind runs, and is recorded, as ``learned``; the command
    line refuses ``--transition FILE`` with ``transition.kind`` kinematic, naming the field."""
    net = pretrained.PRETRAINED / "transition_moderate_medium.pt"
    kinematic = json.dumps({**json.loads(TINY), "transition": {"kind": "kinematic"}})
    argv = ["slam", str(traversal), "--out", str(tmp_path / "cli"), "--config", kinematic]
    assert cli.main([*argv, "--transition", str(net)]) == 2
    err = capsys.readouterr().err
    assert "--transition" in err and "transition.kind 'kinematic'" in err
    config = presets.configure(None, load(traversal), kinematic)[1]
    tr = load(traversal)
    for given, ran in ((pretrained.load_transition(net), "learned"), (None, "kinematic")):
        out = tmp_path / ran
        outputs.run_slam(tr, out, "online", config, transition=given, progress=False)
        recorded = json.loads((out / "metrics.json").read_text())["config"]["transition"]
        assert recorded["kind"] == ran


def test_huge_cache_threads_svi_steps_refused(traversal, tmp_path, capsys):
    """Sizes that would exhaust memory, the OpenMP runtime or any time budget are refused
    before any work with one line naming the field or option and its limit: a particle
    cache of 1e9 particles, 1e6 threads, 1e12 offline SVI steps, 1e9 offline rounds, a scan
    of one beam."""
    out = tmp_path / "run"
    base = ["slam", str(traversal), "--out", str(out)]
    huge = [
        (["--config", '{"training": {"cache_particles": 1000000000}}'], "cache_particles"),
        (["--threads", "1000000"], "--threads"),
        (
            ["--mode", "offline", "--config", '{"offline": {"svi_steps": 1000000000000}}'],
            "svi_steps",
        ),
        (["--mode", "offline", "--config", '{"offline": {"rounds": 1000000000}}'], "rounds"),
    ]
    for extra, named in huge:
        with pytest.raises(SystemExit) if extra[0] == "--threads" else contextlib.nullcontext():
            assert cli.main([*base, *extra]) == 2, extra
        err = capsys.readouterr().err
        assert named in err and "at most" in err and "Traceback" not in err, err
        assert not out.exists()
    arrays = dict(np.load(traversal))
    one = tmp_path / "one_beam.npz"
    beams = ("observations", "obs_mask", "beam_angles")
    np.savez(one, **{k: (v[..., :1] if k in beams else v) for k, v in arrays.items()})
    assert cli.main(["slam", str(one), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "1 beam" in err and "one_beam.npz" in err


def test_oversized_settings_refused_before_work(traversal, tmp_path, capsys):
    """Particle counts whose tensors would not fit in memory, and a configuration nested
    100,000 deep, are refused before anything is allocated or written, one line naming the
    field, no traceback."""
    out = tmp_path / "o"
    deep = tmp_path / "deep.json"
    deep.write_text('{"a": ' * 100_000 + "1" + "}" * 100_000)
    cases = [
        ('{"filter": {"particles": 1000000000}}', "filter.particles"),
        ('{"training": {"particles": 100000000}}', "training.particles"),
        (str(deep), "nested too deeply"),
    ]
    for config, named in cases:
        assert cli.main(["slam", str(traversal), "--out", str(out), "--config", config]) == 2
        err = capsys.readouterr().err
        assert named in err and "Traceback" not in err and len(err.splitlines()) == 1, err
    assert list(tmp_path.iterdir()) == [deep]


def test_short_offline_run_and_a_bad_plot_backend_end_cleanly(tmp_path, capsys):
    """Offline SLAM on a traversal shorter than its SVI chunks is refused naming
    ``training.chunk_length``; an unknown ``MPLBACKEND`` does not stop the command, which
    draws into files with matplotlib's file backend."""
    short = tmp_path / "short.npz"
    assert (
        cli.main(["simulate", "--maze", "simple-small", "--steps", "3", "--out", str(short)]) == 0
    )
    capsys.readouterr()
    assert cli.main(["slam", str(short), "--out", str(tmp_path / "o"), "--mode", "offline"]) == 2
    assert "training.chunk_length 4" in capsys.readouterr().err
    env = {**os.environ, "PYTHONPATH": str(REPO), "MPLBACKEND": "nonexistent"}
    argv = ["slam", str(short), "--out", str(tmp_path / "plots"), "--config", TINY]
    proc = subprocess.run(
        [sys.executable, "-m", "pyro_slam.cli", *argv], env=env, capture_output=True
    )
    assert proc.returncode == 0, proc.stderr.decode()[-2000:]
    assert (tmp_path / "plots" / "slam.png").is_file()


KILLED_IN_THE_SWAP = textwrap.dedent(
    """
    import os, signal, sys
    from pyro_slam import cli
    from pyro_slam.slam import outputs
    replace = os.replace
    def replace_or_die(src, dst):
        if os.path.basename(os.path.dirname(dst)) == ".previous":
            replace(src, dst)
            os.kill(os.getpid(), signal.SIGKILL)  # half-way: the first old output moved aside
        replace(src, dst)
    outputs.os.replace = replace_or_die
    sys.exit(cli.main(sys.argv[1:]))
    """
)


def test_killed_swap_is_reported_and_cleaned(traversal, tmp_path):
    """A run SIGKILLed half-way through putting its finished outputs in place (one old output
    moved aside): the next run on the folder (``--overwrite``) says so on stderr, finishes
    putting the killed run in place, replaces it, and leaves neither ``.previous`` nor
    ``.partial`` behind."""
    out = tmp_path / "run"
    args = ["slam", str(traversal), "--out", str(out), "--config", TINY]
    assert cli.main(args) == 0
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    script = [sys.executable, "-c", KILLED_IN_THE_SWAP, *args, "--overwrite", "--seed", "7"]
    proc = subprocess.run(script, env=env, capture_output=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()[-2000:]
    assert (out / ".previous").is_dir() and (out / ".partial" / ".complete").is_file()
    proc = subprocess.run(
        [sys.executable, "-m", "pyro_slam.cli", *args, "--overwrite", "--seed", "8"],
        env=env,
        capture_output=True,
    )
    err = proc.stderr.decode()
    assert proc.returncode == 0, err[-2000:]
    assert "stopped while being put in place" in err and str(out / ".partial") in err
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []
    assert json.loads((out / "metrics.json").read_text())["seed"] == 8


def test_resume_on_finished_run_is_a_no_op(traversal, tmp_path, capsys):
    """``--resume`` on a folder whose run has finished says so and rewrites nothing (every
    file byte for byte and untouched), keeps nothing hidden; its report is the run's."""
    out = tmp_path / "run"
    args = ["slam", str(traversal), "--out", str(out), "--config", TINY]
    assert cli.main(args) == 0
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in out.iterdir()}
    capsys.readouterr()
    assert cli.main([*args, "--resume"]) == 0
    captured = capsys.readouterr()
    assert "its run has finished; nothing to resume" in captured.err
    assert "final error SLAM" in captured.out
    assert {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in out.iterdir()} == before
