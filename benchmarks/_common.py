"""Helpers shared by the benchmark scripts (not a benchmark itself)."""

from __future__ import annotations

import argparse


def parse_maze_seeds(
    p: argparse.ArgumentParser, text: str, test: tuple[int, ...], tuning: tuple[int, ...] = ()
) -> list[int]:
    """The maze seeds of a ``--maze-seeds`` argument ``"1001,1002"``: each must be one of the
    benchmark's ``test`` mazes or its held-out ``tuning`` mazes; anything else is a usage error
    (``p.error``, exit 2) naming the offending seeds and the allowed ones."""
    try:
        mazes = [int(m) for m in text.split(",")]
    except ValueError:
        p.error(f"--maze-seeds: expected comma-separated integers, got {text!r}")
    if unknown := sorted(set(mazes) - set(test) - set(tuning)):
        allowed = f"not test mazes (these are {list(test)})"
        if tuning:
            allowed += f" or tuning mazes {list(tuning)}"
        p.error(f"--maze-seeds {unknown}: {allowed}")
    return mazes
