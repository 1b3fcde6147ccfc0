"""CARMEN laser logs (``.clf`` / ``.log``, optionally gzipped) -> :class:`Traversal`.

Parsed messages (everything else -- ``PARAM`` lines other than the laser's field of view and
maximum range, ``NEFF``, ``RAWLASER*``, ``#`` comments, blank lines -- is counted in
``metadata["ignored"]`` and otherwise skipped)::

    FLASER n r1..rn x y theta odom_x odom_y odom_theta ipc_timestamp hostname logger_timestamp
    ODOM x y theta tv rv accel ipc_timestamp hostname logger_timestamp
    ROBOTLASER1 laser_type start_angle fov angular_res max_range accuracy remission_mode
        n r1..rn k rem1..remk laser_x laser_y laser_theta robot_x robot_y robot_theta
        tv rv forward_safety side_safety turn_axis ipc_timestamp hostname logger_timestamp

Conventions of the resulting traversal (see :func:`read_carmen`):

* ``observations`` ``[T, B]`` metres, one row per scan (``FLASER``, or ``ROBOTLASER1`` when the
  log has no ``FLASER``); ``obs_mask`` is False for no-return / invalid readings, which are
  replaced by ``max_range``.
* ``beam_angles`` ``[B]``: ``FLASER`` beams from right to left, in CARMEN's own geometry for
  its beam counts (180 beams: -90 to +89 deg at 1 deg, :func:`flaser_angles`), or spread evenly
  over ``PARAM laser_front_laser_fov``, ends included;
  ``ROBOTLASER1``: ``start_angle + i * angular_res`` plus the laser's mounting yaw.
* ``controls`` ``[T-1, 3]`` robot-frame odometry increments (``control_model =
  "odometry_delta"``), from ``ODOM`` lines when present (``prefer="odom"``), else from the
  scans' odometry fields.
* ``poses`` ``[T, 3]``: the scans' logged poses when they differ from the odometry (e.g.
  ``intel.gfs.log``, whose ``FLASER`` poses are GMapping-corrected), else ``None``.
  :func:`pyro_slam.io.odometry_poses` rebuilds the raw-odometry trajectory from the controls.
"""

from __future__ import annotations

import gzip
import math
import os
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pyro_slam.data import Traversal, atomic_write
from pyro_slam.geometry import wrap_angle
from pyro_slam.io.common import (
    ParseError,
    build_traversal,
    odometry_poses,
    open_text,
    parse_float,
    parse_floats,
    poses_at,
    sentinel_max_range,
)
from slamdata.traversal import MAX_TIMESTAMP

SCAN_MESSAGES = ("FLASER", "ROBOTLASER1")
FOV_PARAMS = ("laser_front_laser_fov",)  # degrees
# beam counts with CARMEN's own angular increment (deg), for FLASER lines without a field of view
CARMEN_INCREMENT_DEG = {181: 1.0, 180: 1.0, 361: 0.5, 360: 0.5, 401: 0.25, 400: 0.25}
MAX_RANGE_PARAMS = ("robot_front_laser_max", "laser_front_laser_max_range")  # metres
SENSOR_PARAMS = FOV_PARAMS + MAX_RANGE_PARAMS  # applied (and checked), not ignored
MIN_FOV_DEG = 1e-3  # a narrower field of view is a corrupt value, not a laser
MAX_REASONS = 5  # skip reasons kept in metadata
MAX_ABS = 1e15  # |config value| beyond this is corruption (keeps maths finite)
MAX_COORD = 1e6  # |pose| in metres: a robot 1000 km from its origin is a corrupt line
MAX_TIME_STEP_BACK = 1.0  # s: scan stamps may jitter back this much (clamped), not more


@dataclass
class Scan:
    """One parsed scan line."""

    kind: str  # "FLASER" | "ROBOTLASER1"
    line: int
    ranges: np.ndarray  # [n]
    pose: np.ndarray  # [3] logged pose (FLASER x y theta, ROBOTLASER1 robot pose)
    odom: np.ndarray  # [3] odometry fields (ROBOTLASER1: the robot pose again)
    time: float  # ipc_timestamp
    config: tuple = ()  # ROBOTLASER1: (start_angle, angular_res, max_range, laser yaw offset)
    anchor: np.ndarray | None = None  # [3] pose an ODOM stream re-anchored at after this scan


