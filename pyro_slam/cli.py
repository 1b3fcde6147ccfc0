"""The ``pyro-slam`` command line: the only argparse layer of the project.

    pyro-slam simulate --maze moderate-medium --steps 3000 --seed 1 --out traversal.npz
    pyro-slam slam traversal.npz --mode online --out run/     # also .clf / .log / ROS bags
    pyro-slam slam traversal.npz --preset manhattan --config '{"filter": {"particles": 256}}'
    pyro-slam slam traversal.npz --out run/ --resume          # continue from run/checkpoint.pt
    pyro-slam demo --out out/                       # simulate + SLAM + plots + metrics.json
    pyro-slam navigate --from run/                  # hybrid A* in the SLAM run's map
    pyro-slam pretrain --out pretrained/            # emission + learned transition

Every sub-command validates its inputs before computing and exits with status 2 and a one-line
message naming the file and problem on bad input; ``navigate`` exits with status 1 when it
finds no plan.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import math
import os
import signal
import sys
import textwrap
from pathlib import Path

from .version import package_version, version_only

if version_only(__name__):  # `pyro-slam --version`: answered before torch is imported
    print(f"pyro-slam {package_version()}")
    raise SystemExit(0)

# the command draws into files only: matplotlib's file backend, whatever MPLBACKEND says (an
# unknown one would stop the import of matplotlib itself)
os.environ["MPLBACKEND"] = "Agg"

import numpy as np
import torch

from simulators import make_maze, simulate_traversal
from simulators.maze import SCALES
from simulators.plotting import plot_traversal
from simulators.traversal import integrate_controls

from . import pretrained
from .data import DatasetError, Traversal, atomic_write_all, one_line
from .extras import MissingExtra
from .io import input_kind, read_any
from .model import pretrain_transition
from .planning import (
    NAVIGATION,
    GroundTruthEnv,
    Look,
    Mover,
    check_endpoints,
    free_grid,
    learned_env,
    lookalikes,
    maze_bounds,
    run_env,
    seek_observation,
    sensor,
)
from .planning.inverse import fit_inverse
from .plotting import plot_navigation
from .runtime import DEFAULT_THREADS, MAX_THREADS
from .slam import SLAM, ConfigError, SLAMConfig, from_dict, presets
from .slam.checkpoint import CHECKPOINT_EVERY
from .slam.components import emission_kind
from .slam.config import parse_overrides
from .slam.outputs import (
    check_settings,
    make_parents,
    read_run,
    remove_empty,
    run_folder,
    run_slam,
    terminate_as_interrupt,
    walls_fingerprint,
)
from .slam.training import pretrain_emission

DEFAULT_MAZE, DEFAULT_MAZE_SEED = "moderate-medium", 1001  # navigate's own maze


# ----------------------------------------------------------------------------------- helpers
class _Parser(argparse.ArgumentParser):
    """Usage errors as one line naming the option (``prog: error: ...``), exit status 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


class _Help(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Help that shows each option's default (an option without one says in words what
    happens) and keeps descriptions and epilogues as written."""

    def _get_help_string(self, action):
        if action.default is None:
            return action.help
        return super()._get_help_string(action)


def _number(kind, low: float, inclusive: bool = True, high: float = math.inf):
    """An argparse type: ``kind`` (int or float), finite, at least (or above) ``low`` and at
    most ``high``."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {kind.__name__}, got {text!r}") from None
        if not math.isfinite(value) or value < low or (value == low and not inclusive):
            bound = f">= {low:g}" if inclusive else f"> {low:g}"
            raise argparse.ArgumentTypeError(f"must be {bound}, got {text}")
        if value > high:
            raise argparse.ArgumentTypeError(f"must be at most {high:.0f}, got {text}")
        return value

    parse.__name__ = kind.__name__
    return parse


COUNT = _number(int, 0)  # 0 or more
POSITIVE = _number(int, 1)
FINITE = _number(float, -math.inf)
MAX_SEED = 2**32 - 1  # numpy's legacy seeding takes 32-bit seeds
SEED = _number(int, 0, high=MAX_SEED)
MAX_STEPS = 1_000_000  # a simulated traversal's steps (about 1 GB with camera frames)
STEPS = _number(int, 1, high=MAX_STEPS)
MAX_DISTRACTORS = 1000
THREADS = _number(int, 1, high=MAX_THREADS)


def _bag_options(args, kind: str, path: Path) -> dict:
    """The ROS bag reader's keywords from ``--scan-topic``, ``--odom-topic``,
    ``--laser-offset`` and ``--no-odometry``; each refused for any other input."""
    kw = {}
    for opt in ("scan_topic", "odom_topic", "laser_offset", "no_odometry"):
        if getattr(args, opt, None) not in (None, False):
            if kind != "rosbag":
                raise DatasetError(f"{path}: --{opt.replace('_', '-')} applies to ROS bags")
            kw[opt] = getattr(args, opt)
    if kw.pop("no_odometry", False):
        for opt in ("odom_topic", "laser_offset"):
            if opt in kw:
                raise DatasetError(f"--{opt.replace('_', '-')}: --no-odometry reads no odometry")
        kw["odometry"] = False
    return kw


