"""A SLAM run with its outputs: plots, trajectories (TUM), the posterior, metrics and a
checkpoint, written into one folder (what ``pyro-slam slam`` and ``pyro-slam demo`` do)."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import logging
import math
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import numpy as np

from .. import metrics, plotting
from ..data import DatasetError, Traversal, atomic_write, one_line
from ..inference import ParticleFilterFailed
from ..io.ros_map import occupancy_grid, write_map
from ..runtime import provenance, torch_threads
from .build import MAX_BYTES, path_integration, transition_kind
from .checkpoint import CHECKPOINT_EVERY
from .config import ConfigError, SLAMConfig, TrainingConfig, check_used
from .runner import SLAM
from .state import Phase

log = logging.getLogger(__name__)

# what a run writes into its folder (an --overwrite run does not carry these over)
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
MIN_CELLS_PER_RANGE = 4  # the coarsest map: the sensor's range spans this many grid cells


class Interrupted(KeyboardInterrupt):
    """The run was stopped by a signal (SIGINT or SIGTERM); ``signal``: its name."""

    def __init__(self, signal_name: str, message: str = ""):
        super().__init__(message or f"interrupted ({signal_name})")
        self.signal = signal_name


@contextlib.contextmanager
def terminate_as_interrupt():
    """Within the block, SIGTERM raises :class:`Interrupted` (as SIGINT raises
    ``KeyboardInterrupt``), so that a terminated run cleans up like an interrupted one. Only
    in the main thread (elsewhere signals cannot be handled)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, _frame):
        raise Interrupted(signal.Signals(signum).name)

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


# a run's own hidden entries inside its folder OUT: the run being written, the previous run's
# outputs while the new ones are moved in, the lock, and (in the run being written) the list of
# a finished run's files
WORK, PREVIOUS, LOCK, MANIFEST = ".partial", ".previous", ".lock", ".complete"


def _lock(path: Path, shown: str):
    """An open file holding an exclusive ``flock`` on ``path`` (created if missing, never
    through a symbolic link); a :class:`DatasetError` naming ``--out shown`` when another
    process holds it or when ``path`` is a link."""
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as e:
            if e.errno != errno.ELOOP:
                raise
            raise DatasetError(
                f"--out {shown}: its lock {path} is a symbolic link, which a run does not "
                "follow; remove it"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise DatasetError(
                f"--out {shown}: another run is writing into it (it holds {path}); wait for it "
                "to finish or choose another folder"
            ) from None
        try:  # the holder before us may have removed the file: lock the one on disk
            if os.stat(path, follow_symlinks=False).st_ino == os.fstat(fd).st_ino:
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)


