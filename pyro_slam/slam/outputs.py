"""A SLAM run with its outputs: plots, trajectories (TUM), the posterior, metrics and a
checkpoint, written into one folder (what ``pyro-slam slam`` and ``pyro-slam demo`` do)."""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from .. import metrics, plotting
from ..data import DatasetError, Traversal, atomic_write, one_line
from ..io.ros_map import occupancy_grid, write_map
from ..runtime import provenance, torch_threads
from .build import MAX_BYTES, path_integration
from .config import SLAMConfig
from .runner import SLAM

log = logging.getLogger(__name__)

# what a run writes into its folder (an --overwrite run removes these first)
OUTPUTS = (
    "checkpoint.pt",
    "metrics.json",
    "posterior.npz",
    "slam.png",
    "error.png",
    "map.png",
    "map.pgm",
    "map.yaml",
    "trajectory_slam.tum",
    "trajectory_path_integration.tum",
    "trajectory_true.tum",
    "timing.json",
)
# what a reader chose for its input, recorded in metrics.json (ROS bags)
INPUT_CHOICES = ("odometry_source", "laser_offset", "laser_offset_source", "frames")
MAP_CELL = 0.05  # the finest cell of the exported occupancy grid (metres on real logs)
MAP_BYTES_PER_CELL = 32  # the export's working set per cell (log odds, probabilities, image)