@dataclass
class CarmenLog:
    """Everything :func:`parse_carmen` extracted from a log, in file order."""

    source: str
    scans: list[Scan] = field(default_factory=list)
    odom_pose: list[np.ndarray] = field(default_factory=list)  # K x [3]
    odom_time: list[float] = field(default_factory=list)  # K
    odom_line: list[int] = field(default_factory=list)  # K
    params: dict[str, str] = field(default_factory=dict)
    counts: Counter = field(default_factory=Counter)  # parsed messages by type
    ignored: Counter = field(default_factory=Counter)  # ignored lines by type
    skipped: int = 0
    skip_reasons: list[str] = field(default_factory=list)


# --- line parsers: tokens -> record, raising ValueError(reason) ------------------------------


def _fields(tokens: list[str], start: int, n: int, what: str, limit: float = MAX_ABS) -> np.ndarray:
    """``n`` finite floats from ``tokens[start:]`` with ``|v| <= limit`` (``what`` names them
    in errors)."""
    vals = np.array([parse_float(t) for t in tokens[start : start + n]])
    if not np.all(np.isfinite(vals)):
        raise ValueError(f"non-finite value in {what}: {' '.join(tokens[start : start + n])}")
    if np.any(np.abs(vals) > limit):
        raise ValueError(f"value out of range (|v| > {limit:g}) in {what}")
    return vals


def _count(tokens: list[str], i: int, what: str) -> int:
    tok = tokens[i]
    if not tok.isascii() or not tok.isdigit():
        raise ValueError(f"{what} must be a non-negative integer, got {tok[:40]!r}")
    return int(tok)


def _expect_len(tokens: list[str], expected: int, what: str) -> None:
    if len(tokens) != expected:
        got = len(tokens)
        raise ValueError(f"wrong number of fields for {what}: expected {expected}, got {got}")


def parse_flaser(tokens: list[str], line: int) -> Scan:
    if len(tokens) < 2:
        raise ValueError("wrong number of fields for FLASER: missing num_readings")
    n = _count(tokens, 1, "num_readings")
    if n == 0:
        raise ValueError("FLASER with 0 readings")
    if len(tokens) != n + 11:
        raise ValueError(
            f"wrong number of fields: num_readings={n} needs {n + 11} fields "
            f"(n readings + 6 pose + 3 time/host), got {len(tokens)}"
        )
    ranges = parse_floats(tokens[2 : 2 + n])
    poses = _fields(tokens, 2 + n, 6, "poses", MAX_COORD)
    time = _fields(tokens, 8 + n, 1, "ipc_timestamp", MAX_TIMESTAMP)[0]
    return Scan("FLASER", line, ranges, poses[:3], poses[3:], float(time))


def parse_robotlaser1(tokens: list[str], line: int) -> Scan:
    if len(tokens) < 10:
        raise ValueError(f"wrong number of fields for ROBOTLASER1: got {len(tokens)}")
    head = _fields(tokens, 2, 5, "laser config")  # start fov res max_range accuracy
    n = _count(tokens, 8, "num_readings")
    if n == 0:
        raise ValueError("ROBOTLASER1 with 0 readings")
    if len(tokens) < n + 10:
        raise ValueError(f"wrong number of fields: num_readings={n} but only {len(tokens)} fields")
    k = _count(tokens, 9 + n, "num_remissions")
    _expect_len(tokens, n + k + 24, f"ROBOTLASER1 with {n} readings and {k} remissions")
    ranges = parse_floats(tokens[9 : 9 + n])
    parse_floats(tokens[10 + n : 10 + n + k])
    rest = _fields(tokens, 10 + n + k, 11, "poses / velocities", MAX_COORD)  # laser, robot, 5 more
    time = _fields(tokens, 21 + n + k, 1, "ipc_timestamp", MAX_TIMESTAMP)[0]
    laser, robot = rest[:3], rest[3:6]
    config = (head[0], head[2], head[3], float(wrap_angle(laser[2] - robot[2])))
    return Scan("ROBOTLASER1", line, ranges, robot, robot.copy(), float(time), config)


def parse_odom(tokens: list[str]) -> tuple[np.ndarray, float]:
    _expect_len(tokens, 10, "ODOM")
    vals = _fields(tokens, 1, 3, "pose", MAX_COORD)
    return vals, float(_fields(tokens, 7, 1, "ipc_timestamp", MAX_TIMESTAMP)[0])


