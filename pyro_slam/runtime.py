"""The runtime: how many CPU threads torch uses for SLAM:
as many as the machine has idle cores.

Intra-op threads that spin-wait against another busy process on the same cores slow a run down
by an order of magnitude; with one thread per idle core (at least one) a run degrades
gracefully under load. ``OMP_WAIT_POLICY=PASSIVE`` (set when :mod:`pyro_slam` is imported
before torch, unless the environment says otherwise) makes waiting threads sleep instead of
spin.
"""

from __future__ import annotations

import contextlib
import os

import torch

from .version import package_version

__all__ = ["idle_cores", "package_version", "torch_threads"]


def idle_cores() -> int:
    """The machine's cores minus its 1-minute load average (at least 1)."""
    cores = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except OSError:  # (not available on every platform)
        load = 0.0
    return max(1, min(cores, int(cores - load + 0.5)))


@contextlib.contextmanager
def torch_threads(n: int | None = None):
    """Run the block with ``n`` torch intra-op threads (None: the current count, but at most
    :func:`idle_cores`), then restore the previous count."""
    before = torch.get_num_threads()
    torch.set_num_threads(min(before, idle_cores()) if n is None else max(1, int(n)))
    try:
        yield torch.get_num_threads()
    finally:
        torch.set_num_threads(before)
