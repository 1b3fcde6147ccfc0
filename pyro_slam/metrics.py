"""Trajectory metrics: localisation error over time, error relative to distance travelled, ATE.

Errors are Euclidean position errors in the traversal's units (the unit-square maze for the
simulator, metres for real logs). ATE uses the `evo` package (a well-tested reference
implementation of Sturm et al.'s absolute trajectory error); :func:`summary` reports it both
unaligned (``ate_unaligned``: SLAM is anchored at the known start pose) and after the
least-squares rigid SE(2) alignment of the whole trajectory (``ate_aligned``, as ``evo_ape
-a``). evo is the optional extra ``[eval]``, and without it :func:`summary` leaves the ATE out.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from .data import Traversal, atomic_write
from .extras import require
from .geometry import wrap_angle

try:  # the [eval] extra
    from evo.core import metrics as evo_metrics
    from evo.core import sync as evo_sync
    from evo.core.trajectory import PoseTrajectory3D
except ImportError:
    evo_metrics = evo_sync = PoseTrajectory3D = None

HAVE_EVO = evo_metrics is not None


def localisation_error(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Euclidean position error per step: ``est, true [T, >=2]`` -> ``[T]``."""
    est, true = np.asarray(est), np.asarray(true)
    if est.shape[0] != true.shape[0]:
        raise ValueError(f"trajectory lengths differ: {est.shape[0]} vs {true.shape[0]}")
    return np.linalg.norm(est[:, :2] - true[:, :2], axis=1)


def heading_error(a, b) -> np.ndarray:
    """Absolute angular difference in ``[0, pi]`` (arrays of headings, rad)."""
    return np.abs(wrap_angle(np.asarray(a) - np.asarray(b)))


