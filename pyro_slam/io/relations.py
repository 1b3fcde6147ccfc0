"""Relation-based trajectory error (Kümmerle et al., "On measuring the accuracy of SLAM
algorithms", Autonomous Robots 2009).

A relation file has one relation per line, ``t1 t2 x y z roll pitch yaw``: the pose at time
``t2`` seen from the pose at time ``t1`` (``#`` comments and blank lines allowed). Relations
are kept as a float64 array ``[R, 8]`` with exactly these columns; only ``x, y, yaw`` matter in
2D. The error of an estimated trajectory is, per relation, the translational ``|t_est - t_rel|``
(m) and rotational ``|wrap_angle(yaw_est - yaw_rel)|`` (deg) difference of the relative poses.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from pyro_slam.data import atomic_write
from pyro_slam.geometry import wrap_angle
from pyro_slam.io.common import ParseError, open_text, parse_float, relative

COLUMNS = ("t1", "t2", "x", "y", "z", "roll", "pitch", "yaw")


def read_relations(path: str | os.PathLike) -> np.ndarray:
    """Relations ``[R, 8]`` from a Kümmerle-style file (a byte-order mark skipped);
    :class:`ParseError` ``file:line`` on a line without 8 finite numbers, and naming the file
    where it is a folder."""
    path = Path(path)
    rows = []
    with open_text(path, "relations file") as f:
        for lineno, raw in enumerate(f, start=1):
            tokens = raw.split()
            if not tokens or tokens[0].startswith("#"):
                continue
            if len(tokens) != len(COLUMNS):
                raise ParseError(
                    path,
                    lineno,
                    f"expected {len(COLUMNS)} fields ({' '.join(COLUMNS)}), got {len(tokens)}",
                )
            try:
                row = [parse_float(t) for t in tokens]
            except ValueError as e:
                raise ParseError(path, lineno, str(e)) from None
            if not all(math.isfinite(v) for v in row):
                raise ParseError(path, lineno, "non-finite value")
            rows.append(row)
    return np.array(rows, dtype=np.float64).reshape(-1, len(COLUMNS))


def write_relations(relations: np.ndarray, path: str | os.PathLike) -> Path:
    """Write ``[R, 8]`` relations in the format :func:`read_relations` reads."""
    lines = ["# t1 t2 x y z roll pitch yaw"]
    lines += [" ".join(repr(float(v)) for v in row) for row in np.asarray(relations)]
    text = "\n".join(lines) + "\n"
    atomic_write(Path(path), lambda f: f.write(text.encode()))
    return Path(path)


def _nearest(timestamps: np.ndarray, t: np.ndarray, max_dt: float):
    """Index ``[R]`` of the timestamp nearest each ``t`` and whether it lies within max_dt."""
    order = np.argsort(timestamps, kind="stable")
    s = timestamps[order]
    i = np.clip(np.searchsorted(s, t), 1, len(s) - 1) if len(s) > 1 else np.zeros(len(t), int)
    left = np.maximum(i - 1, 0)
    pick = np.where(np.abs(s[left] - t) <= np.abs(s[i] - t), left, i)
    return order[pick], np.abs(s[pick] - t) <= max_dt


def relation_error(
    timestamps: np.ndarray,  # [T]
    poses: np.ndarray,  # [T, 3]
    relations: np.ndarray,  # [R, 8]
    max_dt: float = 0.1,
) -> dict[str, float]:
    """Mean / std of the translational (m) and rotational (deg) relation errors.

    Each relation uses the poses nearest in time to ``t1`` and ``t2``; it is skipped when either
    is farther than ``max_dt`` seconds. With no usable relation the means and stds are NaN.
    """
    ts = np.asarray(timestamps, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    rel = np.asarray(relations, dtype=np.float64).reshape(-1, len(COLUMNS))
    if poses.shape != (len(ts), 3):
        raise ValueError(f"poses must have shape ({len(ts)}, 3), got {poses.shape}")
    i, ok_i = _nearest(ts, rel[:, 0], max_dt)
    j, ok_j = _nearest(ts, rel[:, 1], max_dt)
    ok = ok_i & ok_j
    est = relative(poses[i[ok]], poses[j[ok]])  # [R_used, 3]
    trans = np.linalg.norm(est[:, :2] - rel[ok][:, 2:4], axis=1)
    rot = np.degrees(np.abs(wrap_angle(est[:, 2] - rel[ok][:, 7])))
    stat = lambda f, a: float(f(a)) if a.size else math.nan
    return {
        "trans_mean": stat(np.mean, trans),
        "trans_std": stat(np.std, trans),
        "rot_mean_deg": stat(np.mean, rot),
        "rot_std_deg": stat(np.std, rot),
        "n_used": int(ok.sum()),
        "n_skipped": int((~ok).sum()),
    }


def relations_from_reference(
    timestamps: np.ndarray,  # [T]
    ref_poses: np.ndarray,  # [T, 3]
    *,
    consecutive: bool = True,
    n_random: int = 0,
    max_steps: int | None = None,
    seed: int = 0,
) -> np.ndarray:
    """Relations ``[R, 8]`` taken from a reference trajectory (e.g. GMapping's Intel poses):
    every consecutive pair ``(t, t+1)`` and ``n_random`` random pairs ``i < j`` (at most
    ``max_steps`` apart when given), drawn with ``seed``. Pairs involving a timestamp that
    several poses share are dropped (a time cannot identify the pose)."""
    ts = np.asarray(timestamps, dtype=np.float64)
    ref = np.asarray(ref_poses, dtype=np.float64)
    T = len(ts)
    pairs = [np.stack([np.arange(T - 1), np.arange(1, T)], axis=1)] if consecutive else []
    if n_random and T > 1:
        rng = np.random.default_rng(seed)
        i = rng.integers(0, T - 1, size=n_random)
        span = np.minimum(T - 1 - i, max_steps or T)
        j = i + 1 + (rng.random(n_random) * span).astype(int).clip(max=span - 1)
        pairs.append(np.stack([i, j], axis=1))
    if not pairs:
        return np.zeros((0, len(COLUMNS)))
    ij = np.concatenate(pairs)
    _, first, counts = np.unique(ts, return_index=True, return_counts=True)
    unique = np.zeros(T, bool)
    unique[first[counts == 1]] = True
    ij = ij[unique[ij[:, 0]] & unique[ij[:, 1]]]  # a shared timestamp cannot name one pose
    d = relative(ref[ij[:, 0]], ref[ij[:, 1]])  # [R, 3]
    out = np.zeros((len(ij), len(COLUMNS)))
    out[:, 0], out[:, 1] = ts[ij[:, 0]], ts[ij[:, 1]]
    out[:, [2, 3, 7]] = d
    return out
