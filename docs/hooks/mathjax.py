"""mkdocs hook: publish MathJax with the site, so that the maths renders offline (no CDN).

MathJax 3 comes from the ``[docs]`` extra's ``django-static-mathjax`` (a copy of MathJax's own
distribution; despite its name it needs no Django). Its SVG output, ``es5/tex-svg-full.js``, is
one file that draws the glyphs itself: no web fonts, which a browser refuses to load from a site
opened from disk. The file and MathJax's licence become ``javascripts/mathjax/`` of the site;
``mkdocs.yml`` loads it after ``javascripts/mathjax.js`` (its configuration).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

PACKAGE = "mathjax"  # the import name of django-static-mathjax
# MathJax's file -> the site's: the SVG output with every TeX extension built in (\boldsymbol
# and the like need no further file)
PUBLISHED = {"es5/tex-svg-full.js": "tex-svg-full.js", "LICENSE": "LICENSE"}


def mathjax_dir() -> Path:
    """The installed MathJax distribution (``es5/``, ``LICENSE``), found without importing
    the package; :class:`PluginError` naming the extra when it is missing."""
    spec = importlib.util.find_spec(PACKAGE)
    root = None if spec is None else Path(list(spec.submodule_search_locations)[0])
    found = None if root is None else root / "static" / "mathjax"
    if found is None or not all((found / name).is_file() for name in PUBLISHED):
        raise PluginError(
            "the docs bundle MathJax from the package 'django-static-mathjax', which is not "
            "installed: pip install '.[docs]'"
        )
    return found


def on_files(files, config):
    src = mathjax_dir()
    for name, dest in PUBLISHED.items():
        path = f"javascripts/mathjax/{dest}"
        files.append(File.generated(config, path, abs_src_path=str(src / name)))
    return files
