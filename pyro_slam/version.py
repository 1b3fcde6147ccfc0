"""The installed package's version, without importing torch (``pyro-slam --version`` answers
before the command line loads the model)."""

from __future__ import annotations

import sys
from importlib import metadata
from pathlib import Path

COMMAND = "pyro-slam"


def package_version() -> str:
    """The installed ``pyro_slam``'s version (its package metadata), ``"unknown"`` when it runs
    from a folder that was never installed."""
    try:
        return metadata.version("pyro_slam")
    except metadata.PackageNotFoundError:
        return "unknown"


def version_only(module_name: str, argv: list[str] | None = None) -> bool:
    """Whether this process is the ``pyro-slam`` command (the console script, or ``python -m
    pyro_slam.cli``, whose module runs as ``__main__``) asked for nothing but ``--version``:
    ``argv`` (default ``sys.argv``) and the command line module's ``module_name``."""
    argv = sys.argv if argv is None else argv
    if not argv or argv[1:] != ["--version"]:
        return False
    return module_name == "__main__" or Path(argv[0]).name == COMMAND
