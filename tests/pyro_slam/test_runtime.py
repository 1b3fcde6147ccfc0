"""The runtime: a stated thread count (never the machine's load), the provenance a run records in
``metrics.json``, and runs of the same command that give the same bytes."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyro
import pytest
import torch
from synthetic_logs import room_log

from pyro_slam import cli, metrics, runtime
from pyro_slam.io import read_any, write_carmen

REPO = Path(__file__).resolve().parents[2]
# a light filter and SVI batch for a short log
SMALL = {"filter": {"particles": 16}}  # (a real log's preset takes no SVI steps)


def test_threads_are_the_stated_count_whatever_the_load(monkeypatch):
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        for load in (0.0, 1.5, 50.0):  # an idle, a busy and an overloaded machine
            monkeypatch.setattr(os, "getloadavg", lambda load=load: (load, load, load))
            with runtime.torch_threads() as n:
                assert n == runtime.DEFAULT_THREADS == 1 == torch.get_num_threads()
            assert torch.get_num_threads() == 2  # restored
            with runtime.torch_threads(3) as n:  # an explicit count
                assert n == 3 == torch.get_num_threads()
        for bad in (0, -1, 1.5, True, "2"):
            with pytest.raises(ValueError, match="threads must be a positive integer"):
                runtime.thread_count(bad)
    finally:
        torch.set_num_threads(before)


def test_sha256_of_a_file_and_of_a_folder_in_sorted_order(tmp_path):
    f = tmp_path / "log.clf"
    f.write_bytes(b"FLASER 1 2 3\n")
    assert runtime.sha256(f) == hashlib.sha256(b"FLASER 1 2 3\n").hexdigest()
    bag = tmp_path / "bag"
    files = {"metadata.yaml": b"m", "sub/b.db3": b"b", "a_0.db3": b"a", "z.db3": b"z"}
    for name in ("z.db3", "sub/b.db3", "metadata.yaml", "a_0.db3"):  # not in sorted order
        (bag / name).parent.mkdir(parents=True, exist_ok=True)
        (bag / name).write_bytes(files[name])
    lines = "".join(
        f"{hashlib.sha256(files[name]).hexdigest()}  {name}\n" for name in sorted(files)
    )
    digest = runtime.sha256(bag)
    assert digest == hashlib.sha256(lines.encode()).hexdigest()
    (bag / "sub" / "b.db3").write_bytes(b"c")  # another content: another digest
    assert runtime.sha256(bag) != digest
    (bag / "sub" / "b.db3").write_bytes(b"b")
    (bag / "sub" / "b.db3").rename(bag / "sub" / "c.db3")  # another name: another digest
    assert runtime.sha256(bag) != digest


def _log(tmp_path: Path) -> Path:
    tr, _ = room_log(T=24)  # scans 20 steps apart score each other
    return write_carmen(tr, tmp_path / "room.clf")


def test_metrics_json_records_threads_versions_argv_and_the_inputs_digest(tmp_path):
    log = _log(tmp_path)
    out = tmp_path / "run"
    argv = ["slam", str(log), "--out", str(out), "--config", json.dumps(SMALL), "--threads", "2"]
    assert cli.main(argv) == 0
    report = json.loads((out / "metrics.json").read_text())
    assert report["threads"] == 2
    assert report["torch"] == torch.__version__ and report["pyro"] == pyro.__version__
    assert report["numpy"] == np.__version__
    assert report["argv"] == ["pyro-slam", *argv]
    assert report["sha256"] == hashlib.sha256(log.read_bytes()).hexdigest()
    # the timings, which differ from run to run, are kept apart
    timing = json.loads((out / "timing.json").read_text())
    assert timing["wall_time_s"] > 0 and timing["seconds_per_step"] > 0
    assert not {"wall_time_s", "seconds_per_step"} & set(report)
    # scan consistency is the quoted metric: every 2nd beam of the log, not SLAM's every 8th
    poses = np.load(out / "posterior.npz")["pose_mean"]
    tr = read_any(log)
    consistency = report["scan_consistency"]["slam"]
    assert consistency == json.loads(json.dumps(metrics.log_scan_consistency(tr, poses)))
    assert consistency["beam_stride"] == 2 and report["config"]["beam_stride"] == 8
    assert consistency["points"] > metrics.scan_consistency(tr.subsample_beams(8), poses)["points"]


def _slam(log: Path, out: Path, seed: str = "0") -> None:
    """``python -m pyro_slam.cli slam`` in a process of its own."""
    cmd = [sys.executable, "-m", "pyro_slam.cli", "slam", str(log), "--out", str(out)]
    cmd += ["--config", json.dumps(SMALL), "--seed", seed, "--threads", "1"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_the_same_command_gives_the_same_bytes(tmp_path):
    log, out = _log(tmp_path), tmp_path / "run"
    _slam(log, out)
    first = tmp_path / "first"
    shutil.move(out, first)
    _slam(log, out)  # the same command again, in another process
    for name in ("trajectory_slam.tum", "metrics.json", "posterior.npz"):
        assert (out / name).read_bytes() == (first / name).read_bytes(), name
    shutil.rmtree(out)
    _slam(log, out, seed="1")  # (the comparison can tell runs apart)
    assert (out / "trajectory_slam.tum").read_bytes() != (
        first / "trajectory_slam.tum"
    ).read_bytes()


def test_a_run_is_set_up_with_what_torch_imports_for_its_first_optimiser():
    """What torch imports on its first optimiser (``torch._dynamo``, seconds) is imported when
    a SLAM run is set up, not at its first SVI step inside the run (where it would stall the
    filter): in a fresh interpreter, building the run's parts imports it."""
    code = (
        "import sys\n"
        "from simulators import simulate_traversal\n"
        "from pyro_slam.slam import SLAM\n"
        "tr = simulate_traversal('moderate-medium', steps=20, seed=1)\n"
        "before = 'torch._dynamo' in sys.modules\n"
        "SLAM(tr, seed=0)\n"
        "print(before, 'torch._dynamo' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "True"]
