"""The runtime: the installed package's version, how many CPU threads torch uses for SLAM, and
the provenance a run records (versions, command line, thread count, the input's digest).

The thread count is a stated number, never read from the machine: :data:`DEFAULT_THREADS`
unless a caller (``pyro-slam slam --threads N``, a benchmark's ``--threads``) says otherwise.
A run's results depend on it (the order of floating-point reductions differs between thread
counts), so the same command with the same seed and thread count gives the same outputs
however busy the machine is. ``OMP_WAIT_POLICY=PASSIVE`` (set when :mod:`pyro_slam` is imported
before torch, unless the environment says otherwise) makes waiting threads sleep instead of
spin, so that several threads on a loaded machine do not slow each other down by spinning.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from pathlib import Path

import numpy as np
import pyro
import torch

from .version import package_version

DEFAULT_THREADS = 1  # torch intra-op threads of a run that names no count
MAX_THREADS = 256  # the most a run may ask for (OpenMP aborts the process far beyond)
CHUNK = 1 << 20  # bytes read at a time when hashing

__all__ = [
    "DEFAULT_THREADS",
    "package_version",
    "thread_count",
    "torch_threads",
    "warm_optimizers",
]


def thread_count(n: int | None = None) -> int:
    """The torch intra-op thread count a run uses: ``n``, or :data:`DEFAULT_THREADS` for None
    (a positive integer; anything else is a :class:`ValueError`)."""
    n = DEFAULT_THREADS if n is None else n
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"threads must be a positive integer, got {n!r}")
    if n > MAX_THREADS:
        raise ValueError(
            f"threads {n}: at most {MAX_THREADS} (this machine has {os.cpu_count()} cores; "
            "a thread count far beyond them only slows a run down)"
        )
    return n


@contextlib.contextmanager
def torch_threads(n: int | None = None):
    """Run the block with :func:`thread_count` ``(n)`` torch intra-op threads, then restore
    the previous count. Yields the count."""
    before = torch.get_num_threads()
    torch.set_num_threads(thread_count(n))
    try:
        yield torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


def warm_optimizers() -> None:
    """Construct one throwaway torch optimiser, so that what torch imports on its first
    optimiser (``torch._dynamo``, about 1.4 s) is imported now, when a run is set up, and not at
    its first SVI step, where it would stall the filter for a dozen scans of a real-time log."""
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(CHUNK):
            h.update(block)
    return h.hexdigest()


def sha256(path: str | Path) -> str:
    """The SHA-256 (hex) of a file's bytes; of a folder (a ROS 2 bag), the SHA-256 of the lines
    ``"<sha256 of the file>  <path relative to the folder>\\n"`` of every file in it, in sorted
    order of the relative paths (what ``sha256sum`` prints for each, sorted)."""
    path = Path(path)
    if not path.is_dir():
        return _file_sha256(path)
    files = sorted(p.relative_to(path).as_posix() for p in path.rglob("*") if p.is_file())
    lines = "".join(f"{_file_sha256(path / rel)}  {rel}\n" for rel in files)
    return hashlib.sha256(lines.encode()).hexdigest()


def provenance(threads: int, argv: list[str] | None = None, source=None) -> dict:
    """What a run's ``metrics.json`` records of how it was made: the thread count, the versions
    of ``pyro_slam``, torch, Pyro and numpy, the command line ``argv`` (None: not given) and the
    input ``source``'s :func:`sha256` (None without an input file)."""
    digest = None
    if source is not None and Path(source).exists():
        digest = sha256(source)
    return {
        "threads": threads,
        "version": package_version(),
        "torch": torch.__version__,
        "pyro": pyro.__version__,
        "numpy": np.__version__,
        "argv": None if argv is None else [str(a) for a in argv],
        "sha256": digest,
    }
