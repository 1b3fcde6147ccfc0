"""Hypothesis profiles: ``dev`` (default) draws new random examples on every run, so local runs
keep exploring; ``ci`` (``HYPOTHESIS_PROFILE=ci``, set by ``.ci/run``) is derandomised, so a CI
verdict is reproducible. A failure found locally is replayed from ``.hypothesis/``; turn it into
a deterministic regression test (see ``test_every_encrypted_flag_bit_fails_cleanly``)."""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("dev")
settings.register_profile("ci", derandomize=True, database=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "dev"))
