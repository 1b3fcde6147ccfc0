"""mkdocs hook: publish ``notebooks/*.ipynb`` as pages at ``notebooks/<name>.html``, with their
outputs.

The notebooks stay in one place (``notebooks/``, committed without outputs). A page shows an
executed copy, ``build/executed/notebooks/<name>.ipynb``, run at smoke size (``SMOKE_TEST=1``)
and stamped with the SHA-256 of the notebook it was run from. ``tests/test_notebooks.py``
writes these copies when it executes the notebooks, so a docs build after the tests (as in CI)
executes nothing; a copy that is missing or older than its notebook is executed here (about a
minute per notebook on one core). ``DOCS_EXECUTE_NOTEBOOKS=false`` skips that and publishes
such notebooks without outputs (a quick preview).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import sys
import tempfile
from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[2]
EXECUTED = ROOT / "build" / "executed"  # holds notebooks/<name>.ipynb
STAMP = "pyro_slam_source_sha256"  # notebook metadata: the SHA-256 of the executed source
log = logging.getLogger("mkdocs.hooks.notebooks")


def source_digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def executed_copy(nb_path: Path) -> Path:
    return EXECUTED / "notebooks" / nb_path.name


def is_current(nb_path: Path) -> bool:
    """Whether the executed copy of ``nb_path`` exists and was run from its current text."""
    copy = executed_copy(nb_path)
    try:
        meta = json.loads(copy.read_text()).get("metadata", {})
    except (OSError, ValueError):
        return False
    return meta.get(STAMP) == source_digest(nb_path)


def store_executed(nb, nb_path: Path) -> Path:
    """Write the executed notebook ``nb`` (an ``nbformat`` node) of ``nb_path``, stamped."""
    import nbformat

    nb.metadata[STAMP] = source_digest(nb_path)
    copy = executed_copy(nb_path)
    copy.parent.mkdir(parents=True, exist_ok=True)
    tmp = copy.with_suffix(".tmp")
    nbformat.write(nb, tmp)
    os.replace(tmp, copy)
    return copy


def _execute(nb_path: Path) -> None:
    """Run ``nb_path`` at smoke size in a kernel of this interpreter; store the copy."""
    import nbclient
    import nbformat

    with tempfile.TemporaryDirectory() as jupyter:
        spec = Path(jupyter) / "kernels" / "pyro-slam-docs"
        spec.mkdir(parents=True)
        argv = [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"]
        spec.joinpath("kernel.json").write_text(json.dumps({"argv": argv, "language": "python"}))
        env = {
            "JUPYTER_PATH": jupyter,
            "SMOKE_TEST": "1",
            "MPLBACKEND": "module://matplotlib_inline.backend_inline",
            "TQDM_DISABLE": "1",
            "OMP_NUM_THREADS": "1",
            "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
        }
        saved = {k: os.environ.get(k) for k in env}
        os.environ.update(env)
        try:
            nb = nbformat.read(nb_path, as_version=4)
            never = 10**9  # no wall-clock limit: a slow machine takes longer, it does not fail
            nbclient.NotebookClient(
                nb,
                timeout=None,
                startup_timeout=never,
                iopub_timeout=never,
                kernel_name="pyro-slam-docs",
                resources={"metadata": {"path": str(nb_path.parent)}},
            ).execute()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
    store_executed(nb, nb_path)


@event_priority(100)  # before mkdocs-jupyter's on_files wraps notebook files
def on_files(files, config):
    # a File whose source directory holds ``notebooks/<name>.ipynb`` (the nav and links use
    # that): the executed copy where there is one, else the notebook itself
    execute = os.environ.get("DOCS_EXECUTE_NOTEBOOKS", "true").lower() not in ("0", "false")
    for nb in sorted((ROOT / "notebooks").glob("*.ipynb")):
        if not is_current(nb) and execute:
            log.info("executing %s at smoke size for its page", nb.name)
            _execute(nb)
        src = EXECUTED if is_current(nb) else ROOT
        files.append(
            File(
                f"notebooks/{nb.name}",
                src_dir=str(src),
                dest_dir=config.site_dir,
                use_directory_urls=config.use_directory_urls,
            )
        )
    return files
