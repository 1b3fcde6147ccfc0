"""Helpers shared by the log-reader tests: hand-made CARMEN lines, an independent FLASER
field reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def flaser(ranges, pose=(0.0, 0.0, 0.0), odom=None, t=0.0) -> str:
    """A valid FLASER line."""
    odom = pose if odom is None else odom
    nums = " ".join(str(v) for v in [*ranges, *pose, *odom])
    return f"FLASER {len(ranges)} {nums} {t} host {t}"


def odom_line(pose, t) -> str:
    return f"ODOM {pose[0]} {pose[1]} {pose[2]} 0 0 0 {t} host {t}"


def raw_flaser_fields(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Independent parse of a log's FLASER lines: ranges ``[T, n]`` and the 7 numbers after
    them ``[T, 7]`` (x y theta odom_x odom_y odom_theta ipc_timestamp)."""
    ranges, tails = [], []
    for line in path.read_text().splitlines():
        tok = line.split()
        if tok and tok[0] == "FLASER":
            n = int(tok[1])
            ranges.append([float(v) for v in tok[2 : 2 + n]])
            tails.append([float(v) for v in tok[2 + n : 9 + n]])
    return np.array(ranges), np.array(tails)
