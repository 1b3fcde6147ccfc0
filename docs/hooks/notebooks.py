"""mkdocs hook: publish ``notebooks/*.ipynb`` as pages at ``notebooks/<name>/``.

The notebooks stay in one place (``notebooks/``, executed by ``tests/test_notebooks.py``); this
hook adds them to the site's files before mkdocs-jupyter converts them (hence the priority).
"""

from __future__ import annotations

from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[2]


@event_priority(100)  # before mkdocs-jupyter's on_files wraps notebook files
def on_files(files, config):
    # a File whose source directory is the repository root: its ``src_uri`` is
    # ``notebooks/<name>.ipynb`` (the nav and links use that), read from the real file
    for nb in sorted((ROOT / "notebooks").glob("*.ipynb")):
        files.append(
            File(
                f"notebooks/{nb.name}",
                src_dir=str(ROOT),
                dest_dir=config.site_dir,
                use_directory_urls=config.use_directory_urls,
            )
        )
    return files
