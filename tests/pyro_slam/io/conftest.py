"""Fixtures for the log-reader tests: the shipped real logs (skipped when absent) and helpers
that build small CARMEN logs by hand."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
SHARED = Path(os.environ.get("PYRO_SLAM_SHARED", REPO.parent / "shared"))


def shared_log(name: str) -> Path:
    path = SHARED / "data" / name
    if not path.is_file():
        pytest.skip(f"shared log {path} not found (set PYRO_SLAM_SHARED to the shared/ folder)")
    return path


@pytest.fixture(scope="session")
def mit_path() -> Path:
    return shared_log("mit-csail.clf")


@pytest.fixture(scope="session")
def intel_path() -> Path:
    return shared_log("intel.gfs.log")