# --- the file loop -----------------------------------------------------------------------------


def _open_lines(source) -> tuple[str, Iterable[str], bool]:
    """``(name, lines, opened_here)`` for a path (``.gz`` transparently) or an iterable."""
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        opener = gzip.open if path.suffix == ".gz" else open
        # (a byte-order mark is not part of the first line's message name)
        return str(path), open_text(path, "CARMEN log", opener), True
    return "<lines>", source, False


def parse_carmen(source, *, lenient: bool = False, name: str | None = None) -> CarmenLog:
    """Parse a CARMEN log (path, or any iterable of text lines) into a :class:`CarmenLog`.

    Strict mode raises :class:`ParseError` ``file:line: reason`` at the first malformed line;
    lenient mode skips it and counts it (``log.skipped``, first reasons in ``log.skip_reasons``).
    Scans whose beam count (or ``ROBOTLASER1`` angle config) differs from the first scan of the
    same type are malformed too.

    An ``ODOM`` line that is the first ``ODOM`` after a scan, repeats that scan's logged pose and
    is stamped earlier than it marks a re-anchored odometry stream (GMapping's ``.gfs.log``
    output writes the corrected pose there, with a zero / garbage timestamp, and continues the
    odometry from it); it is stored as ``scan.anchor`` instead of as an odometry record.
    """
    src, lines, opened = _open_lines(source)
    src = name or src
    parser = _Parser(CarmenLog(src))
    try:
        for lineno, raw in enumerate(lines, start=1):
            tokens = (raw.lstrip("\ufeff") if lineno == 1 else raw).split()
            try:
                parser.line(tokens, lineno)
            except ValueError as e:
                if not lenient:
                    raise ParseError(src, lineno, str(e)) from None
                parser.skip(f"{src}:{lineno}: {e}")
    except (OSError, EOFError) as e:  # e.g. a truncated or corrupt .gz
        raise ParseError(src, None, f"cannot read ({type(e).__name__}: {e})") from e
    finally:
        if opened:
            lines.close()
    return parser.log


class _Parser:
    """The state of :func:`parse_carmen` over a log's lines: the first scan of each type (the
    reference for the rest) and the scan still waiting for its first ``ODOM``."""

    def __init__(self, log: CarmenLog):
        self.log = log
        self.first: dict[str, Scan] = {}
        self.latest: dict[str, float] = {}  # the latest timestamp of each scan type
        self.last_scan: Scan | None = None

    def skip(self, reason: str) -> None:
        self.log.skipped += 1
        if len(self.log.skip_reasons) < MAX_REASONS:
            self.log.skip_reasons.append(reason)

    def line(self, tokens: list[str], lineno: int) -> None:
        """Parse one line's ``tokens``; ``ValueError`` for a malformed line."""
        log = self.log
        kind = tokens[0] if tokens else ""
        if not tokens or kind.startswith("#"):
            log.ignored["#" if tokens else "blank"] += 1
            return
        if kind in SCAN_MESSAGES:
            self._scan(kind, tokens, lineno)
        elif kind == "ODOM":
            self._odom(tokens, lineno)
        elif kind == "PARAM":
            if not self._param(tokens):
                log.ignored[kind] += 1
                return
        else:
            log.ignored[kind[:32]] += 1
            return
        log.counts[kind] += 1

    def _scan(self, kind: str, tokens: list[str], lineno: int) -> None:
        scan = (parse_flaser if kind == "FLASER" else parse_robotlaser1)(tokens, lineno)
        ref = self.first.setdefault(kind, scan)
        if len(scan.ranges) != len(ref.ranges):
            raise ValueError(
                f"n readings {len(scan.ranges)} does not match the first {kind}'s "
                f"{len(ref.ranges)} (line {ref.line})"
            )
        if scan.config[:2] != ref.config[:2]:
            raise ValueError(f"{kind} angle config differs from line {ref.line}")
        latest = self.latest.get(kind, -math.inf)
        if scan.time < latest - MAX_TIME_STEP_BACK:  # (lenient: the line is skipped)
            raise ValueError(
                f"timestamp {scan.time:.6f} is {latest - scan.time:.3f} s earlier than an "
                "earlier scan's: the scans are not in time order"
            )
        self.latest[kind] = max(latest, scan.time)
        self.log.scans.append(scan)
        self.last_scan = scan

    def _odom(self, tokens: list[str], lineno: int) -> None:
        pose, time = parse_odom(tokens)
        if _is_anchor(self.last_scan, pose, time):
            self.last_scan.anchor = pose
        else:
            self.log.odom_pose.append(pose)
            self.log.odom_time.append(time)
            self.log.odom_line.append(lineno)
        self.last_scan = None

    def _param(self, tokens: list[str]) -> bool:
        """Record a ``PARAM``; whether the reader applies it (the sensor's)."""
        if len(tokens) < 3:
            raise ValueError("PARAM needs a name and a value")
        _check_param(tokens[1], tokens[2])
        self.log.params[tokens[1]] = tokens[2]
        return tokens[1] in SENSOR_PARAMS