def _read(args) -> Traversal:
    """The input traversal. ``--lenient``: malformed lines of a text log, or a bag's scans out
    of time order, are skipped and said in one line on stderr; ``--scan-topic`` /
    ``--odom-topic``: a ROS bag's topics;
    ``--no-odometry`` / ``--laser-offset``: a ROS bag's odometry and laser mount, chosen."""
    path = Path(args.traversal)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or directory")
    kind, kw = input_kind(path), {}
    if getattr(args, "lenient", False):
        if kind not in ("carmen", "rosbag"):
            raise DatasetError(
                f"{path}: --lenient applies to CARMEN logs and ROS bags, not this input"
            )
        kw["lenient"] = True
    kw.update(_bag_options(args, kind, path))
    tr = read_any(path, **kw)
    for key, what in (("skipped_lines", "malformed line(s)"), ("skipped_scans", "scan(s)")):
        if tr.metadata.get(key, 0):
            first = (tr.metadata.get("skip_reasons") or ["?"])[0]
            print(
                f"pyro-slam {args.command}: --lenient skipped {tr.metadata[key]} {what} of "
                f"{path} (listed in metrics.json; the first: {first})",
                file=sys.stderr,
            )
    return tr


def _config(args, traversal: Traversal) -> tuple[str, SLAMConfig]:
    """The preset named by ``--preset`` (default: ``real`` for a real log, else the default
    preset) for this traversal, with the ``--config`` JSON overrides (a string or a file):
    :func:`pyro_slam.slam.presets.configure`, as the benchmarks choose theirs. Settings the
    chosen components would ignore (``--odometry-noise`` outside the real-log presets,
    ``transition.sigma`` of a learned transition), or that do not fit the traversal, are
    refused."""
    noise = getattr(args, "odometry_noise", None)
    try:
        name, config = presets.configure(args.preset, traversal, args.config or None, noise)
        check_settings(traversal, config, str(getattr(args, "traversal", "traversal")))
    except ConfigError as e:
        raise DatasetError(f"--config: {e}") from None
    if noise is not None and presets.get(name).adapt is not presets.adapt_real_log:
        real = [p.name for p in presets.PRESETS.values() if p.adapt is presets.adapt_real_log]
        raise DatasetError(
            f"--odometry-noise: applies to the real-log preset{'s' * (len(real) > 1)} "
            f"{', '.join(map(repr, real))}, not to the preset {name!r} chosen here"
        )
    return name, config


def _print_report(report: dict, out: Path) -> None:
    line = f"slam ({report['preset']}, {report['mode']}): T={report['steps']}"
    line += f" {report['wall_time_s']:.0f}s"
    if "slam" in report:
        s, p = report["slam"], report["path_integration"]
        line += (
            f" | final error SLAM {s['final_error']:.4f} vs path integration {p['final_error']:.4f}"
        )
        if "ate_aligned" in s:  # (evo, the [eval] extra)
            line += (
                f" | ATE rmse unaligned {s['ate_unaligned']['rmse']:.4f} vs "
                f"{p['ate_unaligned']['rmse']:.4f}, aligned {s['ate_aligned']['rmse']:.4f} vs "
                f"{p['ate_aligned']['rmse']:.4f}"
            )
    if "scan_consistency" in report:
        c = report["scan_consistency"]
        if c["slam"]["mean"] is None:
            line += f" | scan consistency undefined: {c['slam']['reason']}"
        else:
            line += (
                f" | scan consistency (beam stride {c['slam']['beam_stride']}) SLAM "
                f"{c['slam']['mean']:.3f} vs path integration {c['path_integration']['mean']:.3f}"
            )
    print(line + f" -> {out}/ (metrics.json, slam.png, map.png / error.png, checkpoint.pt)")


def _writable(path: Path, what: str, overwrite: bool = True) -> None:
    """Refuse an output path that cannot be written, or (without ``overwrite``) that exists,
    before any work is done."""
    if path.is_dir():
        raise DatasetError(f"{what} {path}: is a folder, not a file")
    if path.exists() and not overwrite:
        raise DatasetError(f"{what} {path}: exists; use --overwrite to replace it")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        probe = path.parent / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise DatasetError(f"{what} {path}: cannot write there ({e.strerror or e})") from None


# ----------------------------------------------------------------------------------- commands
DEMO_INPUTS = ("traversal.npz", "traversal.png")


def _parents(path: Path, what: str) -> list[Path]:
    """Create the missing folders above ``path`` (:func:`~pyro_slam.slam.outputs.make_parents`),
    an error naming ``what`` where that is impossible."""
    try:
        return make_parents(path)
    except OSError as e:
        raise DatasetError(f"{what} {path}: cannot create its folder ({e.strerror or e})") from None


def _save_with_plot(tr: Traversal, out: Path, plot_path: Path | None) -> Path | None:
    """``out`` and the plot ``plot_path`` together: the plot is drawn beside its place and
    moved there only once ``out`` is written (a failure leaves both previous files)."""
    if plot_path is None:
        tr.save(out)
        return None
    drawn = plot_path.with_name(f".{plot_path.name}.partial.png")
    try:
        plot_traversal(tr, drawn)
        tr.save(out)
        os.replace(drawn, plot_path)
    finally:
        drawn.unlink(missing_ok=True)
    return plot_path


