"""The lean core: without the optional packages (evo, rosbags) the package imports and
simulate -> slam runs; a feature that needs one fails with a one-line message naming the extra
to install."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from pyro_slam import metrics
from pyro_slam.extras import MissingExtra, require

# run in a fresh interpreter in which importing evo or rosbags fails, as in `pip install .`
LEAN_RUN = """
import json, sys
for name in ("evo", "rosbags"):
    sys.modules[name] = None
from pathlib import Path
from pyro_slam import cli, metrics
out = Path(sys.argv[1])
tiny = json.dumps({"filter": {"particles": 16}, "training": {"particles": 4, "chunks": 2}})
assert cli.main(["simulate", "--maze", "simple-small", "--steps", "20", "--no-plot",
                 "--out", str(out / "tr.npz")]) == 0
assert cli.main(["slam", str(out / "tr.npz"), "--out", str(out / "run"), "--config", tiny]) == 0
(out / "scan.bag").write_bytes(b"")
print("bag exit", cli.main(["slam", str(out / "scan.bag"), "--out", str(out / "bag")]))
try:
    metrics.ate([[0, 0, 0]], [[0, 0, 0]])
except ImportError as e:
    print("ate:", e)
"""


def test_the_lean_core_runs_slam_and_names_the_extra_a_feature_needs(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = subprocess.run(
        [sys.executable, "-c", LEAN_RUN, str(tmp_path)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    report = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert report["steps"] == 20 and "final_error" in report["slam"]
    assert not {"ate_aligned", "ate_unaligned"} & set(
        report["slam"]
    )  # ATE is evo's, the [eval] extra
    assert "metrics.json without ATE" in run.stderr and "pyro_slam[eval]" in run.stderr
    assert "bag exit 2" in run.stdout
    assert (
        "pyro-slam slam: error: reading ROS bags needs the optional package 'rosbags': "
        "pip install 'pyro_slam[ros]'\n" in run.stderr
    )
    assert "ate: ATE needs the optional package 'evo': pip install 'pyro_slam[eval]'" in run.stdout
    assert "Traceback" not in run.stderr


def test_require_names_the_extra():
    require(metrics, "anything", "numpy", "eval")  # present: no error
    with pytest.raises(MissingExtra, match=r"pip install 'pyro_slam\[ros\]'"):
        require(None, "reading ROS bags", "rosbags", "ros")
    assert issubclass(MissingExtra, ImportError)
