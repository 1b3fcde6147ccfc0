"""Shared settings of the core tests: one intra-op thread (the tensors are tiny; on a shared
2-core machine thread hand-offs cost 10-30x the compute) and a clean Pyro state per test."""

from __future__ import annotations

import pyro
import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _clean_pyro_state():
    pyro.clear_param_store()
    yield
    pyro.clear_param_store()