def _check_param(name: str, value: str) -> None:
    """A sensor ``PARAM`` the reader applies must be a plausible number: a field of view in
    ``[MIN_FOV_DEG, 360]`` degrees, a maximum range in ``(0, MAX_COORD]`` metres."""
    if name not in SENSOR_PARAMS:
        return
    fov = name in FOV_PARAMS
    low, high, unit = (MIN_FOV_DEG, 360.0, "degrees") if fov else (0.0, MAX_COORD, "metres")
    try:
        v = parse_float(value)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and low <= v <= high and v > 0):
        what = "the laser's field of view" if fov else "the laser's maximum range"
        raise ValueError(
            f"PARAM {name} {value[:40]}: {what} must be a number in "
            f"{'[' if low else '('}{low:g}, {high:g}] {unit}"
        )


def _is_anchor(scan: Scan | None, pose: np.ndarray, time: float) -> bool:
    if scan is None or time >= scan.time:
        return False
    d = np.abs(pose - scan.pose)
    d[2] = abs(float(wrap_angle(d[2])))
    return bool(np.all(d < 1e-6))


# --- CarmenLog -> Traversal ----------------------------------------------------------------------


def flaser_angles(n: int, fov_deg: float | None = None) -> np.ndarray:
    """The directions ``[n]`` (rad, right to left) of a ``FLASER`` scan's ``n`` beams. With
    a logged field of view, ``fov_deg`` spread evenly, ends included. Without one, CARMEN's own
    geometry (``carmen_laser_get_fov``, ``carmen_laser_get_angle_increment``): 181 beams at 1
    deg and 361 at 0.5 deg span 180 deg from -90 deg, 401 at 0.25 deg span 100 deg; 180, 360
    and 400 beams are those scans with the last beam dropped (180 beams: -90 to +89 deg, as
    GMapping reads them); any other count spreads over 180 deg, ends included."""
    if fov_deg is None and n in CARMEN_INCREMENT_DEG:
        inc = CARMEN_INCREMENT_DEG[n]
        full = n if n % 2 else n + 1  # the scan the last beam was dropped from
        return np.radians(-0.5 * (full - 1) * inc + inc * np.arange(n))
    fov = math.radians(fov_deg or 180.0)
    return np.linspace(-fov / 2, fov / 2, n) if n > 1 else np.zeros(1)


def _param(log: CarmenLog, names: tuple[str, ...], upper: float = MAX_ABS) -> float | None:
    """The first of the ``PARAM`` values ``names`` that is a number in ``(0, upper]``."""
    for key in names:
        if key in log.params:
            try:
                value = parse_float(log.params[key])
            except ValueError:
                continue
            if 0 < value <= upper:
                return value
    return None


