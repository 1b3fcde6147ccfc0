"""Shared settings of the core tests: one intra-op thread (the tensors are tiny; on a shared
2-core machine thread hand-offs cost 10-30x the compute), a clean Pyro state per test, and the
shared test helpers of ``support/`` (synthetic logs, the PF-net stand-in world) importable from
every test folder, which mirror the package's subpackages."""

from __future__ import annotations

import sys
from pathlib import Path

import pyro
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent / "support"))
torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _clean_pyro_state():
    pyro.clear_param_store()
    yield
    pyro.clear_param_store()