def cmd_simulate(args) -> int:
    """Simulate a traversal, save it (``.npz``) and a plot of it; print a one-line summary.
    Both outputs are checked first and written together at the end, so a failure (or SIGINT,
    SIGTERM) loses no file and leaves no folder it created."""
    out = Path(args.out)
    plot_path = None if args.no_plot else Path(args.plot or out.with_suffix(".png"))
    made = _parents(out, "--out") + ([] if plot_path is None else _parents(plot_path, "--plot"))
    try:
        _writable(out, "--out")
        if plot_path is not None:
            _writable(plot_path, "--plot")
        tr = simulate_traversal(
            args.maze, args.steps, args.seed, images=args.images, distractors=args.distractors
        )
        plot = _save_with_plot(tr, out, plot_path)
    except BaseException:
        remove_empty(made)
        raise
    dead = integrate_controls(tr.poses[0], tr.controls)
    drift = float(np.linalg.norm(dead[-1, :2] - tr.poses[-1, :2]))
    print(
        f"simulate: {args.maze} seed={args.seed} T={tr.num_steps} beams={tr.num_beams} "
        f"coverage={tr.metadata['coverage']:.2f} collisions={tr.metadata['collisions']} "
        f"dead-reckoning drift={drift:.3f} images={'yes' if tr.images is not None else 'no'} "
        f"-> {out}" + (f" (plot {plot})" if plot else "")
    )
    return 0


def cmd_slam(args) -> int:
    """Read the input, the configuration and the networks, then run SLAM into ``--out``
    (written into its ``.partial`` and put in place at the end: a failure leaves ``--out`` as
    it was)."""
    torch.manual_seed(args.seed)
    with run_folder(args.out, args.resume, args.overwrite) as folder:
        report = _slam(args, folder)
    _print_report(report, args.out)
    return 0


def _slam(args, folder) -> dict:
    """``slam``'s work inside its run folder (:class:`~pyro_slam.slam.outputs.RunFolder`)."""
    tr = _read(args)
    if args.steps:
        tr = tr.slice(0, min(args.steps, tr.num_steps))
    name, config = _config(args, tr)
    source = str(Path(args.traversal).resolve())
    emission = None
    if args.emission is not None:
        kind = emission_kind(config.emission.kind)
        if kind.load is None:
            raise DatasetError(
                f"--emission loads a pretrained emission network; emission.kind {kind.name!r} "
                "has none"
            )
        emission = kind.load(args.emission, tr)
    transition = None
    if args.transition is not None:
        if config.transition.kind != "learned":
            raise DatasetError(
                "--transition loads a learned transition network; transition.kind "
                f"{config.transition.kind!r} has none (set it to 'learned')"
            )
        transition = pretrained.load_transition(args.transition)
    return run_slam(
        tr,
        folder,
        args.mode,
        config,
        emission,
        transition,
        args.resume,
        seed=args.seed,
        preset=name,
        source=source,
        checkpoint_every=args.checkpoint_every,
        threads=args.threads,
        argv=args.argv,
        overrides=parse_overrides(args.config) if args.config else None,
    )


def _pretrain_out(args) -> Path:
    """``--out`` of ``pretrain``, refused inside the installed package's folder of shipped
    networks unless ``--into-package``, and where it would replace networks without
    ``--overwrite``."""
    package = pretrained.PRETRAINED.resolve()
    out = Path(args.out) if args.out is not None else None
    if out is None:
        out = package if args.into_package else Path("pretrained")
    inside = out.resolve() == package or package in out.resolve().parents
    if inside and not args.into_package:
        raise DatasetError(
            f"--out {out}: is inside the installed package ({package}), whose networks every "
            "run uses by default; pass --into-package to replace them there"
        )
    if out.exists() and not out.is_dir():
        raise DatasetError(f"--out {out}: exists and is not a folder")
    names = [
        n for n in (pretrained.EMISSION_FILE, pretrained.TRANSITION_FILE) if (out / n).exists()
    ]
    if names and not args.overwrite:
        raise DatasetError(
            f"--out {out}: holds {', '.join(names)}; use --overwrite to replace them, or "
            "another folder"
        )
    _writable(out / pretrained.EMISSION_FILE, "--out")
    return out