def prepare_out_dir(
    out: Path, resume: bool = False, overwrite: bool = False, keep: tuple[str, ...] = ()
) -> None:
    """Make ``out`` ready for a run, before any work: a writable folder that holds no other
    run's results. A non-empty folder is refused unless ``resume`` (continue the run in it) or
    ``overwrite`` (remove its run outputs first; other files stay); ``keep``: files this
    command wrote there itself."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DatasetError(f"--out {out}: exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise DatasetError(f"--out {out}: cannot write there ({e.strerror or e})") from None
    present = sorted(
        p.name for p in out.iterdir() if not p.name.startswith(".") and p.name not in keep
    )
    if resume:
        if not (out / "checkpoint.pt").is_file():
            raise DatasetError(f"{out / 'checkpoint.pt'}: no checkpoint to resume from")
    elif present and not overwrite:
        shown = ", ".join(present[:4]) + (", ..." if len(present) > 4 else "")
        raise DatasetError(
            f"--out {out}: not empty ({shown}); use --resume to continue the run in it, "
            "--overwrite to replace it, or another folder"
        )


@contextlib.contextmanager
def replacing(out: Path, names: Iterable[str], overwrite: bool = True):
    """Replace the files ``names`` of a previous run in the folder ``out`` (``overwrite``;
    otherwise the block just runs) only once the new run has written one of its own.

    Enter the block after the input and configuration have been read: the previous files are
    moved into a hidden folder ``out/.previous-*`` when it starts and deleted when it ends. If
    it fails before it wrote any of ``names``, they are moved back: ``out`` is as it was. (A
    process killed in between leaves them in that hidden folder.)"""
    out, names = Path(out), tuple(names)
    old = [n for n in names if (out / n).exists()] if overwrite else []
    backup = Path(tempfile.mkdtemp(prefix=".previous-", dir=out)) if old else None
    for n in old:
        os.replace(out / n, backup / n)
    try:
        yield
    except BaseException:
        if backup is not None and not any((out / n).exists() for n in names):
            for n in old:
                os.replace(backup / n, out / n)
        raise
    finally:
        if backup is not None:
            shutil.rmtree(backup, ignore_errors=True)


def _write_trajectories(out: Path, traversal: Traversal, res: dict) -> None:
    """The TUM trajectories: SLAM, path integration and, where the traversal has them, its
    true / reference poses (for ``evo_ape``); and ``posterior.npz``."""
    paths = {"slam": res["mean"], "path_integration": res["path_integration"]}
    if traversal.poses is not None:
        paths["true"] = traversal.poses
    for name, poses in paths.items():
        metrics.write_trajectory_tum(out / f"trajectory_{name}.tum", poses, traversal.timestamps)
    arrays = {
        k: res[v]
        for k, v in (
            ("pose_mean", "mean"),
            ("pose_std", "std"),
            ("map_loc", "map_loc"),
            ("map_scale", "map_scale"),
            ("path_integration", "path_integration"),
        )
    }
    atomic_write(out / "posterior.npz", lambda f: np.savez_compressed(f, **arrays))


def _json_safe(value):
    """``value`` with every non-finite float replaced by None (``null``: JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def _report(slam: SLAM, traversal: Traversal, res: dict, mode: str, run: dict):
    """What ``metrics.json`` holds: nothing that differs between two runs of the same command
    (the timings are in ``timing.json``); ``run``: ``preset``, ``seed``, ``input`` (path) and
    the :func:`~pyro_slam.runtime.provenance`."""
    report = {
        "mode": mode,
        **run,
        "steps": traversal.num_steps,
        "config": slam.cfg.to_dict(),
        "metadata": {k: traversal.metadata.get(k) for k in ("source", "seed", "maze")},
    }
    for key in INPUT_CHOICES:  # a real log's: where odometry and the laser's mount came from
        if key in traversal.metadata:
            report[key] = traversal.metadata[key]
    if "skipped_lines" in traversal.metadata:  # a text log: what --lenient skipped
        report["skipped_lines"] = traversal.metadata["skipped_lines"]
        report["skip_reasons"] = traversal.metadata.get("skip_reasons", [])
    if traversal.poses is not None:
        if not metrics.HAVE_EVO:
            log.warning("metrics.json without ATE: it needs evo, pip install 'pyro_slam[eval]'")
        report["slam"] = metrics.summary(res["mean"], traversal.poses)
        report["path_integration"] = metrics.summary(res["path_integration"], traversal.poses)
    if not traversal.walls.shape[0]:  # real log: how well the scans agree under each path
        scans = metrics.consistency_scans(traversal)
        report["scan_consistency"] = {
            k: metrics.log_scan_consistency(traversal, res[v], scans)
            for k, v in (("slam", "mean"), ("path_integration", "path_integration"))
        }
    return report


def _occupancy(out: Path, slam: SLAM, res: dict, progress: bool) -> None:
    """``map.pgm`` + ``map.yaml`` (ROS ``map_server``): the scans SLAM read (strided, clipped at
    the range clip) placed at the SLAM poses."""
    cell = min(slam.cfg.emission.resolution, MAP_CELL)
    t0 = time.perf_counter()
    grid = occupancy_grid(slam.tr, res["mean"], cell, margin=2 * cell, progress=progress)
    write_map(grid, out / "map.yaml")
    h, w = grid.image.shape
    log.info("map.pgm: %d x %d cells of %g in %.1f s", w, h, cell, time.perf_counter() - t0)


def _plots(out: Path, slam: SLAM, traversal: Traversal, res: dict) -> None:
    if traversal.poses is not None:
        plotting.plot_errors(traversal, res, out / "error.png")
    plotting.plot_slam(traversal, res, slam.model.grid, out / "slam.png")
    if not traversal.walls.shape[0]:  # real log: map image from the reprojected scans
        plotting.plot_scan_map(
            slam.tr,
            res["mean"],
            out / "map.png",
            slam.model.grid,
            res["map_loc"],
            others={"path integration": res["path_integration"]},
        )


RUN_ARRAYS = ("pose_mean", "map_loc", "map_scale")  # what read_run takes from posterior.npz


def read_run(out: Path) -> dict:
    """A finished run's folder: ``metrics.json`` (``"metrics"``) and from ``posterior.npz``
    the pose means ``pose_mean [T, 3]`` and the map belief ``map_loc``, ``map_scale [w, h,
    D_m]``, checked (finite, matching shapes); :class:`DatasetError` naming the file otherwise.
    Nothing in them is unpickled."""
    out = Path(out)
    if not out.is_dir():
        raise DatasetError(f"--from {out}: not the folder of a SLAM run")
    path = out / "metrics.json"
    try:
        report = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DatasetError(f"{path}: not a finished run's metrics ({one_line(e)})") from None
    keys = isinstance(report, dict) and isinstance(report.get("config"), dict)
    if not keys or not isinstance(report.get("steps"), int):
        raise DatasetError(f"{path}: not a finished run's metrics (no 'config' or 'steps')")
    path = out / "posterior.npz"
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: np.asarray(f[k], dtype=np.float64) for k in RUN_ARRAYS}
    except Exception as e:  # numpy and zipfile raise many types for missing or damaged files
        raise DatasetError(f"{path}: not a run's posterior ({one_line(e)})") from None
    loc, scale, poses = arrays["map_loc"], arrays["map_scale"], arrays["pose_mean"]
    for name, a in arrays.items():
        if not np.isfinite(a).all():
            raise DatasetError(f"{path}: field '{name}' has non-finite values")
    if poses.shape != (report["steps"], 3) or loc.ndim != 3 or scale.shape != loc.shape:
        raise DatasetError(
            f"{path}: fields pose_mean {poses.shape}, map_loc {loc.shape}, map_scale "
            f"{scale.shape} do not fit a run of {report['steps']} steps"
        )
    return {"metrics": report, **arrays}