def distance_travelled(true: np.ndarray) -> np.ndarray:
    """Cumulative path length ``[T]`` (0 at the start)."""
    steps = np.linalg.norm(np.diff(np.asarray(true)[:, :2], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def relative_error(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Localisation error divided by the distance travelled so far ``[T]`` (NaN-free: 0 at t=0)."""
    d = distance_travelled(true)
    e = localisation_error(est, true)
    return np.divide(e, d, out=np.zeros_like(e), where=d > 0)


def _to_evo(poses: np.ndarray, stamps: np.ndarray, feature: str):
    require(PoseTrajectory3D, feature, "evo", "eval")
    p = np.asarray(poses, dtype=np.float64)
    xyz = np.column_stack([p[:, 0], p[:, 1], np.zeros(len(p))])
    h = p[:, 2] / 2
    quat = np.column_stack([np.cos(h), np.zeros(len(p)), np.zeros(len(p)), np.sin(h)])  # wxyz
    return PoseTrajectory3D(positions_xyz=xyz, orientations_quat_wxyz=quat, timestamps=stamps)


def rigid_alignment(est: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares rigid SE(2) transform (Umeyama without scale) that maps the positions
    of ``est [T, >=2]`` onto those of ``true [T, >=2]``: ``(R [2, 2], t [2])``. Unlike evo's
    3-D alignment it is defined for a straight-line path too."""
    a, b = np.asarray(est, np.float64)[:, :2], np.asarray(true, np.float64)[:, :2]
    ma, mb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((b - mb).T @ (a - ma) / len(a))
    r = u @ np.diag([1.0, 1.0 if np.linalg.det(u @ vt) >= 0 else -1.0]) @ vt
    return r, mb - r @ ma


def align_poses(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """``est [T, 3]`` moved by :func:`rigid_alignment` onto ``true [T, 3]`` (positions and
    headings)."""
    est = np.asarray(est, dtype=np.float64)
    r, t = rigid_alignment(est, true)
    xy = est[:, :2] @ r.T + t
    return np.column_stack([xy, wrap_angle(est[:, 2] + math.atan2(r[1, 0], r[0, 0]))])


def ate(est: np.ndarray, true: np.ndarray, align: bool = False) -> dict:
    """Absolute trajectory error (translation) via ``evo``: rmse / mean / std / max, of ``est
    [T, 3]`` against ``true [T, 3]`` as they are, or (``align``) after the rigid SE(2)
    alignment of :func:`align_poses` (``evo_ape -a``); :class:`~pyro_slam.extras.MissingExtra`
    without the ``[eval]`` extra."""
    stamps = np.arange(len(true), dtype=np.float64)
    if align:
        est = align_poses(est, true)
    ref, e = _to_evo(true, stamps, "ATE"), _to_evo(est, stamps, "ATE")
    ref, e = evo_sync.associate_trajectories(ref, e)
    m = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    m.process_data((ref, e))
    s = m.get_all_statistics()
    return {k: float(s[k]) for k in ("rmse", "mean", "std", "max")}


def aligned_error(est: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, float]:
    """A diagnostic, not the benchmark's error: the position error per step ``[T]`` after the
    least-squares rigid alignment (rotation and translation, evo's Umeyama) of the whole
    trajectory ``est [T, 3]`` to ``true [T, 3]``, and that alignment's rotation (rad). What
    remains after it is the trajectory's shape error; the rest of the plain error is a rigid
    offset of the whole solution (map and poses) from the world frame."""
    stamps = np.arange(len(true), dtype=np.float64)
    ref, e = _to_evo(true, stamps, "aligned_error"), _to_evo(est, stamps, "aligned_error")
    rot, _, _ = e.align(ref, correct_scale=False)
    err = np.linalg.norm(e.positions_xyz[:, :2] - ref.positions_xyz[:, :2], axis=1)
    return err, float(np.arctan2(rot[1, 0], rot[0, 0]))


def std_over_error(std: np.ndarray, error: np.ndarray) -> float:
    """The posterior's calibration over one run: its time-averaged position std (``std [T,
    >= 2]``, the filter's ``x, y`` std; per step their hypot) over the time-averaged position
    error ``error [T]``: below 1 overconfident, above 2 underconfident. A calibrated isotropic
    Gaussian reads ``sqrt(2) / sqrt(pi / 2) = 1.13`` (its mean distance is ``sqrt(pi / 2)``
    per-axis stds)."""
    spread = float(np.hypot(std[:, 0], std[:, 1]).mean())
    return spread / max(float(np.mean(error)), 1e-12)


# the first steps the calibration figures leave out (the posterior starts at the known pose)
CALIBRATION_START = 100


def coverage(std: np.ndarray, est: np.ndarray, true: np.ndarray, k: float = 2.0) -> float:
    """The fraction of steps whose true position ``true [T, >= 2]`` lies inside the
    ``k``-sigma ellipse of the posterior (mean ``est [T, >= 2]``, per-axis std ``std [T, >=
    2]``): ``1 - exp(-k^2 / 2)`` for a calibrated 2-D Gaussian (0.865 at 2 sigma)."""
    d = (est[:, :2] - true[:, :2]) / np.maximum(std[:, :2], 1e-12)
    return float(np.mean((d**2).sum(1) <= k * k)) if len(d) else float("nan")


def calibration(std: np.ndarray, est: np.ndarray, true: np.ndarray, start: int = 0) -> dict:
    """How the posterior's spread compares with its error over one run, from step ``start``
    on (from the first step in a run no longer than twice ``start``): the time-averaged
    position std (``std [T, 3]``) over the time-averaged position error of ``est [T, 3]``, raw
    and after the rigid alignment of :func:`aligned_error` (1.13 for a calibrated isotropic
    Gaussian; below 1: overconfident; :func:`std_over_error`), and the 2-sigma
    :func:`coverage` of the true positions (0.865 for a calibrated Gaussian)."""
    start = start if len(true) > 2 * start else 0
    aligned = aligned_error(est, true)[0][start:]
    std, est, true = std[start:], est[start:], true[start:]
    return {
        "std_over_error": std_over_error(std, localisation_error(est, true)),
        "std_over_aligned_error": std_over_error(std, aligned),
        "coverage_2sigma": coverage(std, est, true),
    }


def frame_error(frame: float, true_frame: float = 0.0) -> float:
    """The error of an estimated walls' frame ``frame`` (rad; the heading observation's
    ``phi``) against ``true_frame``, modulo a quarter turn: in ``[-pi / 4, pi / 4)``."""
    return float(wrap_angle(frame - true_frame, math.pi / 2))


def summary(est: np.ndarray, true: np.ndarray) -> dict:
    """Final and mean errors, relative error and (with the ``[eval]`` extra) ATE for one run:
    ``ate_unaligned`` and ``ate_aligned`` (rigid SE(2) alignment, ``evo_ape -a``)."""
    e = localisation_error(est, true)
    r = relative_error(est, true)
    out = {
        "final_error": float(e[-1]),
        "mean_error": float(e.mean()),
        "final_relative_error": float(r[-1]),
        "distance_travelled": float(distance_travelled(true)[-1]),
    }
    if HAVE_EVO:
        out["ate_unaligned"] = ate(est, true)
        out["ate_aligned"] = ate(est, true, align=True)
    return out


def write_trajectory_tum(path, poses: np.ndarray, stamps: np.ndarray | None = None) -> None:
    """Export ``[T, 3]`` poses in TUM format (``t x y z qx qy qz qw``), readable by evo.

    Written with numpy rather than evo's ``file_interface``: evo is an optional extra
    (``[eval]``) and the format is one line per pose; the test suite reads the files back with
    evo's reader."""
    p = np.asarray(poses, dtype=np.float64)
    stamps = np.arange(len(p), dtype=np.float64) if stamps is None else np.asarray(stamps)
    h = p[:, 2] / 2
    rows = np.column_stack(
        [
            stamps,
            p[:, 0],
            p[:, 1],
            np.zeros(len(p)),
            np.zeros(len(p)),
            np.zeros(len(p)),
            np.sin(h),
            np.cos(h),
        ]
    )
    atomic_write(Path(path), lambda f: np.savetxt(f, rows, fmt="%.9f"))


def scan_points(traversal: Traversal, poses: np.ndarray, max_range: float | None = None):
    """Valid scan endpoints reprojected with ``poses [T, 3]``: ``([N, 2] xy, [N] step index)``.

    Readings that are masked or at / beyond ``max_range`` are left out (default: the range clip
    of a :func:`~pyro_slam.slam.prepare_traversal`-ed log, whose clipped readings are not
    endpoints, else the sensor's max range).
    """
    p = np.asarray(poses, dtype=np.float64)
    obs = np.asarray(traversal.observations, dtype=np.float64)
    if max_range is None:
        max_range = traversal.metadata.get("range_clip") or traversal.max_range
    ok = obs < min(max_range, traversal.max_range)
    if traversal.obs_mask is not None:
        ok &= traversal.obs_mask
    ang = p[:, 2:3] + traversal.beam_angles[None, :]  # [T, B]
    x = p[:, 0:1] + obs * np.cos(ang)
    y = p[:, 1:2] + obs * np.sin(ang)
    t = np.broadcast_to(np.arange(len(p))[:, None], obs.shape)
    return np.column_stack([x[ok], y[ok]]), t[ok]


def scan_consistency(
    traversal: Traversal,
    poses: np.ndarray,
    *,
    exclude: int = 10,
    cap: float = 1.0,
    max_range: float | None = None,
) -> dict:
    """How well scans reprojected with ``poses`` agree with the map the other scans make.

    Each scan's endpoints are matched to the nearest endpoint (``scipy.spatial.cKDTree``) of all
    scans at least ``exclude`` steps away in time (so a scan is not matched against its own
    neighbours, which agree under any smooth trajectory); distances are capped at ``cap`` (a
    region seen only once has no partner). Lower is better. Returns mean / median distance,
    the fraction of points within 0.1 and the number of points; where they are undefined (no
    endpoint, or a log too short for any scan to have a partner) they are None and ``reason``
    says why.
    """
    xy, t = scan_points(traversal, poses, max_range)
    blocks = t // exclude
    dist = np.full(len(xy), cap)
    paired = False
    for b in np.unique(blocks):
        q = blocks == b
        ref = np.abs(blocks - b) > 1  # at least `exclude` steps away
        if not ref.any():
            continue
        paired = True
        d, _ = cKDTree(xy[ref]).query(xy[q], distance_upper_bound=cap)
        dist[q] = np.minimum(d, cap)
    out = dict.fromkeys(("mean", "median", "frac_within_0.1"))
    out.update(points=len(dist), exclude_steps=exclude, cap=cap)
    if not len(dist):
        return {**out, "reason": "no valid scan endpoint below the range limit"}
    if not paired:
        steps = traversal.num_steps
        why = f"too short ({steps} steps): no two scans with endpoints {exclude} steps apart"
        return {**out, "reason": why}
    out.update(mean=float(dist.mean()), median=float(np.median(dist)))
    out["frac_within_0.1"] = float((dist < 0.1).mean())
    return out


# the scans on which a real log's scan consistency is quoted (pyro-slam slam's metrics.json,
# benchmarks.real_data, the docs), whatever beam stride and range clip SLAM itself ran with
SCAN_CONSISTENCY_BEAM_STRIDE = 2  # every 2nd beam
SCAN_CONSISTENCY_RANGE_QUANTILE = 99.0  # readings below this percentile of the valid ranges


def consistency_scans(traversal: Traversal) -> Traversal:
    """The scans of a real log that :func:`log_scan_consistency` scores: every
    :data:`SCAN_CONSISTENCY_BEAM_STRIDE`-th beam, readings clipped at the
    :data:`SCAN_CONSISTENCY_RANGE_QUANTILE` percentile of the log's valid ranges (rounded to
    0.01, as the ``real`` preset clips them), so that clipped readings are not endpoints."""
    valid = traversal.valid_ranges()
    tr = traversal.subsample_beams(SCAN_CONSISTENCY_BEAM_STRIDE)
    if valid.size:
        tr = tr.clip_ranges(round(float(np.percentile(valid, SCAN_CONSISTENCY_RANGE_QUANTILE)), 2))
    return tr


def log_scan_consistency(traversal: Traversal, poses: np.ndarray, scans=None) -> dict:
    """The scan consistency quoted for a real log: :func:`scan_consistency` of ``poses [T, 3]``
    on :func:`consistency_scans` of the raw ``traversal`` (``scans``: those, if already made),
    with the ``beam_stride`` and ``range_clip`` it used."""
    scans = consistency_scans(traversal) if scans is None else scans
    out = scan_consistency(scans, poses)
    clip = scans.metadata.get("range_clip")
    return {**out, "beam_stride": SCAN_CONSISTENCY_BEAM_STRIDE, "range_clip": clip}