@contextlib.contextmanager
def _deferred_signals():
    """Within the block SIGINT and SIGTERM are recorded (in the list yielded), not raised, so
    that they never stop a swap half-way (main thread only)."""
    pending: list[str] = []
    if threading.current_thread() is not threading.main_thread():
        yield pending
        return

    def record(signum, _frame):
        pending.append(signal.Signals(signum).name)

    previous = {s: signal.signal(s, record) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield pending
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def finish_swap(out: Path, owned: tuple[str, ...]) -> None:
    """Put the finished run in ``out/.partial`` (its files listed in ``.partial/.complete``)
    in place of the previous run's outputs, from wherever a swap stopped: each previous output
    (``owned``, or a name of the new run) not yet replaced is moved into ``out/.previous``,
    each new file still in ``.partial`` is moved in, then ``.complete``, ``.partial`` and
    ``.previous`` are removed. Every step is one rename or removal inside ``out``, so running
    it again after a stop at any step ends in the same folder."""
    work, previous = out / WORK, out / PREVIOUS
    names = json.loads((work / MANIFEST).read_text())
    previous.mkdir(exist_ok=True)
    for name in sorted({*owned, *names}):
        p = out / name
        moved_in = name in names and not (work / name).exists()
        if (p.exists() or p.is_symlink()) and not moved_in:
            os.replace(p, previous / name)
    for name in names:
        if (work / name).exists():
            os.replace(work / name, out / name)
    os.remove(work / MANIFEST)
    os.rmdir(work)
    shutil.rmtree(previous)


def _recover(out: Path, shown: str, owned: tuple[str, ...]) -> None:
    """Finish what a run stopped at any point (a kill, a power cut) left inside ``out``,
    saying what: a finished run half put in place is put in place, the previous run's leftover
    outputs are removed; an interrupted run's folder stays (:func:`_check_out` names it)."""
    work, previous = out / WORK, out / PREVIOUS
    try:
        _finish_leftovers(out, shown, owned, work, previous)
    except (OSError, ValueError) as e:  # (ValueError: a damaged list of the run's files)
        raise DatasetError(
            f"--out {shown}: cannot finish what a stopped run left in it ({one_line(e)}); "
            f"move {work} and {previous} away by hand"
        ) from None


def _finish_leftovers(out: Path, shown: str, owned, work: Path, previous: Path) -> None:
    """:func:`_recover`'s work: finish a committed swap, or remove a finished one's
    ``.previous``, each with a warning naming it."""
    if (work / MANIFEST).is_file():
        log.warning(
            "--out %s: the run in %s had finished but was stopped while being put in place; "
            "putting it in place now (the previous run's outputs moved into %s are removed)",
            shown,
            work,
            previous,
        )
        finish_swap(out, owned)
    elif previous.exists():
        log.warning(
            "--out %s: removing %s, a previous run's outputs left by a run stopped once it was "
            "in place (the folder holds that run)",
            shown,
            previous,
        )
        shutil.rmtree(previous)


class RunFolder:
    """The output folder ``out`` of one run, made ready by :func:`run_folder`.

    A run writes into the hidden folder ``work`` inside it (``OUT/.partial``); only
    :meth:`writing` finishing puts it in place, whole: until then ``out`` keeps the previous
    run, if any, as it was. Everything happens inside ``out``, so a mount point, ``.`` or a
    symbolic link (which stays a link) all work: the list of the finished run's files is
    written (the commit point), then :func:`finish_swap` moves the files, one rename each;
    SIGINT and SIGTERM wait for its end, and the next run on ``out`` finishes a swap that a
    kill stopped. Files of ``out`` that are not run outputs (``owned``) stay. An interrupted
    run (SIGINT, SIGTERM, a full disk) keeps ``work`` where it holds a checkpoint, for
    ``--resume``; any other failure removes it. ``shown``: ``out`` as the user wrote it (for
    messages).
    """

    def __init__(self, out: Path, resume: bool, owned: tuple[str, ...], shown: str = ""):
        self.out, self.resume, self.owned = Path(out), resume, tuple(owned)
        self.shown = shown or str(out)
        self.work = self.out / WORK
        self.checkpoint = self.work / "checkpoint.pt"
        self.committed = False

    @property
    def finished(self) -> bool:
        """``out`` holds a finished run and no interrupted one is kept beside it."""
        return not self.checkpoint.is_file() and (self.out / "checkpoint.pt").is_file()

    @property
    def resume_from(self) -> Path:
        """The checkpoint ``--resume`` continues: the interrupted run's kept in ``.partial``,
        else the finished run's in ``out``."""
        return self.checkpoint if self.checkpoint.is_file() else self.out / "checkpoint.pt"

    @contextlib.contextmanager
    def writing(self):
        """The block that writes the run into :attr:`work` (yielded); put in place as ``out``
        at its end. A failure before that leaves ``out`` as it was; :attr:`work` stays only
        where it was there before (a resumed interrupted run) or, after an interruption or a
        write error, where it holds a checkpoint."""
        existed = self.work.exists()
        if self.resume and not existed and (self.out / "checkpoint.pt").is_file():
            _copy_outputs(self.out, self.work, self.owned)  # continue a finished run: a copy
        self.work.mkdir(exist_ok=True)
        try:
            yield self.work
            self._swap()
        except BaseException as e:
            if self.committed:  # the run is finished: out holds it, or the next run's will
                if isinstance(e, OSError):
                    raise DatasetError(self._describe(e, False)) from None
                raise
            stopped = isinstance(e, (KeyboardInterrupt, OSError))
            kept = (existed or stopped) and self.checkpoint.is_file()
            if not kept:
                shutil.rmtree(self.work, ignore_errors=True)
            if isinstance(e, OSError):
                raise DatasetError(self._describe(e, kept)) from None
            if isinstance(e, KeyboardInterrupt):
                e.args = (self._describe(e, kept),)
            raise

    def _describe(self, e: BaseException, kept: bool) -> str:
        """One line: what stopped the run, in what state ``out`` is, what was kept."""
        if isinstance(e, OSError):
            where = f" ({e.filename})" if e.filename else ""
            what = f"cannot write the run: {e.strerror or one_line(e)}{where}"
        else:
            what = f"interrupted ({getattr(e, 'signal', 'SIGINT')})"
        if self.committed:
            return (
                f"--out {self.shown}: {what} while putting the finished run in place; it is "
                f"kept in {self.work}, and the next run on the folder puts it in place"
            )
        line = f"--out {self.shown}: {what}; the folder is as it was before this run"
        if kept:
            line += f"; the run so far is kept in {self.work} (--resume continues it)"
        return line

    def _swap(self) -> None:
        """Put :attr:`work` in place: its list of files (the commit point), then
        :func:`finish_swap`, with SIGINT and SIGTERM held until it has ended."""
        names = sorted(p.name for p in self.work.iterdir())
        text = json.dumps(names).encode()
        with _deferred_signals() as pending:
            atomic_write(self.work / MANIFEST, lambda f: f.write(text))
            self.committed = True
            finish_swap(self.out, self.owned)
        if pending:
            raise Interrupted(
                pending[0],
                f"--out {self.shown}: interrupted ({pending[0]}) once the run had finished; "
                "the folder holds it",
            )


def _copy_outputs(src: Path, dst: Path, names: tuple[str, ...]) -> None:
    """Copy the files ``names`` of the folder ``src`` into a new folder ``dst`` (removed again
    if the copy fails)."""
    dst.mkdir()
    try:
        for name in names:
            if (src / name).is_file():
                shutil.copy2(src / name, dst / name)
    except BaseException:
        shutil.rmtree(dst, ignore_errors=True)
        raise


def make_parents(out: Path) -> list[Path]:
    """Create the missing folders above ``out``; returns them, deepest first."""
    made, p = [], out.absolute().parent
    while not p.exists():
        made.append(p)
        p = p.parent
    for d in reversed(made):
        d.mkdir()
    return made


def _check_out(out: Path, resume: bool, overwrite: bool, work: Path, keep, shown: str) -> None:
    """Refuse ``out`` (before any work) where it holds another run's results (without
    ``resume`` / ``overwrite``), or where resuming has no checkpoint."""
    present = sorted(
        p.name for p in out.iterdir() if not p.name.startswith(".") and p.name not in keep
    )
    interrupted = (work / "checkpoint.pt").is_file()
    if resume:
        if not interrupted and not (out / "checkpoint.pt").is_file():
            raise DatasetError(f"{Path(shown) / 'checkpoint.pt'}: no checkpoint to resume from")
    elif interrupted and not overwrite:
        raise DatasetError(
            f"--out {shown}: an interrupted run into it is kept in {work}; use --resume to "
            "continue it, or --overwrite to discard it"
        )
    elif present and not overwrite:
        listed = ", ".join(present[:4]) + (", ..." if len(present) > 4 else "")
        raise DatasetError(
            f"--out {shown}: not empty ({listed}); use --resume to continue the run in it, "
            "--overwrite to replace it, or another folder"
        )


def _make_out(out: Path, shown: str) -> list[Path]:
    """Create the folder ``out`` and the missing ones above it (returned, deepest first)."""
    if out.exists() and not out.is_dir():
        raise DatasetError(f"--out {shown}: exists and is not a folder")
    try:
        made = make_parents(out)
        if not out.exists():
            out.mkdir()
            made.insert(0, out)
    except OSError as e:
        raise DatasetError(f"--out {shown}: cannot create it ({e.strerror or e})") from None
    return made


@contextlib.contextmanager
def run_folder(
    out: Path, resume: bool = False, overwrite: bool = False, keep: tuple[str, ...] = ()
):
    """Make ``out`` ready for a run, before any work, and hold it for the block: a
    :class:`RunFolder` (write the run inside ``folder.writing()``).

    ``out`` is resolved first (a symbolic link to a folder is that folder, and stays a link).
    It is refused when it is no folder, when another process holds its lock (the file
    ``OUT/.lock``, never followed through a link), or when it holds other results unless
    ``resume`` (continue the run in it, or the interrupted one kept in it) or ``overwrite``
    (replace it once the new run has finished; files that are not run outputs stay). A swap
    that a kill stopped is finished first (:func:`finish_swap`). ``keep``: files the command
    itself writes there (not counted as another run's). Folders created for ``out`` and not
    used are removed again at the end of the block."""
    shown = str(out)
    out = Path(os.path.realpath(out))
    made = _make_out(out, shown)
    try:
        fd = _lock(out / LOCK, shown)
    except OSError as e:
        remove_empty(made)
        raise DatasetError(f"--out {shown}: cannot write there ({e.strerror or e})") from None
    try:
        owned = (*OUTPUTS, *keep)
        _recover(out, shown, owned)
        folder = RunFolder(out, resume, owned, shown)
        _check_out(out, resume, overwrite, folder.work, keep, shown)
        if not resume and folder.work.exists():  # a discarded or checkpoint-less leftover
            why = "discarded (--overwrite)" if folder.checkpoint.is_file() else "no checkpoint"
            log.warning(
                "--out %s: removing %s, a run stopped unfinished (%s)", shown, folder.work, why
            )
            shutil.rmtree(folder.work)
        with terminate_as_interrupt():
            yield folder
    finally:
        with contextlib.suppress(OSError):
            os.unlink(out / LOCK)
        os.close(fd)
        remove_empty(made)


def remove_empty(folders: list[Path]) -> None:
    """Remove those of ``folders`` (deepest first, as :func:`make_parents` lists them) that
    are empty."""
    for d in folders:
        with contextlib.suppress(OSError):
            d.rmdir()


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


def walls_fingerprint(walls: np.ndarray) -> str:
    """A SHA-256 of the walls ``[W, 2, 2]`` (float64): which maze a run mapped."""
    a = np.ascontiguousarray(walls, dtype=np.float64)
    return hashlib.sha256(f"{a.shape}".encode() + a.tobytes()).hexdigest()[:32]


def _config_that_ran(slam: SLAM) -> dict:
    """The run's configuration as it ran: ``transition.kind`` is that of the transition the
    model holds (a network passed in runs as ``"learned"``)."""
    config = slam.cfg.to_dict()
    config["transition"]["kind"] = transition_kind(slam.model.transition)
    return config


def _report(slam: SLAM, traversal: Traversal, res: dict, mode: str, run: dict):
    """What ``metrics.json`` holds: nothing that differs between two runs of the same command
    (the timings are in ``timing.json``); ``run``: ``preset``, ``seed``, ``input`` (path) and
    the :func:`~pyro_slam.runtime.provenance`."""
    report = {
        "mode": mode,
        **run,
        "steps": traversal.num_steps,
        "config": _config_that_ran(slam),
        "metadata": {k: traversal.metadata.get(k) for k in ("source", "seed", "maze")},
        "walls": walls_fingerprint(traversal.walls),
    }
    for key in INPUT_CHOICES:  # a real log's: where odometry and the laser's mount came from
        if key in traversal.metadata:
            report[key] = traversal.metadata[key]
    for key in (
        "skipped_lines",
        "skipped_scans",
    ):  # a text log's or a bag's: what --lenient skipped
        if key in traversal.metadata:
            report[key] = traversal.metadata[key]
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


def check_settings(traversal: Traversal, config: SLAMConfig, src: str = "traversal") -> None:
    """Refuse, before any work, settings that cannot mean anything for this (raw) traversal,
    naming the field and its limit: a scan of one beam, a ``beam_stride`` that leaves fewer
    than two beams, a ``range_clip`` beyond the sensor's range, and an ``emission.resolution``
    whose grid cell is not small against what the sensor sees (a beam must cross at least
    ``MIN_CELLS_PER_RANGE`` cells)."""
    lidar = config.emission.observation == "lidar"
    n = traversal.num_beams
    if lidar and n < 2:
        raise DatasetError(
            f"{src}: field 'observations' has {n} beam per scan; a LiDAR scan needs at least 2"
        )
    if lidar and config.beam_stride >= max(n, 2):
        raise ConfigError(
            f"beam_stride {config.beam_stride} leaves fewer than 2 of the {n} beams of {src} "
            f"(at most {max(n - 1, 1)})"
        )
    top = math.ceil(traversal.max_range * 100) / 100  # (the real-log preset rounds its clip)
    if config.range_clip is not None and config.range_clip > top:
        raise ConfigError(
            f"range_clip {config.range_clip:g} is beyond the sensor's range "
            f"{traversal.max_range:g} in {src} (at most {top:g})"
        )
    reach = float(config.range_clip or traversal.max_range)
    limit = reach / MIN_CELLS_PER_RANGE
    if config.emission.resolution > limit:
        raise ConfigError(
            f"emission.resolution {config.emission.resolution:g} is too coarse for the "
            f"sensor's range {reach:g} in {src}: a beam must cross at least "
            f"{MIN_CELLS_PER_RANGE} grid cells (at most {limit:g})"
        )


def check_offline_length(traversal: Traversal, config: SLAMConfig, mode: str, src: str) -> None:
    """Refuse an offline run whose SVI steps draw chunks longer than the traversal."""
    o, L = config.offline, config.training.chunk_length
    svi = mode == "offline" and o.rounds > 0 and o.svi_steps > 0
    if svi and traversal.num_steps < L:
        raise DatasetError(
            f"{src}: {traversal.num_steps} steps, fewer than training.chunk_length {L}, the "
            "length of the chunks offline SVI draws: use --mode online or a shorter "
            "training.chunk_length"
        )


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


def diverged(e: Exception, cfg: SLAMConfig) -> DatasetError:
    """A one-line error for a run whose SVI loss or particle weights stopped being finite
    (``e``), naming the settings that most likely caused it."""
    t, em = cfg.training, cfg.emission
    lr = f"training.lr {t.lr:g}"
    if isinstance(e, FloatingPointError) or t.lr > 1:  # an SVI step of that size breaks q(M)
        default = TrainingConfig().lr
        cause = f"{lr} too large (default {default:g}), or training.lr_emission {t.lr_emission:g}"
    else:
        cause = (
            f"emission.sigma {em.sigma:g} too small for the sensor's noise, "
            f"filter.particles {cfg.filter.particles} too few, or {lr} too large"
        )
    return DatasetError(f"SLAM diverged ({one_line(e)}): most likely {cause}")


def _check_used(overrides: dict | None, config: SLAMConfig, mode: str, learns=None) -> None:
    """:func:`~pyro_slam.slam.config.check_used` as the command line's ``--config`` error."""
    try:
        check_used(overrides or {}, config, mode, learns)
    except ConfigError as e:
        raise DatasetError(f"--config: {e}") from None


def run_slam(
    traversal: Traversal,
    out: Path | RunFolder,
    mode: str,
    config: SLAMConfig,
    emission=None,
    transition=None,
    resume: bool = False,
    progress: bool = True,
    seed: int = 0,
    preset: str | None = None,
    overwrite: bool = True,
    source: str | None = None,
    checkpoint_every: int = CHECKPOINT_EVERY,
    inputs: dict | None = None,
    threads: int | None = None,
    argv: list[str] | None = None,
    overrides: dict | None = None,
) -> dict:
    """SLAM on ``traversal`` writing plots, trajectories, metrics and a checkpoint (every
    ``checkpoint_every`` steps) into the folder ``out``: a :class:`RunFolder` made ready by
    :func:`run_folder` (a path: made ready here, with ``resume`` / ``overwrite``). The run is
    written beside it and swapped in at the end (a failure leaves ``out`` as it was; a
    diverged filter raises :func:`diverged`'s error). ``source``: the input's path, recorded
    in ``metrics.json`` with its SHA-256; ``inputs``: files the command writes into the run
    first, ``{name: write(path)}`` (the demo's traversal); ``threads``: torch intra-op threads
    for the whole run (:func:`~pyro_slam.runtime.thread_count`); ``argv``: the command line
    recorded in ``metrics.json``; ``overrides``: the configuration changes the user gave, each
    refused where nothing built would read it (:func:`~pyro_slam.slam.config.check_used`).
    Returns the report written to ``metrics.json`` together with
    the timings written to ``timing.json`` (``wall_time_s``, summed over the sessions of a
    resumed run, ``seconds_per_step``, ``wall_time_session_s`` and ``resumed``)."""
    if not isinstance(out, RunFolder):
        kw = dict(locals())
        with run_folder(out, resume, overwrite and not resume, tuple(inputs or ())) as folder:
            return run_slam(**{**kw, "out": folder})
    check_settings(traversal, config, source or "traversal")
    _check_used(overrides, config, mode)
    check_offline_length(traversal, config, mode, source or "traversal")
    with torch_threads(threads) as n:
        slam = SLAM(
            traversal,
            config,
            transition,
            emission,
            out.checkpoint,
            checkpoint_every=checkpoint_every,
            seed=seed,
            threads=n,
        )
        _check_used(overrides, slam.cfg, mode, slam.model.learn_emission)
        dead_reckoning = path_integration(traversal, slam.model.transition)
        check_map_extent(slam, dead_reckoning, source or "traversal")
        if resume:
            slam.resume(out.resume_from)
            if out.finished and slam.state.phase == Phase.DONE and slam.state.mode == mode:
                log.warning("--out %s: its run has finished; nothing to resume", out.shown)
                return _finished_report(out.out)
        run = {"preset": preset, "seed": seed, "input": source}
        with out.writing() as work:
            for name, write in (inputs or {}).items():
                write(work / name)
            t0 = time.perf_counter()
            try:
                res = slam.run(mode, progress=progress)
            except (FloatingPointError, ParticleFilterFailed) as e:
                raise diverged(e, slam.cfg) from None
            timing = {
                "wall_time_s": slam.state.wall_time_s,  # summed over the sessions
                "seconds_per_step": slam.state.wall_time_s / traversal.num_steps,
                "wall_time_session_s": time.perf_counter() - t0,
                "resumed": bool(resume),
            }
            res.update(mode=mode, path_integration=dead_reckoning)
            run.update(provenance(slam.threads, argv, source))
            return _write_run(work, slam, traversal, res, run, timing, progress)


def _finished_report(out: Path) -> dict:
    """A finished run's ``metrics.json`` and ``timing.json``, as :func:`run_slam` returns."""
    report = {}
    for name in ("metrics.json", "timing.json"):
        try:
            report.update(json.loads((out / name).read_text()))
        except (OSError, ValueError) as e:
            raise DatasetError(f"{out / name}: not a finished run's ({one_line(e)})") from None
    return report


def _write_run(work: Path, slam: SLAM, traversal: Traversal, res: dict, run, timing, progress):
    """Write a finished run's files into ``work``: trajectories, ``metrics.json``,
    ``timing.json``, plots, the occupancy grid; returns the report and the timings."""
    _write_trajectories(work, traversal, res)
    report = _json_safe(_report(slam, traversal, res, res["mode"], run))
    for name, data in (("metrics.json", report), ("timing.json", timing)):
        text = json.dumps(data, indent=2, default=float)
        atomic_write(work / name, lambda f, text=text: f.write(text.encode()))
    _plots(work, slam, traversal, res)
    if slam.cfg.emission.observation == "lidar":
        _occupancy(work, slam, res, progress)
    return {**report, **timing}