def _odometry_from_odom_lines(log: CarmenLog, scans: list[Scan], method: str):
    """Odometry at each scan ``[T, 3]`` and the pose each control starts from ``[T, 3]``.

    Records are grouped into segments split at anchors; a scan's odometry is looked up (by
    ``method``, see :func:`poses_at`) among the records of its own segment.
    """
    rec_pose = np.array(log.odom_pose)  # [K, 3]
    rec_time = np.array(log.odom_time)  # [K]
    anchored = [s for s in log.scans if s.anchor is not None]
    anchors = np.array([s.line for s in anchored], dtype=np.int64)  # segment boundaries
    rec_seg = np.searchsorted(anchors, np.array(log.odom_line), side="left")  # [K]
    scan_seg = np.searchsorted(anchors, np.array([s.line for s in scans]), side="left")  # [T]
    times = np.array([s.time for s in scans])
    end, gap = np.empty((len(scans), 3)), np.zeros(len(scans))
    fallback = 0
    for seg in np.unique(scan_seg):
        at, rec = scan_seg == seg, rec_seg == seg
        if rec.any():
            end[at], gap[at] = poses_at(times[at], rec_time[rec], rec_pose[rec], method)
        elif seg > 0:  # no odometry since the last anchor: no motion as far as we know
            fallback += int(at.sum())
            end[at] = anchored[seg - 1].anchor
        else:  # no ODOM before the first anchor: the scans' own odometry fields
            fallback += int(at.sum())
            end[at] = [s.odom for s, here in zip(scans, at) if here]
    start = np.array([s.anchor if s.anchor is not None else e for s, e in zip(scans, end)])
    info = {
        "odometry_anchors": len(anchors),
        "odometry_max_time_gap": float(gap.max()) if len(gap) else 0.0,
        "odometry_fallbacks": fallback,
    }
    return start, end, info


def _check_time_order(source: str, scans: list[Scan]) -> None:
    """Refuse scans whose timestamps run backwards by more than a jitter (odometry would be
    paired with the wrong scans), naming the line."""
    times = np.array([s.time for s in scans])  # [T]
    back = np.maximum.accumulate(times) - times  # [T] how far each stamp lies behind the last
    if back.size and back.max() > MAX_TIME_STEP_BACK:
        i = int(np.argmax(back > MAX_TIME_STEP_BACK))
        raise ParseError(
            source,
            scans[i].line,
            f"timestamp {times[i]:.6f} is {back[i]:.3f} s earlier than an "
            "earlier scan's: the scans are not in time order",
        )


def carmen_to_traversal(
    log: CarmenLog,
    *,
    beam_stride: int = 1,
    max_range: float | None = None,
    prefer: str = "odom",
    pairing: str = "interp",
) -> Traversal:
    """Turn a parsed log into a traversal; arguments as in :func:`read_carmen`."""
    if prefer not in ("odom", "flaser"):
        raise ValueError(f"prefer must be 'odom' or 'flaser', got {prefer!r}")
    kind = "FLASER" if log.counts["FLASER"] else "ROBOTLASER1"
    scans = [s for s in log.scans if s.kind == kind]
    if not scans:
        raise ParseError(log.source, None, "no scans (FLASER / ROBOTLASER1 lines) in the log")
    _check_time_order(log.source, scans)
    ranges = np.stack([s.ranges for s in scans])  # [T, n]
    n = ranges.shape[1]
    sensor: dict = {"type": kind, "num_beams_raw": n}
    if kind == "FLASER":
        angles = flaser_angles(n, _param(log, FOV_PARAMS, upper=360.0))
        sensor["fov_deg"] = math.degrees(angles[-1] - angles[0])
        logged_max = _param(log, MAX_RANGE_PARAMS)
        logged_how = "PARAM"
    else:
        start, res, logged_max, yaw = scans[0].config
        angles = wrap_angle(start + np.arange(n) * res + yaw)
        sensor.update(fov_deg=math.degrees(res * (n - 1)), laser_yaw_offset=yaw)
        logged_how = "ROBOTLASER1 max_range"
    if max_range is not None:
        sensor["max_range_source"] = "argument"
    elif logged_max is not None and logged_max > 0:
        max_range, sensor["max_range_source"] = logged_max, logged_how
    else:
        max_range, sensor["max_range_source"] = sentinel_max_range(ranges)

    odom_fields = np.array([s.odom for s in scans])  # [T, 3]
    meta_odom: dict = {}
    if prefer == "odom" and log.odom_pose:
        start, end, meta_odom = _odometry_from_odom_lines(log, scans, pairing)
        meta_odom["odometry_source"] = f"ODOM lines ({pairing} in time to each scan)"
    else:
        start = end = odom_fields
        meta_odom["odometry_source"] = f"{kind} odometry fields"

    logged = np.array([s.pose for s in scans])  # [T, 3]
    diff = np.abs(logged - end)
    diff[:, 2] = np.abs(wrap_angle(logged[:, 2] - end[:, 2]))
    differs = float(diff.max()) > 1e-9
    meta = {
        "source": "carmen",
        "file": log.source,
        "scan_message": kind,
        "counts": dict(log.counts),
        "ignored": dict(log.ignored),
        "skipped_lines": log.skipped,
        "skip_reasons": list(log.skip_reasons),
        "params": dict(log.params),
        "pose_source": f"{kind} logged pose (differs from odometry)" if differs else None,
        "sensor": sensor,
        **meta_odom,
    }
    return build_traversal(
        ranges,
        angles,
        max_range,
        start,
        end,
        np.array([s.time for s in scans]),
        logged if differs else None,
        meta,
        beam_stride=beam_stride,
    )


