"""Thread counts that degrade gracefully under load."""

from __future__ import annotations

import os

import torch

from pyro_slam import runtime


def test_threads_follow_the_idle_cores_and_are_restored(monkeypatch):
    monkeypatch.setattr(os, "cpu_count", lambda: 4)
    before = torch.get_num_threads()
    torch.set_num_threads(4)
    try:
        monkeypatch.setattr(os, "getloadavg", lambda: (3.0, 3.0, 3.0))  # 3 cores busy
        assert runtime.idle_cores() == 1
        with runtime.torch_threads() as n:
            assert n == 1 and torch.get_num_threads() == 1
        assert torch.get_num_threads() == 4
        monkeypatch.setattr(os, "getloadavg", lambda: (0.2, 0.2, 0.2))  # idle
        with runtime.torch_threads() as n:
            assert n == 4
        monkeypatch.setattr(os, "getloadavg", lambda: (9.0, 9.0, 9.0))  # overloaded
        assert runtime.idle_cores() == 1  # never fewer than one
        with runtime.torch_threads(3) as n:  # an explicit count wins
            assert n == 3
    finally:
        torch.set_num_threads(before)
