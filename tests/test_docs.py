"""The documentation names what exists: configuration fields that ``--config`` accepts and
those of the exploration configuration, files of the repository, every notebook."""

from __future__ import annotations

import re
from dataclasses import fields, replace
from pathlib import Path

import pytest

from pyro_slam.planning.exploration import ExploreConfig
from pyro_slam.slam import SLAMConfig, presets
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


# ------------------------------------------------------------------------------ the site
def _orphan_table_rows(text: str) -> list[int]:
    """Line numbers of table rows that follow a blank line inside a table: rows without a
    header of their own (a blank line ends a Markdown table, so they are no table at all)."""
    lines, found, fenced = text.splitlines(), [], False
    for i, line in enumerate(lines):
        if line.startswith("```"):
            fenced = not fenced
        if fenced or not line.startswith("|") or i < 2 or lines[i - 1].strip():
            continue
        header = i + 1 < len(lines) and re.match(r"^\|[\s:|-]+\|$", lines[i + 1].strip())
        if lines[i - 2].startswith("|") and not header:
            found.append(i + 1)
    return found


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_tables_in_the_docs_are_not_split_by_a_blank_line(page):
    rows = _orphan_table_rows(page.read_text())
    assert not rows, f"{page.name}: table rows after a blank line at lines {rows}"


def test_the_site_works_from_disk_and_offline():
    """Links end in .html (no web server needed), and nothing is fetched from the network:
    no script, style or font from another site."""
    import yaml

    class Loader(yaml.SafeLoader):  # mkdocs.yml's !ENV tags: their default
        pass

    Loader.add_constructor("!ENV", lambda loader, node: None)
    config = yaml.load((ROOT / "mkdocs.yml").read_text(), Loader=Loader)
    assert config["use_directory_urls"] is False
    assert config["theme"].get("font") is False  # the theme's default loads a font CDN
    remote = [u for u in config.get("extra_javascript", []) + config.get("extra_css", [])]
    assert not [u for u in remote if "://" in str(u)], remote
    assert "docs/hooks/mathjax.py" in config["hooks"]


def test_the_notebooks_extra_has_what_the_tutorials_use():
    """A tutorial that reads the ATE needs evo (``metrics.json`` has no ATE without it)."""
    import configparser

    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    extra = cfg["options.extras_require"]["notebooks"]
    notebooks = sorted((ROOT / "notebooks").glob("*.ipynb"))
    uses_ate = [p.name for p in notebooks if re.search(r"\['ate_(un)?aligned'\]", p.read_text())]
    assert uses_ate, "no tutorial reads the ATE: this test checks nothing"
    assert "evo" in extra, f"{uses_ate} read the ATE, which needs evo in the [notebooks] extra"


def _hook(name: str):
    pytest.importorskip("mkdocs")  # the [docs] extra
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"hook_{name}", ROOT / "docs" / "hooks" / name)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_mathjax_hook_names_the_package_it_needs(monkeypatch):
    from mkdocs.exceptions import PluginError

    hook = _hook("mathjax.py")
    assert (hook.mathjax_dir() / "es5" / "tex-svg-full.js").is_file()
    monkeypatch.setattr(hook.importlib.util, "find_spec", lambda _name: None)
    with pytest.raises(PluginError, match="django-static-mathjax"):
        hook.mathjax_dir()


def test_notebook_pages_use_an_executed_copy_only_of_the_current_notebook(tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    hook = _hook("notebooks.py")
    monkeypatch.setattr(hook, "EXECUTED", tmp_path / "executed")
    source = tmp_path / "n.ipynb"
    nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell("1 + 1")])
    nbformat.write(nb, source)
    assert not hook.is_current(source)
    hook.store_executed(nb, source)
    assert hook.is_current(source)
    nb.cells[0].source = "2 + 2"  # the notebook changed since its copy was executed
    nbformat.write(nb, source)
    assert not hook.is_current(source)