def _torch_writer(obj):
    """A writer of ``obj`` in ``torch.save``'s format (for :func:`atomic_write_all`)."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    data = buf.getvalue()
    return lambda f: f.write(data)


def cmd_pretrain(args) -> int:
    """Pretrain the emission and the learned transition; both files are written together at
    the end (a failure leaves the previous ones as they were)."""
    out = _pretrain_out(args)
    tr = simulate_traversal(args.maze, steps=args.steps, seed=args.seed)
    paper = presets.get("paper").config  # the paper's emission MLP and its grid
    em, stats = pretrain_emission([tr], paper, steps=args.emission_steps, seed=args.seed)
    blob = {
        "state_dict": em.state_dict(),
        "meta": {
            "n_world": em.n_world,
            "map_dim": em.map_dim,
            "scale": tr.max_range,
            "maze": args.maze,
            "seed": args.seed,
            **stats,
        },
    }
    tran, tstats = pretrain_transition([tr], epochs=args.transition_epochs, seed=args.seed)
    files = {
        out / pretrained.EMISSION_FILE: _torch_writer(blob),
        out / pretrained.TRANSITION_FILE: _torch_writer(tran.to_state()),
    }
    atomic_write_all(files)
    print(json.dumps({"emission": stats, "transition": tstats, "out": str(out)}, default=float))
    return 0


def cmd_demo(args) -> int:
    """Simulate the default maze, run SLAM with the default preset, write plots and metrics."""
    torch.manual_seed(args.seed)
    out = Path(args.out)
    with run_folder(out, args.resume, args.overwrite, keep=DEMO_INPUTS) as folder:
        tr = simulate_traversal(args.maze, steps=args.steps, seed=args.seed)
        _, config = presets.configure(args.preset, tr)
        inputs = {"traversal.npz": tr.save, "traversal.png": lambda p: plot_traversal(tr, p)}
        report = run_slam(
            tr,
            folder,
            args.mode,
            config,
            resume=args.resume,
            seed=args.seed,
            preset=args.preset,
            inputs=inputs,
            source=str((out / "traversal.npz").resolve()),
            checkpoint_every=args.checkpoint_every,
            threads=args.threads,
            argv=args.argv,
        )
    _print_report(report, out)
    return 0


# ----------------------------------------------------------------------------------- navigate
def _maze_of(tr: Traversal, src, args):
    """The simulator's maze a traversal was recorded in (its ``metadata.maze``), checked
    against its walls and against ``--maze`` / ``--maze-seed`` where given."""
    spec = tr.metadata.get("maze")
    if not (
        isinstance(spec, dict) and spec.get("name") in SCALES and isinstance(spec.get("seed"), int)
    ):
        raise DatasetError(
            f"{src}: field 'metadata.maze' names no simulated maze; navigate executes its plan "
            "in the simulator, so it needs a traversal simulated by pyro-slam"
        )
    for opt, given, have in (
        ("--maze", args.maze, spec["name"]),
        ("--maze-seed", args.maze_seed, spec["seed"]),
    ):
        if given is not None and given != have:
            raise DatasetError(
                f"{opt} {given}: {src} was recorded in maze {spec['name']} seed {spec['seed']}"
            )
    maze = make_maze(spec["name"], spec["seed"])
    if maze.walls.shape != tr.walls.shape or not np.allclose(maze.walls, tr.walls):
        raise DatasetError(
            f"{src}: field 'walls' differs from maze {spec['name']} seed {spec['seed']} "
            "(rotated or edited): navigate executes its plan in the simulator's own maze"
        )
    return maze


def _same_maze(report: dict, tr: Traversal, path, run_dir) -> None:
    """Refuse a traversal ``tr`` of another maze than the one the run in ``run_dir`` mapped
    (its ``metrics.json``: the walls' fingerprint, or, in older runs, the maze's name and
    seed)."""
    walls, maze = report.get("walls"), (report.get("metadata") or {}).get("maze")
    if isinstance(walls, str):
        same = walls == walls_fingerprint(tr.walls)
    else:
        same = maze is None or maze == tr.metadata.get("maze")
    if not same:
        what = "" if maze is None else f" (maze {maze.get('name')} seed {maze.get('seed')})"
        raise DatasetError(
            f"{path}: field 'walls' differs from the maze the run --from {run_dir} mapped"
            f"{what}: give the traversal that run mapped"
        )


def _navigation_data(args):
    """``(maze, mapping traversal, run)``: simulated here (``--seed``), given
    (``--traversal``), or a finished SLAM run's (``--from``; ``run`` from
    :func:`~pyro_slam.slam.outputs.read_run`, else None)."""
    if args.from_run is None and args.traversal is None:
        maze = make_maze(
            args.maze or DEFAULT_MAZE,
            DEFAULT_MAZE_SEED if args.maze_seed is None else args.maze_seed,
        )
        return maze, simulate_traversal(maze, steps=args.traversal_steps, seed=args.seed), None
    run = None
    path = args.traversal
    if args.from_run is not None:
        if args.map is not None:
            raise DatasetError("--map: the map of --from is the SLAM run's own; give one of them")
        run = read_run(args.from_run)
        own = Path(args.from_run) / DEMO_INPUTS[0]  # a demo run keeps its traversal
        path = path or (own if own.is_file() else run["metrics"].get("input"))
        if path is None:
            raise DatasetError(
                f"--from {args.from_run}: its metrics.json names no input; "
                "give the run's traversal with --traversal"
            )
    tr = read_any(path)
    if run is not None and run["metrics"]["steps"] != tr.num_steps:
        tr = tr.slice(0, min(run["metrics"]["steps"], tr.num_steps))  # (a run of --steps N)
    if run is not None:
        _same_maze(run["metrics"], tr, path, args.from_run)
    if run is not None and run["pose_mean"].shape[0] != tr.num_steps:
        raise DatasetError(
            f"{path}: {tr.num_steps} steps, but the run --from "
            f"{args.from_run} has {run['pose_mean'].shape[0]}"
        )
    return _maze_of(tr, path, args), tr, run


def _navigation_map(args, maze, tr, run):
    """The learned environment of ``navigate``: the SLAM run's own ``q(M)`` (``--from``), or
    ``q(M)`` fitted at the true poses or at an online SLAM run's pose means (``--map slam``,
    the ``paper`` preset: the map the planner reads is the paper's chart map)."""
    if run is not None:
        try:
            return run_env(
                maze,
                tr,
                from_dict(run["metrics"]["config"]),
                run["map_loc"],
                run["map_scale"],
                run["pose_mean"],
            )
        except (ConfigError, ValueError, TypeError) as e:
            raise DatasetError(f"--from {args.from_run}: {one_line(e)}") from None
    poses = None
    if args.map == "slam":
        res = SLAM(tr, presets.get("paper").config, seed=args.seed).run("online", progress=True)
        poses = np.asarray(res["mean"])
    lenv, _, _ = learned_env(
        maze,
        tr,
        fit_steps=args.fit_steps,
        poses=poses,
        progress=True,
        seed=args.seed,
        emission_steps=args.emission_steps,
        n_world=args.n_world,
    )
    return lenv