def read_carmen(
    path: str | os.PathLike,
    *,
    lenient: bool = False,
    beam_stride: int = 1,
    max_range: float | None = None,
    prefer: str = "odom",
    pairing: str = "interp",
) -> Traversal:
    """Read a CARMEN log into a :class:`Traversal` (see the module docstring for conventions).

    Args:
        path: ``.clf`` / ``.log`` / ``.carmen`` file, optionally ``.gz``.
        lenient: skip malformed lines (``metadata["skipped_lines"]``, ``["skip_reasons"]``)
            instead of raising :class:`ParseError`.
        beam_stride: keep every ``beam_stride``-th beam.
        max_range: override the range limit; default: ``ROBOTLASER1``'s field, else ``PARAM
            robot_front_laser_max``, else the data's repeated maximum (81.91 in mit-csail.clf).
        prefer: ``"odom"`` takes odometry from ``ODOM`` lines when there are any, ``"flaser"``
            always from the scans' own odometry fields.
        pairing: ``"interp"`` or ``"nearest"``: how ``ODOM`` records are matched to scan times.
    Raises:
        ParseError: malformed line (strict mode) or no scans at all.
    """
    log = parse_carmen(path, lenient=lenient)
    return carmen_to_traversal(
        log, beam_stride=beam_stride, max_range=max_range, prefer=prefer, pairing=pairing
    )


def write_carmen(traversal: Traversal, path: str | os.PathLike) -> Path:
    """Write ``traversal`` as ``PARAM`` + ``FLASER`` lines that :func:`read_carmen` reads back.

    Logged pose = ``traversal.poses`` (or the odometry when absent), odometry fields =
    :func:`odometry_poses`, timestamps = ``traversal.timestamps`` (or 0.1 s steps), masked
    readings written as ``max_range``. Beams must be evenly spaced and symmetric about the
    heading (written with their field of view), or CARMEN's own geometry for their count
    (:func:`flaser_angles`, written without one): FLASER cannot express anything else. Numbers
    are written in full precision.
    """
    a = np.asarray(traversal.beam_angles, dtype=np.float64)
    step = np.diff(a)
    even = len(a) < 2 or (abs(a[0] + a[-1]) <= 1e-9 and np.ptp(step) <= 1e-9 and step[0] > 0)
    native = len(a) in CARMEN_INCREMENT_DEG and np.abs(a - flaser_angles(len(a))).max() <= 1e-9
    if not (even or native):
        raise ValueError(
            "write_carmen needs evenly spaced beam angles symmetric about 0, or CARMEN's own "
            "for their count"
        )
    odom = odometry_poses(traversal)  # [T, 3]
    poses = odom if traversal.poses is None else np.asarray(traversal.poses, dtype=np.float64)
    T = traversal.num_steps
    ts = traversal.timestamps if traversal.timestamps is not None else np.arange(T) * 0.1
    obs = np.asarray(traversal.observations, dtype=np.float64)
    if traversal.obs_mask is not None:
        obs = np.where(traversal.obs_mask, obs, traversal.max_range)
    fov = math.degrees(a[-1] - a[0]) if len(a) > 1 else 180.0
    out = ["# written by pyro_slam.io.write_carmen"]
    if even:
        out.append(f"PARAM {FOV_PARAMS[0]} {fov!r}")
    out.append(f"PARAM {MAX_RANGE_PARAMS[0]} {float(traversal.max_range)!r}")
    for t in range(T):
        nums = [*obs[t], *poses[t], *odom[t]]
        stamp = repr(float(ts[t]))
        out.append(f"FLASER {len(a)} {' '.join(map(repr, map(float, nums)))} {stamp} pyro {stamp}")
    text = "\n".join(out) + "\n"
    atomic_write(Path(path), lambda f: f.write(text.encode()))
    return Path(path)
