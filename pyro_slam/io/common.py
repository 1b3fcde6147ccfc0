"""Shared pieces of the log readers: errors, strict number parsing, SE(2) helpers (numpy),
range masking, odometry pairing and the final :class:`~pyro_slam.data.Traversal` assembly.

Pose convention: ``(x, y, heading)``, heading wrapped to ``[-pi, pi)``; odometry controls are
robot-frame increments ``(dx, dy, dtheta)`` exactly as :func:`pyro_slam.geometry.odometry_delta`
applies them: ``compose(pose_t, u_t) == pose_{t+1}``.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from pyro_slam.data import DatasetError, Traversal
from pyro_slam.geometry import wrap_angle


class ParseError(ValueError):
    """A log file is malformed. ``str(err)`` is ``"file:line: reason"`` (``"file: reason"`` when
    the problem has no line, e.g. an empty log)."""

    def __init__(self, path: str | os.PathLike, lineno: int | None, reason: str):
        self.path, self.lineno, self.reason = str(path), lineno, reason
        where = self.path if lineno is None else f"{self.path}:{lineno}"
        super().__init__(f"{where}: {reason}")


def open_text(path: str | os.PathLike, what: str, opener=open):
    """The text file ``path`` opened for reading (``opener``: e.g. ``gzip.open``), a byte-order
    mark skipped; :class:`FileNotFoundError` where it is missing and :class:`ParseError` where it
    is a folder or cannot be read, naming it as ``what`` (e.g. ``"CARMEN log"``)."""
    path = Path(path)
    if path.is_dir():
        raise ParseError(path, None, f"is a folder, not a {what}")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such {what}")
    try:
        return opener(path, "rt", encoding="utf-8-sig", errors="replace")
    except OSError as e:
        raise ParseError(path, None, f"cannot read the {what} ({e.strerror or e})") from None


_NUMBER = re.compile(
    r"[+-]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|nan|inf|infinity)", re.IGNORECASE | re.ASCII
)


def parse_float(token: str) -> float:
    """``float(token)`` for plain ASCII decimal / scientific / nan / inf tokens only.

    (Python's ``float`` also takes ``"1_0"`` and non-ASCII digits, which no log writer emits.)
    Raises ``ValueError`` naming the token otherwise.
    """
    if not _NUMBER.fullmatch(token):
        raise ValueError(f"non-numeric value {token[:40]!r}")
    return float(token)


def parse_floats(tokens: list[str]) -> np.ndarray:
    """Vectorised :func:`parse_float` for the long range lists; ``[len(tokens)]`` float64."""
    try:
        out = np.array(tokens, dtype=np.float64)
    except ValueError:
        out = None
    if out is None or not all(_NUMBER.fullmatch(t) for t in tokens):
        for t in tokens:  # find the culprit and raise with its text
            parse_float(t)
    return out


# --- SE(2) in numpy -------------------------------------------------------------------------


def compose(z: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Apply robot-frame increments ``u`` ``[..., 3]`` to poses ``z`` ``[..., 3]``."""
    c, s = np.cos(z[..., 2]), np.sin(z[..., 2])
    x = z[..., 0] + c * u[..., 0] - s * u[..., 1]
    y = z[..., 1] + s * u[..., 0] + c * u[..., 1]
    return np.stack([x, y, wrap_angle(z[..., 2] + u[..., 2])], axis=-1)


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Increment ``u`` ``[..., 3]`` with ``compose(a, u) == b`` (``b`` seen from ``a``)."""
    d = b[..., :2] - a[..., :2]
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]
    return np.stack([dx, dy, wrap_angle(b[..., 2] - a[..., 2])], axis=-1)


def integrate(origin, controls: np.ndarray, control_model: str = "odometry_delta") -> np.ndarray:
    """Dead-reckon ``[T, 3]`` poses from ``origin`` ``[3]`` and ``controls`` ``[T-1, D_u]``."""
    poses = np.empty((len(controls) + 1, 3))
    poses[0] = np.asarray(origin, dtype=np.float64)
    poses[0, 2] = wrap_angle(poses[0, 2])
    u = np.asarray(controls, dtype=np.float64)
    for t in range(len(u)):
        if control_model == "odometry_delta":
            poses[t + 1] = compose(poses[t], u[t])
        elif control_model == "rotate_forward":
            h = poses[t, 2] + u[t, 0]
            poses[t + 1] = [
                poses[t, 0] + u[t, 1] * math.cos(h),
                poses[t, 1] + u[t, 1] * math.sin(h),
                wrap_angle(h),
            ]
        else:
            raise ValueError(f"unknown control_model {control_model!r}")
    return poses


def odometry_poses(traversal: Traversal, origin=None) -> np.ndarray:
    """Dead-reckoned odometry trajectory ``[T, 3]``: the controls integrated with the
    traversal's control model from ``origin [3]``. The package's one odometry helper.

    Default origin: ``metadata["odometry_origin"]`` (set by the readers: the odometry pose the
    first control starts from, so for mit-csail.clf this reproduces the logged raw odometry);
    for a traversal without it, or sliced from a later step (whose metadata still names the
    original first step), :attr:`~pyro_slam.data.Traversal.start_pose`. Pass
    ``traversal.start_pose`` for the dead reckoning in SLAM's frame.
    """
    meta = traversal.metadata
    if origin is None:
        sliced = meta.get("sliced_from", [0])[0] != 0
        origin = meta.get("odometry_origin") if not sliced else None
    if origin is None:
        origin = traversal.start_pose
    return integrate(origin, traversal.controls, meta.get("control_model", "rotate_forward"))


# --- pairing odometry with scans ----------------------------------------------------------


def poses_at(times: np.ndarray, stamps: np.ndarray, poses: np.ndarray, method: str = "interp"):
    """Odometry poses at query ``times`` ``[T]`` from records ``stamps`` ``[K]``, ``poses``
    ``[K, 3]`` (any order). ``"nearest"``: the record nearest in time (the last one in record
    order on ties); ``"interp"``: an exact time match if there is one, else linear
    interpolation between the neighbouring records in time (heading unwrapped), clamped at the
    ends. Returns ``([T, 3] poses, [T] distance to the nearest record in s)``.
    """
    times = np.asarray(times, dtype=np.float64)
    order = np.argsort(stamps, kind="stable")
    s, p = stamps[order], poses[order]
    # index of the last record with stamp <= t, and the first with stamp >= t
    hi = np.clip(np.searchsorted(s, times, side="left"), 0, len(s) - 1)
    lo = np.clip(np.searchsorted(s, times, side="right") - 1, 0, len(s) - 1)
    nearest = np.where(np.abs(s[lo] - times) <= np.abs(s[hi] - times), lo, hi)
    gap = np.abs(s[nearest] - times)
    if method == "nearest":
        return p[nearest].copy(), gap
    if method != "interp":
        raise ValueError(f"unknown pairing method {method!r}; expected 'nearest' or 'interp'")
    exact = s[lo] == times
    span = s[hi] - s[lo]
    w = np.where(span > 0, (times - s[lo]) / np.where(span > 0, span, 1.0), 0.0)
    w = np.clip(w, 0.0, 1.0)[:, None]
    dtheta = wrap_angle(p[hi, 2] - p[lo, 2])
    out = p[lo] + w * (p[hi] - p[lo])
    out[:, 2] = wrap_angle(p[lo, 2] + w[:, 0] * dtheta)
    out[exact] = p[lo[exact]]
    return out, gap


# --- ranges and assembly ------------------------------------------------------------------


MAX_RANGE = 1e6  # a reading beyond this (metres) is corrupt, never a return


def sentinel_max_range(ranges: np.ndarray, min_count: int = 2, min_fraction: float = 1e-3):
    """Guess the sensor's "no return" value from the data: the largest finite reading if it
    repeats (at least ``min_count`` times and ``min_fraction`` of the readings, e.g. 81.91 m in
    mit-csail.clf). Otherwise the largest reading rounded up to the next metre (+1 m), so that no
    real return is masked. Returns ``(max_range, how)``."""
    finite = ranges[np.isfinite(ranges) & (ranges > 0) & (ranges <= MAX_RANGE)]
    if finite.size == 0:
        return 1.0, "default (no valid reading)"
    top = float(finite.max())
    count = int(np.count_nonzero(finite == top))
    if count >= max(min_count, min_fraction * finite.size):
        return top, f"data sentinel ({count} readings at {top:g})"
    return float(math.floor(top) + 1.0), "largest reading rounded up"


def mask_ranges(ranges: np.ndarray, max_range: float, min_range: float = 0.0):
    """Mask invalid readings: non-finite, ``<= min_range`` (and ``<= 0``) or ``>= max_range``.

    Returns ``(observations [T, B] float64 with masked entries set to max_range, mask [T, B])``.
    """
    r = np.asarray(ranges, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        mask = np.isfinite(r) & (r > max(min_range, 0.0)) & (r < max_range)
    return np.where(mask, r, max_range), mask


def monotone_timestamps(ts: np.ndarray) -> tuple[np.ndarray, int]:
    """Running maximum of ``ts`` ``[T]`` (Traversal requires non-decreasing timestamps), and
    how many entries it changed (log timestamps jitter backwards occasionally)."""
    ts = np.asarray(ts, dtype=np.float64)
    fixed = np.maximum.accumulate(ts) if ts.size else ts
    return fixed, int(np.count_nonzero(fixed != ts))


def build_traversal(
    ranges: np.ndarray,  # [T, B] raw readings
    beam_angles: np.ndarray,  # [B]
    max_range: float,
    odom_start: np.ndarray,  # [T, 3] odometry pose each control starts from
    odom_end: np.ndarray,  # [T, 3] odometry pose at each scan
    timestamps: np.ndarray,  # [T]
    poses: np.ndarray | None,  # [T, 3] logged / reference poses, or None
    metadata: dict[str, Any],
    *,
    beam_stride: int = 1,
    min_range: float = 0.0,
) -> Traversal:
    """Common tail of every reader: stride, mask, odometry controls, timestamps, metadata.

    ``controls[t] = relative(odom_start[t], odom_end[t + 1])``: for a plain odometry stream
    ``odom_start == odom_end``; logs that re-anchor odometry at corrected poses after every scan
    (GMapping output) pass the anchors as ``odom_start``.
    """
    if beam_stride < 1:
        raise ValueError(f"beam_stride must be >= 1, got {beam_stride}")
    ranges = np.asarray(ranges, dtype=np.float64)[:, ::beam_stride]
    obs, mask = mask_ranges(ranges, max_range, min_range)
    controls = relative(odom_start[:-1], odom_end[1:])  # [T-1, 3]
    ts, clamped = monotone_timestamps(timestamps)
    meta = dict(metadata)
    meta.update(
        control_model="odometry_delta",
        odometry_origin=[float(v) for v in odom_start[0]],
        timestamps_clamped=clamped,
        masked_fraction=float(1.0 - mask.mean()),
    )
    meta.setdefault("sensor", {}).update(
        num_beams=int(obs.shape[1]), beam_stride=beam_stride, max_range=float(max_range)
    )
    try:
        return _traversal(obs, controls, beam_angles, beam_stride, max_range, poses, mask, ts, meta)
    except DatasetError as e:  # name the log, not the traversal built from it
        src = str(metadata.get("file", "log"))
        raise DatasetError(str(e).replace("traversal:", f"{src}:", 1)) from None


def _traversal(obs, controls, beam_angles, beam_stride, max_range, poses, mask, ts, meta):
    return Traversal(
        observations=obs,
        controls=controls,
        walls=np.zeros((0, 4)),
        beam_angles=np.asarray(beam_angles, dtype=np.float64)[::beam_stride],
        max_range=float(max_range),
        poses=None if poses is None else np.column_stack([poses[:, :2], wrap_angle(poses[:, 2])]),
        obs_mask=mask,
        timestamps=ts,
        metadata=meta,
    )