def _observation_goal(args, maze, lenv, tr):
    """``--target-scan-from-pose``: the goals inferred from the target's scan (``[k, 3]``, best
    first: the learned inverse model's modes, or the truth's best-matching place), the target,
    the number of exact look-alike places of its scan, and the agent's look (its own view,
    turning on the spot, matched against the target scan: :class:`~pyro_slam.planning.Look`)."""
    target = np.array(args.target_scan_from_pose)
    truth = GroundTruthEnv(maze)
    tscan = truth.scan(target)  # [1, B]
    pz, pd = truth.places(tscan.numpy())[0]  # every place that looks like the target
    n_lookalikes = lookalikes(pz, pd, target)[0]
    look = Look(truth, tscan[0].numpy())  # the agent's own view, matched against the target
    if args.planner == "learned":
        inv = fit_inverse(
            lenv, tr, steps=args.inverse_steps, sleep_steps=args.inverse_sleep_steps, progress=True
        )
        hyps = inv.modes(tscan, k=NAVIGATION.hypotheses, separation=NAVIGATION.mode_separation)
        return hyps[0].numpy(), target, n_lookalikes, look
    return pz[:1], target, n_lookalikes, look  # the truth's own inverse: its best place


def cmd_navigate(args) -> int:
    """Plan with hybrid A*, execute the plan in the simulator, plot both and print a JSON
    report; exit status 1 when no plan was found. An observation target's goals are the
    inverse model's modes, visited in turn (:func:`~pyro_slam.planning.seek_observation`)."""
    _writable(Path(args.out), "--out", args.overwrite)
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    maze, tr, run = _navigation_data(args)
    pts = free_grid(maze)
    start = np.array(args.start) if args.start else np.array([*pts[0], 0.0])
    goal = np.array(args.goal) if args.goal else pts[-1]
    check_endpoints(maze_bounds(maze), start, goal, ("--start", "--goal"))
    if args.target_scan_from_pose is not None:
        target = args.target_scan_from_pose
        check_endpoints(maze_bounds(maze), start, target, ("--start", "--target-scan-from-pose"))
    lenv = _navigation_map(args, maze, tr, run)
    if args.planner == "learned":  # the agent's own scan at the start: trusted free space
        env = lenv.with_observation(start, GroundTruthEnv(maze).scan(start)[0].numpy())
    else:
        env = GroundTruthEnv(maze)
    hyps, target, n_lookalikes = np.asarray(goal)[None, :2], None, None
    look, accept_tol = (lambda z: (0.0, np.zeros(2))), np.inf  # a pose target: no view to check
    if args.target_scan_from_pose is not None:
        hyps, target, n_lookalikes, look = _observation_goal(args, maze, lenv, tr)
        accept_tol = NAVIGATION.accept_tol
    mover = Mover(maze, noise=None if args.noise else 0, seed=args.seed)
    # the learned planner's agent scans where a goal has no plan yet
    sense = sensor(GroundTruthEnv(maze)) if args.planner == "learned" else None
    res = seek_observation(
        env,
        start,
        hyps,
        mover,
        look,
        accept_tol=accept_tol,
        sense=sense,
        max_expansions=args.max_expansions,
    )
    executed, inferred = res.poses, None if target is None else hyps[0]
    true_goal = goal if target is None else target[:2]
    err = float(np.hypot(*(executed[-1, :2] - true_goal)))
    title = f"maze {maze.seed}, {args.planner} planner" + (
        "" if inferred is None else " (x: goal inferred from the target scan)"
    )
    shown = lenv if args.planner == "learned" else env
    plot_navigation(
        maze, shown, res.as_plan(), executed, true_goal, args.out, title, inferred=inferred
    )
    report = {
        "found": res.found,
        "expansions": res.expansions,
        "steps": len(res.controls),
        "final_error": err,
        "success": bool(res.found and err <= 0.05),
        "collisions": mover.collisions,
        "scans": res.scans,
        "plot": str(args.out),
    }
    if inferred is not None:
        report["inferred_goal"] = inferred.tolist()
        report["inference_error"] = float(np.hypot(*(inferred[:2] - target[:2])))
        report["target_lookalikes_exact"] = n_lookalikes  # places > 0.05 away that look the same
        report["goals_visited"] = len(res.goals)
        report["view_differences"] = [d if np.isfinite(d) else None for d in res.diffs]
    print(json.dumps(report))
    return 0 if res.found else 1