def check_map_extent(slam: SLAM, path: np.ndarray, src: str = "traversal") -> None:
    """Refuse, before SLAM runs, a traversal whose exported occupancy grid (``map.pgm``) would
    not fit in memory: the dead-reckoned ``path [T, 3]`` plus the sensor's range, at the
    export's cell, naming the field that spans it."""
    cell = min(slam.cfg.emission.resolution, MAP_CELL)
    reach = slam.tr.max_range + 2 * cell
    lo, hi = path[:, :2].min(0) - reach, path[:, :2].max(0) + reach
    cells = np.prod((hi - lo) / cell + 1)
    if cells * MAP_BYTES_PER_CELL > MAX_BYTES:
        w, h = hi - lo
        raise DatasetError(
            f"{src}: field 'controls' moves the dead-reckoned path over {w:.4g} x {h:.4g}: the "
            f"exported map would need {cells:.3g} cells of {cell:g} (at most "
            f"{MAX_BYTES / MAP_BYTES_PER_CELL:.3g})"
        )


def run_slam(
    traversal: Traversal,
    out: Path,
    mode: str,
    config: SLAMConfig,
    emission=None,
    transition=None,
    resume: bool = False,
    progress: bool = True,
    seed: int = 0,
    preset: str | None = None,
    overwrite: bool = False,
    source: str | None = None,
    checkpoint_every: int = 1000,
    inputs: dict | None = None,
    threads: int | None = None,
    argv: list[str] | None = None,
) -> dict:
    """SLAM on ``traversal`` writing plots, trajectories, metrics and a checkpoint (every
    ``checkpoint_every`` steps) into the folder ``out`` (made ready by :func:`prepare_out_dir`
    first; ``overwrite``: the previous run's outputs are replaced only once SLAM has been set
    up, see :func:`replacing`). ``source``: the input's path, recorded in ``metrics.json`` with
    its SHA-256; ``inputs``: files the command writes into ``out`` first, ``{name:
    write(path)}`` (the demo's traversal); ``threads``: torch intra-op threads for the whole
    run (:func:`~pyro_slam.runtime.thread_count`); ``argv``: the command line recorded in
    ``metrics.json``. Returns the report written to ``metrics.json`` together with the
    timings written to ``timing.json`` (``wall_time_s``, summed over the sessions of a resumed
    run, ``seconds_per_step``, ``wall_time_session_s`` and ``resumed``)."""
    with torch_threads(threads) as n:
        slam = SLAM(
            traversal,
            config,
            transition,
            emission,
            Path(out) / "checkpoint.pt",
            checkpoint_every=checkpoint_every,
            seed=seed,
            threads=n,
        )
        dead_reckoning = path_integration(traversal, slam.model.transition)
        check_map_extent(slam, dead_reckoning, source or "traversal")
        if resume:
            slam.resume(Path(out) / "checkpoint.pt")
        with replacing(out, (*(inputs or {}), *OUTPUTS), overwrite):
            run = {"preset": preset, "seed": seed, "input": source, "resumed": resume}
            return _run_and_write(
                slam, traversal, Path(out), mode, dead_reckoning, run, argv, inputs or {}, progress
            )


def _run_and_write(slam, traversal, out, mode, dead_reckoning, run, argv, inputs, progress):
    """The body of :func:`run_slam` once SLAM is set up: write ``inputs``, run, write the
    outputs; returns the report and the timings."""
    for name, write in inputs.items():
        write(out / name)
    t0 = time.perf_counter()
    res = slam.run(mode, progress=progress)
    session = time.perf_counter() - t0
    wall = slam.state.wall_time_s  # summed over the sessions of a resumed run
    resumed = run.pop("resumed")
    res["mode"] = mode
    res["path_integration"] = dead_reckoning
    _write_trajectories(out, traversal, res)
    run = {**run, **provenance(slam.threads, argv, run["input"])}
    report = _json_safe(_report(slam, traversal, res, mode, run))
    timing = {
        "wall_time_s": wall,
        "seconds_per_step": wall / traversal.num_steps,
        "wall_time_session_s": session,
        "resumed": resumed,
    }
    for name, data in (("metrics.json", report), ("timing.json", timing)):
        text = json.dumps(data, indent=2, default=float)
        atomic_write(out / name, lambda f, text=text: f.write(text.encode()))
    _plots(out, slam, traversal, res)
    if slam.cfg.emission.observation == "lidar":
        _occupancy(out, slam, res, progress)
    return {**report, **timing}