# ------------------------------------------------------------------ preset tables
PRESET_NAME = re.compile(r"`([a-z][a-z-]*)`")
KINDS = (("row MLPs", "image_mlp"), ("ray camera", "ray_camera"), ("emission MLP", "mlp"))
KINDS += (("ray-cast", "raycast"),)


def _tables(text: str):
    """The markdown tables of ``text``: lists of rows, each a list of its cells' text."""
    rows: list[list[str]] = []
    for line in [*text.splitlines(), ""]:
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if not all(set(c) <= set("-: ") for c in cells):  # (the header's rule)
                rows.append(cells)
        elif rows:
            yield rows
            rows = []


def _preset_rows(page: Path):
    """``(table, name, summary, whole)`` for each row of a table whose rows are presets: its
    preset, the row's statement of it (its ``model`` column, or what follows the name in the
    first cell) and whether the table lists every preset (it has a ``model`` column);
    ``(table, name, cell, True)`` for each column of a table whose columns are presets and
    for each preset an option table lists for ``--preset NAME`` (up to its "see")."""
    for n, table in enumerate(_tables(page.read_text(encoding="utf-8"))):
        head = table[0]
        for row in table:
            if row[0] == "`--preset NAME`":
                listed = row[1].split("(see")[0]
                for found in PRESET_NAME.finditer(listed):
                    yield -n - 1, found.group(1), listed[found.end() :].split(",")[0], True
        if head[0] == "component":  # presets as columns
            for cell in head[1:]:
                yield n, PRESET_NAME.search(cell).group(1), cell, True
        elif head[0] == "preset":
            model = head.index("model") if "model" in head else None
            for row in table[1:]:
                found = PRESET_NAME.search(row[0])
                if found:
                    rest = row[0][found.end() :]
                    summary = row[model] if model is not None else rest
                    yield n, found.group(1), f"{rest} {summary}", model is not None


def _check_summary(name: str, summary: str) -> list[str]:
    """What the statement ``summary`` of the preset ``name`` says that its configuration is
    not: the default, the emission kind it names, a heading factor, and the preset it says
    it adds the heading factor to (``plus``) or takes it from (``without``)."""
    cfg, bad = presets.PRESETS[name].config, []
    if bool(re.search(r"\((the library's )?default", summary)) != (name == presets.DEFAULT):
        bad.append("the default marker")
    for words, kind in KINDS:
        if words in summary:
            if cfg.emission.kind != kind:
                bad.append(f"{words!r}: emission.kind is {cfg.emission.kind!r}")
            break
    base = re.match(r"\s*`([a-z-]+)` (without|plus) the heading factor", summary)
    if base:
        other = presets.PRESETS[base.group(1)].config
        same = replace(cfg, heading=None) == replace(other, heading=None)
        if not same or (cfg.heading is None) != (base.group(2) == "without"):
            bad.append(f"{base.group(0).strip()!r}")
    elif re.search(r"\b(without|no) (the )?heading factor", summary):
        if cfg.heading is not None:
            bad.append("no heading factor: heading is set")
    elif "heading factor" in summary and cfg.heading is None:
        bad.append("the heading factor: heading is None")
    return bad


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_docs_preset_tables_match_presets(page):
    """Every table of presets names presets that exist; one that describes them all names
    each once; a row's statement of its preset (the default, its emission, the heading factor
    and the preset it is stated against) holds for its configuration."""
    tables: dict[int, list[str]] = {}
    for table, name, summary, whole in _preset_rows(page):
        assert name in presets.PRESETS, f"{page.name}: `{name}` is not a preset"
        problems = _check_summary(name, summary)
        assert not problems, f"{page.name}: `{name}`: {'; '.join(problems)}"
        if whole:
            tables.setdefault(table, []).append(name)
    for names in tables.values():
        assert sorted(names) == sorted(presets.PRESETS), f"{page.name}: {names}"