# ----------------------------------------------------------------------------------- parsers
def _sub(sub, name: str, summary: str, description: str, **kw) -> argparse.ArgumentParser:
    """A sub-command's parser: ``summary`` in the command list, ``description`` atop its help."""
    text = textwrap.fill(description, 88)
    return sub.add_parser(name, help=summary, description=text, formatter_class=_Help, **kw)


def _add_simulate(sub) -> None:
    p = _sub(
        sub,
        "simulate",
        "simulate a maze traversal and save it as .npz",
        "Simulate an agent exploring a generated maze with a LiDAR (and, with --images, a "
        "camera): the data set SLAM runs on, and a plot of it.",
    )
    p.add_argument("--maze", default="moderate-medium", choices=sorted(SCALES), help="maze scale")
    p.add_argument(
        "--steps", type=STEPS, default=3000, help=f"number of time steps T (at most {MAX_STEPS})"
    )
    p.add_argument("--seed", type=SEED, default=1, help="seeds maze, noise and driver")
    p.add_argument("--out", type=Path, default=Path("traversal.npz"), help="output .npz")
    p.add_argument("--images", action="store_true", help="also render 32x24 camera frames")
    p.add_argument(
        "--distractors",
        type=_number(int, 0, high=MAX_DISTRACTORS),
        default=0,
        help=f"boxes not in the floor map (at most {MAX_DISTRACTORS})",
    )
    p.add_argument("--plot", type=Path, default=None, help="output PNG (default: next to --out)")
    p.add_argument("--no-plot", action="store_true", help="do not write a PNG")
    p.set_defaults(func=cmd_simulate)


def _add_run_options(p, out: str, what: str) -> None:
    """The options ``slam`` and ``demo`` share: the folder, the mode, resume or overwrite."""
    p.add_argument("--out", type=Path, default=Path(out), help=f"folder for {what}")
    p.add_argument(
        "--mode",
        choices=["online", "offline"],
        default="online",
        help="online: one filtering sweep with SVI; offline: then rounds of SVI on "
        "the whole traversal",
    )
    again = p.add_mutually_exclusive_group()
    again.add_argument(
        "--resume",
        action="store_true",
        help="continue the interrupted run kept in OUT (OUT/.partial), or the run in OUT, "
        "from its checkpoint.pt",
    )
    again.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the run in a non-empty OUT once the new one has finished (a run is "
        "written into OUT/.partial and put in place at its end: a failure leaves OUT as it was)",
    )
    p.add_argument(
        "--checkpoint-every",
        type=POSITIVE,
        default=CHECKPOINT_EVERY,
        metavar="N",
        help="write OUT/checkpoint.pt every N steps (and at the end)",
    )
    p.add_argument(
        "--threads",
        type=THREADS,
        default=DEFAULT_THREADS,
        metavar="N",
        help="torch intra-op threads (the results depend on N, never on the machine's load; "
        "recorded in metrics.json)",
    )


def _add_slam(sub) -> None:
    s = _sub(
        sub,
        "slam",
        "run DVBF-LM SLAM on a traversal (.npz, CARMEN, ROS bag)",
        "Run DVBF-LM SLAM on a simulated traversal (.npz) or a real laser log (CARMEN .clf / "
        ".log, ROS 1 .bag, ROS 2 bag folder) and write plots, trajectories (TUM), the "
        "posterior, the occupancy map, metrics.json and a resumable checkpoint into OUT.",
        epilog="presets:\n" + presets.describe(),
    )
    s.add_argument("traversal", type=Path, help="the input: .npz, .clf / .log, .bag or a folder")
    _add_run_options(s, "run", "the run's outputs")
    s.add_argument("--steps", type=COUNT, default=0, help="use only the first N steps (0: all)")
    s.add_argument("--seed", type=SEED, default=0, help="seeds Pyro and the particle filter")
    s.add_argument(
        "--preset",
        choices=list(presets.PRESETS),
        default=None,
        help=f"named configuration (default: {presets.DEFAULT}; 'real' for real laser logs)",
    )
    s.add_argument(
        "--config",
        help="JSON object (or file) of overrides on top of the preset, e.g. "
        '\'{"filter": {"particles": 256}}\' (default: none)',
    )
    s.add_argument(
        "--emission",
        help="a pretrained LiDAR emission MLP .pt (emission.kind 'mlp'; default: the shipped "
        "one when the sensor matches the simulator's)",
    )
    s.add_argument(
        "--transition",
        help="a pretrained LearnedTransition .pt (default: the preset's: the shipped one for "
        "transition.kind 'learned')",
    )
    s.add_argument(
        "--lenient",
        action="store_true",
        help="CARMEN logs: skip malformed lines; ROS bags: skip scans whose stamps do not go "
        "forward (counted and listed in metrics.json, said on stderr) instead of stopping at "
        "the first",
    )
    s.add_argument(
        "--odometry-noise",
        type=_number(float, 0.0, inclusive=False),
        help="the real preset: transition std on x/y as this fraction of the RMS odometry step "
        f"(default {presets.REAL_LOG.odometry_noise:g}; the heading's is the drift that the "
        "scans' walls show, else a share of the motion; refused with another preset)",
    )
    s.add_argument(
        "--scan-topic",
        help="ROS bags: the LaserScan topic (default: the bag's only one)",
    )
    s.add_argument(
        "--odom-topic",
        help="ROS bags: the Odometry topic (default: the bag's only one; without one, "
        "odometry from /tf, odom -> the laser's base frame)",
    )
    s.add_argument(
        "--no-odometry",
        action="store_true",
        help="ROS bags: ignore any odometry, zero controls (a bag without odometry is refused "
        "otherwise)",
    )
    s.add_argument(
        "--laser-offset",
        type=FINITE,
        nargs=3,
        metavar=("X", "Y", "YAW"),
        help="ROS bags: the laser's pose on the odometry's frame (metres, rad), instead of "
        "/tf_static and /tf (default: from the bag's transforms; refused where they are none)",
    )
    s.set_defaults(func=cmd_slam)


