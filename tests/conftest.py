"""Shared settings of every test: one intra-op thread (the tensors are tiny; on a shared 2-core
machine thread hand-offs cost 10-30x the compute), a clean Pyro state per test, and the
Hypothesis profiles: ``dev`` (default) draws new random examples on every run, so local runs
keep exploring; ``ci`` (``HYPOTHESIS_PROFILE=ci``, set by ``.ci/run``) is derandomised, so a CI
verdict is reproducible. A failure found locally is replayed from ``.hypothesis/``; turn it into
a deterministic regression test (see ``test_every_encrypted_flag_bit_fails_cleanly``)."""

from __future__ import annotations

import os

import pyro
import pytest
import torch
from hypothesis import settings

torch.set_num_threads(1)

settings.register_profile("dev")
settings.register_profile("ci", derandomize=True, database=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "dev"))


@pytest.fixture(autouse=True)
def _clean_pyro_state():
    pyro.clear_param_store()
    yield
    pyro.clear_param_store()
