"""Execute every tutorial notebook in ``notebooks/`` with ``SMOKE_TEST=1`` (tiny sizes).

A cell that raises fails the test. ``NOTEBOOKS`` is the explicit list CI runs; a notebook that
is added to ``notebooks/`` without being listed here fails ``test_every_notebook_is_executed``,
so no tutorial can silently go untested. Notebooks are committed without outputs.

The kernel is ``python3`` from the interpreter running pytest (ipykernel in the same venv), and
it inherits this process's environment (``SMOKE_TEST``, ``PYTHONPATH``).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK_DIR = ROOT / "notebooks"
NOTEBOOKS = [
    "01_quickstart.ipynb",
    "02_guides_and_priors.ipynb",
    "03_predictive_rollouts.ipynb",
]
FOUND = sorted(p.name for p in NOTEBOOK_DIR.glob("*.ipynb"))
CELL_TIMEOUT_S = 300  # per cell; a smoke run of a whole notebook takes < 60 s on one core


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


@pytest.mark.parametrize("name", FOUND)
def test_notebook_executes(name, monkeypatch):
    monkeypatch.setenv("SMOKE_TEST", "1")
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    monkeypatch.setenv("TQDM_DISABLE", "1")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    # the kernel imports the package under test (editable install or PYTHONPATH=repo root)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(ROOT), os.environ.get(
        "PYTHONPATH")])))  # fmt: skip
    nb = nbformat.read(NOTEBOOK_DIR / name, as_version=4)
    client = nbclient.NotebookClient(
        nb,
        timeout=CELL_TIMEOUT_S,
        kernel_name="python3",
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
    )
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
