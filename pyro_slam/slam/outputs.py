"""A SLAM run with its outputs: plots, trajectories (TUM), the posterior, metrics and a
checkpoint, written into one folder (what ``pyro-slam slam`` and ``pyro-slam demo`` do)."""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from .. import metrics, plotting
from ..data import DatasetError, Traversal, atomic_write
from ..io.ros_map import occupancy_grid, write_map
from .build import path_integration
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
)
MAP_CELL = 0.05  # the finest cell of the exported occupancy grid (metres on real logs)


def prepare_out_dir(out: Path, resume: bool = False, overwrite: bool = False,
                    keep: tuple[str, ...] = ()) -> None:  # fmt: skip
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
    elif overwrite:
        for name in OUTPUTS:
            (out / name).unlink(missing_ok=True)


def _write_trajectories(out: Path, traversal: Traversal, res: dict) -> None:
    """The TUM trajectories: SLAM, path integration and, where the traversal has them, its
    true / reference poses (for ``evo_ape``); and ``posterior.npz``."""
    paths = {"slam": res["mean"], "path_integration": res["path_integration"]}
    if traversal.poses is not None:
        paths["true"] = traversal.poses
    for name, poses in paths.items():
        metrics.write_trajectory_tum(out / f"trajectory_{name}.tum", poses, traversal.timestamps)
    arrays = {k: res[v] for k, v in (("pose_mean", "mean"), ("pose_std", "std"),
              ("map_loc", "map_loc"), ("map_scale", "map_scale"),
              ("path_integration", "path_integration"))}  # fmt: skip
    atomic_write(out / "posterior.npz", lambda f: np.savez_compressed(f, **arrays))


def _report(slam: SLAM, traversal: Traversal, res: dict, mode: str, wall: float, preset) -> dict:
    report = {
        "mode": mode,
        "preset": preset,
        "steps": traversal.num_steps,
        "wall_time_s": wall,
        "seconds_per_step": wall / traversal.num_steps,
        "config": slam.cfg.to_dict(),
        "metadata": {k: traversal.metadata.get(k) for k in ("source", "seed", "maze")},
    }
    if traversal.poses is not None:
        if not metrics.HAVE_EVO:
            log.warning("metrics.json without ATE: it needs evo, pip install 'pyro_slam[eval]'")
        report["slam"] = metrics.summary(res["mean"], traversal.poses)
        report["path_integration"] = metrics.summary(res["path_integration"], traversal.poses)
    if not traversal.walls.shape[0]:  # real log: how well the scans agree under each path
        report["scan_consistency"] = {
            "slam": metrics.scan_consistency(slam.tr, res["mean"]),
            "path_integration": metrics.scan_consistency(slam.tr, res["path_integration"]),
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
            slam.tr, res["mean"], out / "map.png", slam.model.grid, res["map_loc"],
            others={"path integration": res["path_integration"]},
        )  # fmt: skip


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
) -> dict:
    """SLAM on ``traversal`` writing plots, trajectories, metrics and a checkpoint into the
    folder ``out`` (made ready by :func:`prepare_out_dir` first). Returns the report written to
    ``metrics.json``."""
    ckpt = Path(out) / "checkpoint.pt"
    slam = SLAM(traversal, config, transition, emission, checkpoint=ckpt, seed=seed)
    if resume:
        slam.resume(ckpt)
    t0 = time.perf_counter()
    res = slam.run(mode, progress=progress)
    wall = time.perf_counter() - t0
    res["mode"] = mode
    res["path_integration"] = path_integration(traversal, slam.model.transition)
    _write_trajectories(out, traversal, res)
    report = _report(slam, traversal, res, mode, wall, preset)
    _plots(out, slam, traversal, res)
    if slam.cfg.emission.observation == "lidar":
        _occupancy(out, slam, res, progress)
    text = json.dumps(report, indent=2, default=float)
    atomic_write(out / "metrics.json", lambda f: f.write(text.encode()))
    return report
