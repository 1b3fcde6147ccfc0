"""Execute every tutorial notebook in ``notebooks/`` with ``SMOKE_TEST=1`` (tiny sizes).

A cell that raises fails the test. ``NOTEBOOKS`` is the explicit list CI runs; a notebook that
is added to ``notebooks/`` without being listed here fails ``test_every_notebook_is_executed``,
so no tutorial can silently go untested. Notebooks are committed without outputs; each executed
copy is kept in ``build/executed/notebooks/`` for the documentation's tutorial pages
(``docs/hooks/notebooks.py`` publishes it, stamped with the source's SHA-256, instead of
executing the notebook again).

The kernel runs the interpreter that runs pytest (``sys.executable``, ipykernel from the same
venv), via a kernel spec written for the test session -- the stock ``python3`` spec launches
whatever ``python`` is first on ``PATH``, which need not be the venv's. The kernel inherits
this process's environment (``SMOKE_TEST``, ``PYTHONPATH``). nbformat, nbclient and ipykernel
come with the ``dev`` extra; without them this module fails to import rather than skipping, so
a CI environment cannot silently leave the notebooks out.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from pathlib import Path

import nbclient  # the "dev" extra; a missing package fails (no skip: CI must run notebooks)
import nbformat
import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK_DIR = ROOT / "notebooks"
NOTEBOOKS = [
    "01_quickstart.ipynb",
    "02_guides_and_priors.ipynb",
    "03_predictive_rollouts.ipynb",
    "04_pfnet.ipynb",
    "05_navigation_exploration.ipynb",
]
FOUND = sorted(p.name for p in NOTEBOOK_DIR.glob("*.ipynb"))
EXECUTED = ROOT / "build" / "executed" / "notebooks"  # what docs/hooks/notebooks.py publishes
STAMP = "pyro_slam_source_sha256"  # its metadata key: the SHA-256 of the executed notebook
# No wall-clock limit decides a verdict: a cell may take as long as the machine needs (a smoke
# run of a whole notebook takes < 60 s on one idle core). nbclient's kernel start and output
# waits need a number of seconds; this one never expires.
NEVER_S = 10**9


def test_every_notebook_is_executed():
    assert FOUND, f"no notebooks found in {NOTEBOOK_DIR}"
    assert FOUND == sorted(NOTEBOOKS), (
        f"notebooks on disk {FOUND} differ from the executed list {sorted(NOTEBOOKS)}: "
        "add new notebooks to NOTEBOOKS in tests/test_notebooks.py"
    )


@pytest.mark.parametrize("name", FOUND)
def test_notebook_is_committed_without_outputs(name):
    nb = nbformat.read(NOTEBOOK_DIR / name, as_version=4)
    nbformat.validate(nb)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert not cell.outputs and cell.execution_count is None, f"{name}: cell {i} has output"


KERNEL_NAME = "pyro-slam-test"


def _client(nb) -> nbclient.NotebookClient:
    """The client that executes ``nb`` in the test kernel, with no wall-clock limit."""
    return nbclient.NotebookClient(
        nb,
        timeout=None,  # no limit per cell
        startup_timeout=NEVER_S,
        iopub_timeout=NEVER_S,
        kernel_name=KERNEL_NAME,
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
    )


def test_no_wall_clock_limit_decides_a_verdict():
    """A slow machine takes longer; it never fails a notebook: no limit on a cell, and the
    kernel's start and its output are waited for as long as it takes."""
    client = _client(nbformat.v4.new_notebook())
    assert client.timeout is None or client.timeout < 0
    assert client._get_timeout(None) is None
    assert min(client.startup_timeout, client.iopub_timeout) >= 10**9  # about 30 years


@pytest.fixture(scope="session")
def kernel_dir(tmp_path_factory):
    """A JUPYTER_PATH entry holding a kernel spec for this very interpreter."""
    root = tmp_path_factory.mktemp("jupyter")
    spec = root / "kernels" / KERNEL_NAME
    spec.mkdir(parents=True)
    argv = [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"]
    spec.joinpath("kernel.json").write_text(
        json.dumps({"argv": argv, "display_name": KERNEL_NAME, "language": "python"})
    )
    return root


@pytest.mark.parametrize("name", FOUND)
def test_notebook_executes(name, monkeypatch, kernel_dir):
    monkeypatch.setenv("JUPYTER_PATH", str(kernel_dir))
    monkeypatch.setenv("SMOKE_TEST", "1")
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    monkeypatch.setenv("TQDM_DISABLE", "1")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    # the kernel imports the package under test (editable install or PYTHONPATH=repo root)
    monkeypatch.setenv(
        "PYTHONPATH", os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    )
    nb = nbformat.read(NOTEBOOK_DIR / name, as_version=4)
    client = _client(nb)
    start = time.perf_counter()
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as e:  # the message names cell and traceback
        pytest.fail(f"{name}: {e}", pytrace=False)
    elapsed = time.perf_counter() - start
    errors = [
        o
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.outputs
        if o.get("output_type") == "error"
    ]
    assert not errors, f"{name}: error outputs {errors}"
    print(f"{name}: executed in {elapsed:.1f} s")
    _store_executed(nb, NOTEBOOK_DIR / name)


def _store_executed(nb, source: Path) -> None:
    """Keep the executed notebook for the docs, stamped with its source's SHA-256."""
    nb.metadata[STAMP] = hashlib.sha256(source.read_bytes()).hexdigest()
    EXECUTED.mkdir(parents=True, exist_ok=True)
    tmp = EXECUTED / f".{source.name}.tmp"
    nbformat.write(nb, tmp)
    os.replace(tmp, EXECUTED / source.name)