def _add_pretrain(sub) -> None:
    t = _sub(
        sub,
        "pretrain",
        "pretrain emission + transition on a held-out maze",
        "Pretrain the LiDAR emission MLP and the learned transition on a simulated held-out "
        "maze and write them into OUT (use them with slam --emission / --transition). The "
        "networks shipped inside the installed package are replaced only with --into-package.",
    )
    t.add_argument(
        "--out",
        type=Path,
        default=None,
        help="folder for the two network files (default: pretrained/ in the current folder; "
        "with --into-package the package's own)",
    )
    t.add_argument(
        "--into-package",
        action="store_true",
        help=f"allow writing into the installed package's networks ({pretrained.PRETRAINED})",
    )
    t.add_argument("--overwrite", action="store_true", help="replace network files in OUT")
    t.add_argument("--maze", default="moderate-medium", choices=sorted(SCALES), help="maze scale")
    t.add_argument("--seed", type=SEED, default=100, help="maze and training seed")
    t.add_argument("--steps", type=STEPS, default=6000, help="steps of the training traversal")
    t.add_argument("--emission-steps", type=POSITIVE, default=3000, help="emission SGD steps")
    t.add_argument("--transition-epochs", type=POSITIVE, default=30, help="transition epochs")
    t.set_defaults(func=cmd_pretrain)


def _add_demo(sub) -> None:
    d = _sub(
        sub,
        "demo",
        "simulate the default maze and run SLAM (plots + metrics)",
        "Simulate a maze traversal and run SLAM on it: the traversal, plots, trajectories, "
        "the posterior, metrics.json and a checkpoint in OUT (what `make demo` runs).",
    )
    _add_run_options(d, "out", "the traversal and the run's outputs")
    d.add_argument("--maze", default="moderate-medium", choices=sorted(SCALES), help="maze scale")
    d.add_argument(
        "--steps", type=STEPS, default=3000, help=f"number of time steps T (at most {MAX_STEPS})"
    )
    d.add_argument("--seed", type=SEED, default=1, help="seeds the simulation and SLAM")
    d.add_argument(
        "--preset", choices=list(presets.PRESETS), default=presets.DEFAULT, help="SLAM preset"
    )
    d.set_defaults(func=cmd_demo)


def _add_navigate_inputs(p) -> None:
    """Where ``navigate``'s maze and map come from."""
    p.add_argument(
        "--from",
        dest="from_run",
        type=Path,
        metavar="OUT",
        help="plan in the map of a finished SLAM run: OUT/posterior.npz and OUT/metrics.json "
        "(its traversal: OUT/traversal.npz, the input metrics.json names, or --traversal; "
        "default: no run)",
    )
    p.add_argument(
        "--traversal",
        type=Path,
        help="a simulated traversal (.npz) to map and plan in (its maze is the one the plan "
        "runs in; default: simulate one of --traversal-steps steps)",
    )
    p.add_argument(
        "--maze",
        choices=sorted(SCALES),
        help=f"maze scale (default: {DEFAULT_MAZE}, or the traversal's)",
    )
    p.add_argument(
        "--maze-seed",
        type=SEED,
        help=f"maze seed (default: {DEFAULT_MAZE_SEED}, or the traversal's)",
    )
    p.add_argument(
        "--map",
        choices=["known_poses", "slam"],
        help="q(M) fitted at the true poses, or at the pose means of an online SLAM run with "
        "the 'paper' preset (default: known_poses; with --from the run's own map)",
    )
    p.add_argument("--seed", type=SEED, default=1, help="seeds the simulation, fits and actuation")
    p.add_argument(
        "--traversal-steps",
        type=STEPS,
        default=NAVIGATION.traversal_steps,
        help="mapping traversal T",
    )
    p.add_argument(
        "--fit-steps", type=POSITIVE, default=NAVIGATION.fit_steps, help="SVI steps fitting q(M)"
    )
    p.add_argument(
        "--emission-steps",
        type=COUNT,
        default=NAVIGATION.emission_steps,
        help="fit the emission on the mapping traversal for this many steps (0: the shipped "
        "one, frozen)",
    )
    p.add_argument(
        "--n-world",
        type=_number(int, 20),
        default=NAVIGATION.n_world,
        help="world directions of a fitted emission",
    )


