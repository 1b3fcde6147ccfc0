"""The documentation names what exists: configuration fields that ``--config`` accepts and
those of the exploration configuration, files of the repository, every notebook."""

from __future__ import annotations

import re
from dataclasses import fields
from pathlib import Path

import pytest

from pyro_slam.planning.exploration import ExploreConfig
from pyro_slam.slam import SLAMConfig
from pyro_slam.slam.config import COMPONENTS, component_fields

ROOT = Path(__file__).resolve().parents[1]
PAGES = [
    ROOT / "README.md",
    ROOT / "notebooks" / "README.md",
    *sorted((ROOT / "docs").glob("*.md")),
]
CONFIG_NAME = re.compile(r"`((?:" + "|".join(COMPONENTS) + r")\.[a-z_.]+)`")
EXPLORE_NAME = re.compile(r"`ExploreConfig\.([A-Za-z_.]+)")
REPO_PATH = re.compile(r"`((?:pyro_slam|simulators|benchmarks|notebooks|tests)/[\w/.-]*\w)`")


def _is_field(name: str, cls=SLAMConfig) -> bool:
    """Whether the configuration ``cls`` has the dotted field ``name`` (e.g.
    ``emission.insert.gap``, as ``--config`` knows it)."""
    for part in name.split("."):
        if cls is None or part not in {f.name for f in fields(cls)}:
            return False
        cls = component_fields(cls).get(part, (None,))[0]
    return True


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_configuration_names_in_the_docs_are_accepted_by_config(page):
    for name in sorted(set(CONFIG_NAME.findall(page.read_text()))):
        if name.endswith(".py"):  # a file (heading.py), not a field
            continue
        assert _is_field(name), f"{page.name}: `{name}` is not a configuration field"
    for name in sorted(set(EXPLORE_NAME.findall(page.read_text()))):
        if callable(getattr(ExploreConfig, name.split(".")[0], None)):  # a method: smoke()
            continue
        ok = _is_field(name.rstrip("."), ExploreConfig)
        assert ok, f"{page.name}: `ExploreConfig.{name}` is not an exploration configuration field"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_repository_paths_in_the_docs_exist(page):
    missing = [p for p in REPO_PATH.findall(page.read_text()) if not (ROOT / p).exists()]
    assert not missing, f"{page.name} names files that do not exist: {missing}"


def test_notebook_readme_lists_every_notebook():
    text = (ROOT / "notebooks" / "README.md").read_text()
    missing = [p.name for p in sorted((ROOT / "notebooks").glob("*.ipynb")) if p.name not in text]
    assert not missing, f"notebooks/README.md does not list {missing}"