def _add_navigate(sub) -> None:
    p = _sub(
        sub,
        "navigate",
        "plan with hybrid A* in the learned model and execute in the simulator",
        "Plan a path with hybrid A* in a learned map (a finished SLAM run's, or one fitted "
        "here), execute it open loop in the simulator, plot both and print a JSON report. "
        "Exit status 1 when no plan is found.",
    )
    _add_navigate_inputs(p)
    p.add_argument(
        "--start",
        type=FINITE,
        nargs=3,
        metavar=("X", "Y", "H"),
        help="start pose (default: the first free grid point, heading 0)",
    )
    p.add_argument(
        "--goal",
        type=FINITE,
        nargs=2,
        metavar=("X", "Y"),
        help="goal position (default: the last free grid point)",
    )
    p.add_argument(
        "--target-scan-from-pose",
        type=FINITE,
        nargs=3,
        metavar=("X", "Y", "H"),
        help="observation target: render the simulator's scan at this pose and infer the goal "
        "with the inverse model q(z|x) (with --planner ground_truth the truth's own inverse, "
        "GroundTruthEnv.places); overrides --goal (default: none)",
    )
    p.add_argument("--inverse-steps", type=POSITIVE, default=1000, help="ELBO steps of q(z|x)")
    p.add_argument("--inverse-sleep-steps", type=COUNT, default=3000, help="sleep steps of q(z|x)")
    p.add_argument(
        "--planner",
        choices=["learned", "ground_truth"],
        default="learned",
        help="plan in the learned map, or in the simulator's truth",
    )
    p.add_argument(
        "--max-expansions",
        type=POSITIVE,
        default=NAVIGATION.max_expansions,
        help="A* node expansions",
    )
    p.add_argument("--noise", action="store_true", help="execute with actuation noise")
    p.add_argument("--out", type=Path, default=Path("navigate.png"), help="output plot (PNG)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    p.set_defaults(func=cmd_navigate)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="pyro-slam",
        description="DVBF-LM SLAM in Pyro: simulate maze traversals, run SLAM on them or on\n"
        "real laser logs, plan in the learned map, pretrain the networks.",
        epilog="`pyro-slam command --help` describes each command.",
        formatter_class=_Help,
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    talk = p.add_mutually_exclusive_group()
    talk.add_argument(
        "--verbose", action="store_true", help="log the library's progress messages (INFO)"
    )
    talk.add_argument("--quiet", action="store_true", help="log errors only, no warnings")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser, metavar="command")
    for add in (_add_simulate, _add_slam, _add_demo, _add_navigate, _add_pretrain):
        add(sub)
    return p


LOGGERS = ("pyro_slam", "simulators")  # the packages whose log messages the command shows


@contextlib.contextmanager
def _logging(args):
    """The packages' log messages on stderr for the command's duration: warnings and errors
    (default), also INFO with ``--verbose``, errors only with ``--quiet``. (Progress bars are
    not log messages: they stay.)"""
    level = logging.ERROR if args.quiet else logging.INFO if args.verbose else logging.WARNING
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(f"pyro-slam {args.command}: %(levelname)s: %(message)s"))
    loggers = [logging.getLogger(name) for name in LOGGERS]
    before = [(lg.level, lg.propagate) for lg in loggers]
    for lg in loggers:
        lg.setLevel(level)
        lg.addHandler(handler)
        lg.propagate = False
    try:
        yield
    finally:
        for lg, (lvl, prop) in zip(loggers, before):
            lg.removeHandler(handler)
            lg.setLevel(lvl)
            lg.propagate = prop


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    args.argv = ["pyro-slam", *(sys.argv[1:] if argv is None else argv)]  # for metrics.json
    try:
        with _logging(args), terminate_as_interrupt():  # SIGTERM cleans up as SIGINT does
            return args.func(args)
    except (DatasetError, FileNotFoundError, ValueError, MissingExtra) as e:
        print(f"pyro-slam {args.command}: error: {e}", file=sys.stderr)
        return 2
    except (OSError, MemoryError) as e:  # the machine refused: disk, permissions, memory
        why = f"{type(e).__name__}: {one_line(e)}"
        print(f"pyro-slam {args.command}: error: {why}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:  # SIGINT, or SIGTERM during a run (outputs.Interrupted)
        sig = getattr(e, "signal", "SIGINT")
        print(
            f"pyro-slam {args.command}: {one_line(e) if str(e) else 'interrupted (SIGINT)'}",
            file=sys.stderr,
        )
        return 128 + getattr(signal, sig, signal.SIGINT)


if __name__ == "__main__":
    raise SystemExit(main())
