"""The ``pyro-slam`` command line: the only argparse layer of the project.

    pyro-slam simulate --maze moderate-medium --steps 3000 --seed 1 --out traversal.npz
    pyro-slam slam traversal.npz --mode online --out run/     # also .clf / .log / ROS bags
    pyro-slam slam traversal.npz --preset manhattan --config '{"filter": {"particles": 256}}'
    pyro-slam slam traversal.npz --out run/ --resume          # continue from run/checkpoint.pt
    pyro-slam demo --out out/                       # simulate + SLAM + plots + metrics.json
    pyro-slam navigate --maze-seed 1001             # hybrid A* in the learned model
    pyro-slam pretrain --out pretrained/            # emission + learned transition

Every sub-command validates its inputs before computing and exits with status 2 and a one-line
message naming the file and problem on bad input.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import torch

from simulators import make_maze, simulate_traversal
from simulators.maze import SCALES
from simulators.plotting import plot_traversal
from simulators.traversal import integrate_controls

from . import pretrained
from .data import DatasetError, Traversal, one_line
from .extras import MissingExtra
from .io import read_any
from .model import pretrain_transition
from .planning import GroundTruthEnv, execute, free_grid, learned_env, lookalikes, plan
from .planning.inverse import fit_inverse
from .plotting import plot_navigation
from .slam import SLAM, ConfigError, SLAMConfig, presets, with_overrides
from .slam.outputs import prepare_out_dir, run_slam
from .slam.training import pretrain_emission


# ----------------------------------------------------------------------------------- helpers
class _Parser(argparse.ArgumentParser):
    """Usage errors as one line naming the option (``prog: error: ...``), exit status 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def _number(kind, low: float, inclusive: bool = True):
    """An argparse type: ``kind`` (int or float), finite, at least (or above) ``low``."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {kind.__name__}, got {text!r}") from None
        if not math.isfinite(value) or value < low or (value == low and not inclusive):
            bound = f">= {low:g}" if inclusive else f"> {low:g}"
            raise argparse.ArgumentTypeError(f"must be {bound}, got {text}")
        return value

    parse.__name__ = kind.__name__
    return parse


COUNT = _number(int, 0)  # 0 or more
POSITIVE = _number(int, 1)
FINITE = _number(float, -math.inf)


def _read(args) -> Traversal:
    """The input traversal (``--lenient``: a log's malformed lines are skipped and counted)."""
    kw = {"lenient": True} if getattr(args, "lenient", False) else {}
    path = Path(args.traversal)
    if kw and path.suffix.lower() == ".npz":
        raise DatasetError(f"{path}: --lenient applies to text logs, not .npz data sets")
    return read_any(path, **kw)


def _config(args, traversal: Traversal) -> tuple[str, SLAMConfig]:
    """The preset named by ``--preset`` (default: ``real`` for a real log, else the default
    preset) for this traversal, with the ``--config`` JSON overrides (a string or a file)."""
    name = args.preset or ("real" if presets.is_real_log(traversal) else presets.DEFAULT)
    preset = presets.get(name)
    if getattr(args, "odometry_noise", None) is not None and preset.adapt is presets.adapt_real_log:
        config = presets.adapt_real_log(
            traversal, preset.config, odometry_noise=args.odometry_noise
        )
    else:
        config = preset.for_traversal(traversal)
    if args.config:
        text = args.config
        if not text.lstrip().startswith("{"):  # a file of JSON
            try:
                text = Path(text).read_text()
            except (OSError, UnicodeDecodeError) as e:
                raise DatasetError(f"--config {text[:60]!r}: not a JSON object, nor a readable "
                                   f"file ({one_line(e)})") from None  # fmt: skip
        try:
            over = json.loads(text)
        except json.JSONDecodeError as e:
            raise DatasetError(f"--config: not a JSON object or file: {e}") from e
        try:
            config = with_overrides(config, over)
        except ConfigError as e:
            raise DatasetError(f"--config: {e}") from e
    return name, config


def _print_report(report: dict, out: Path) -> None:
    line = f"slam ({report['preset']}, {report['mode']}): T={report['steps']}"
    line += f" {report['wall_time_s']:.0f}s"
    if "slam" in report:
        s, p = report["slam"], report["path_integration"]
        line += (
            f" | final error SLAM {s['final_error']:.4f} vs path integration {p['final_error']:.4f}"
        )
        if "ate" in s:  # (evo, the [eval] extra)
            line += f" | ATE rmse {s['ate']['rmse']:.4f} vs {p['ate']['rmse']:.4f}"
    if "scan_consistency" in report:
        c = report["scan_consistency"]
        line += (
            f" | scan consistency SLAM {c['slam']['mean']:.3f} vs path integration "
            f"{c['path_integration']['mean']:.3f}"
        )
    print(line + f" -> {out}/ (metrics.json, slam.png, map.png / error.png, checkpoint.pt)")


# ----------------------------------------------------------------------------------- commands
DEMO_INPUTS = ("traversal.npz", "traversal.png")


def _writable(path: Path, what: str) -> None:
    """Refuse an output path that cannot be written (before any work is done)."""
    if path.is_dir():
        raise DatasetError(f"{what} {path}: is a folder, not a file")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        probe = path.parent / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise DatasetError(f"{what} {path}: cannot write there ({e.strerror or e})") from None


def cmd_simulate(args) -> int:
    """Simulate a traversal, save it (``.npz``) and a plot of it; print a one-line summary.
    Both outputs are checked first and written atomically, so a failure loses no file."""
    out = Path(args.out)
    plot_path = None if args.no_plot else Path(args.plot or out.with_suffix(".png"))
    _writable(out, "--out")
    if plot_path is not None:
        _writable(plot_path, "--plot")
    tr = simulate_traversal(
        args.maze, args.steps, args.seed, images=args.images, distractors=args.distractors
    )
    plot = None if plot_path is None else plot_traversal(tr, plot_path)
    out = tr.save(out)
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
    torch.manual_seed(args.seed)
    prepare_out_dir(args.out, args.resume, args.overwrite)
    tr = _read(args)
    if args.steps:
        tr = tr.slice(0, min(args.steps, tr.num_steps))
    name, config = _config(args, tr)
    emission = None
    if args.emission is not None:
        if config.emission.kind != "mlp":
            raise DatasetError(
                f"--emission loads a LiDAR emission MLP; emission.kind {config.emission.kind!r} "
                "has none"
            )
        emission = pretrained.load_emission(args.emission, tr)
    transition = pretrained.load_transition(args.transition) if args.transition else None
    report = run_slam(tr, args.out, args.mode, config, emission, transition, args.resume,
                      seed=args.seed, preset=name)  # fmt: skip
    _print_report(report, args.out)
    return 0


def cmd_pretrain(args) -> int:
    if args.out.exists() and not args.out.is_dir():
        raise DatasetError(f"--out {args.out}: exists and is not a folder")
    _writable(args.out / pretrained.EMISSION_FILE, "--out")
    tr = simulate_traversal(args.maze, steps=args.steps, seed=args.seed)
    em, stats = pretrain_emission([tr], SLAMConfig(), steps=args.emission_steps, seed=args.seed)
    blob = {
        "state_dict": em.state_dict(),
        "meta": {"n_world": em.n_world, "map_dim": em.map_dim, "scale": tr.max_range,
                 "maze": args.maze, "seed": args.seed, **stats},
    }  # fmt: skip
    torch.save(blob, args.out / pretrained.EMISSION_FILE)
    tran, tstats = pretrain_transition([tr], epochs=args.transition_epochs, seed=args.seed)
    torch.save(tran.to_state(), args.out / pretrained.TRANSITION_FILE)
    print(json.dumps({"emission": stats, "transition": tstats}, default=float))
    return 0


def cmd_demo(args) -> int:
    """Simulate the default maze, run SLAM with the default preset, write plots and metrics."""
    torch.manual_seed(args.seed)
    out = Path(args.out)
    prepare_out_dir(out, args.resume, args.overwrite, keep=DEMO_INPUTS)
    if args.overwrite:
        for name in DEMO_INPUTS:
            (out / name).unlink(missing_ok=True)
    tr = simulate_traversal(args.maze, steps=args.steps, seed=args.seed)
    tr.save(out / "traversal.npz")
    plot_traversal(tr, out / "traversal.png")
    config = presets.get(args.preset).for_traversal(tr)
    report = run_slam(tr, out, args.mode, config, resume=args.resume, seed=args.seed,
                      preset=args.preset)  # fmt: skip
    _print_report(report, out)
    return 0


def _navigation_map(args, maze, tr):
    """The learned environment of ``navigate``: ``q(M)`` fitted at the true poses or at an
    online SLAM run's pose means (``--map slam``, the ``paper`` preset: the map the planner
    reads is the paper's chart map)."""
    poses = None
    if args.map == "slam":
        res = SLAM(tr, presets.get("paper").config).run("online", progress=True)
        poses = np.asarray(res["mean"])
    lenv, _, _ = learned_env(
        maze, tr, fit_steps=args.fit_steps, poses=poses, progress=True,
        emission_steps=args.emission_steps, n_world=args.n_world,
    )  # fmt: skip
    return lenv


def _observation_goal(args, maze, lenv, tr):
    """``--target-scan-from-pose``: the goal inferred from the target's scan, the target, and
    the number of exact look-alike places of its scan."""
    target = np.array(args.target_scan_from_pose)
    truth = GroundTruthEnv(maze)
    tscan = truth.scan(target)  # [1, B]
    pz, pd = truth.places(tscan.numpy())[0]  # every place that looks like the target
    n_lookalikes = lookalikes(pz, pd, target)[0]
    if args.planner == "learned":
        inv = fit_inverse(lenv, tr, steps=args.inverse_steps, sleep_steps=args.inverse_sleep_steps,
                          progress=True)  # fmt: skip
        return inv.infer(tscan[0])[0].numpy(), target, n_lookalikes
    return pz[0], target, n_lookalikes  # the truth's own inverse: its best-matching place


def cmd_navigate(args) -> int:
    _writable(Path(args.out), "--out")
    torch.set_num_threads(1)
    maze = make_maze(args.maze, args.maze_seed)
    pts = free_grid(maze)
    start = np.array(args.start) if args.start else np.array([*pts[0], 0.0])
    goal = np.array(args.goal) if args.goal else pts[-1]
    tr = simulate_traversal(maze, steps=args.traversal_steps, seed=1)
    lenv = _navigation_map(args, maze, tr)
    if args.planner == "learned":  # the agent's own scan at the start: trusted free space
        env = lenv.with_observation(start, GroundTruthEnv(maze).scan(start)[0].numpy())
    else:
        env = GroundTruthEnv(maze)
    inferred = target = n_lookalikes = None
    if args.target_scan_from_pose is not None:
        inferred, target, n_lookalikes = _observation_goal(args, maze, lenv, tr)
        goal = inferred[:2]
    res = plan(env, start, goal, max_expansions=args.max_expansions)
    executed, coll = execute(maze, start, res.controls, noise=None if args.noise else 0)
    true_goal = goal if inferred is None else target[:2]
    err = float(np.hypot(*(executed[-1, :2] - true_goal)))
    title = f"maze {args.maze_seed}, {args.planner} planner" + (
        "" if inferred is None else " (x: goal inferred from the target scan)"
    )
    shown = lenv if args.planner == "learned" else env
    plot_navigation(maze, shown, res, executed, true_goal, args.out, title, inferred=inferred)
    report = {"found": res.success, "expansions": res.expansions, "steps": len(res.controls),
              "final_error": err, "success": bool(res.success and err <= 0.05),
              "collisions": int(coll), "plot": str(args.out)}  # fmt: skip
    if inferred is not None:
        report["inferred_goal"] = inferred.tolist()
        report["inference_error"] = float(np.hypot(*(inferred[:2] - target[:2])))
        report["target_lookalikes_exact"] = n_lookalikes  # places > 0.05 away that look the same
    print(json.dumps(report))
    return 0


# ----------------------------------------------------------------------------------- parsers
def _add_simulate(sub) -> None:
    p = sub.add_parser("simulate", help="simulate a maze traversal and save it as .npz")
    p.add_argument("--maze", default="moderate-medium", choices=sorted(SCALES), help="maze scale")
    p.add_argument("--steps", type=POSITIVE, default=3000, help="number of time steps T")
    p.add_argument("--seed", type=COUNT, default=1, help="seeds maze, noise and driver")
    p.add_argument("--out", type=Path, default=Path("traversal.npz"), help="output .npz")
    p.add_argument("--images", action="store_true", help="also render 32x24 camera frames")
    p.add_argument("--distractors", type=COUNT, default=0, help="boxes not in the floor map")
    p.add_argument("--plot", type=Path, default=None, help="output PNG (default: next to --out)")
    p.add_argument("--no-plot", action="store_true", help="do not write a PNG")
    p.set_defaults(func=cmd_simulate)


def _add_slam(sub) -> None:
    s = sub.add_parser(
        "slam", help="run DVBF-LM SLAM on a traversal (.npz, CARMEN, ROS bag)",
        epilog="presets:\n" + presets.describe(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    s.add_argument("traversal", type=Path)
    s.add_argument("--mode", choices=["online", "offline"], default="online")
    s.add_argument("--out", type=Path, default=Path("run"))
    s.add_argument("--steps", type=COUNT, default=0, help="use only the first N steps (0: all)")
    s.add_argument("--seed", type=COUNT, default=0)
    s.add_argument(
        "--preset", choices=list(presets.PRESETS), default=None,
        help=f"named configuration (default: {presets.DEFAULT}; 'real' for real laser logs)",
    )  # fmt: skip
    s.add_argument("--config", help="JSON object (or file) of overrides, e.g. "
                   '\'{"filter": {"particles": 256}}\'')  # fmt: skip
    s.add_argument("--emission", help="a pretrained LiDAR emission MLP .pt (emission.kind 'mlp'; "
                   "default: the shipped one when the sensor matches the simulator's)")  # fmt: skip
    s.add_argument("--transition", help="a pretrained LearnedTransition .pt (default: the "
                   "preset's: the shipped one for transition.kind 'learned')")  # fmt: skip
    s.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    s.add_argument("--overwrite", action="store_true", help="replace the run in a non-empty OUT")
    s.add_argument("--lenient", action="store_true",
                   help="text logs: skip malformed lines (counted in metrics.json) instead of "
                   "stopping at the first")  # fmt: skip
    s.add_argument(
        "--odometry-noise", type=_number(float, 0.0, inclusive=False),
        help="real logs: transition std as this fraction of the RMS odometry step (default 0.1)",
    )  # fmt: skip
    s.set_defaults(func=cmd_slam)


def _add_pretrain_and_demo(sub) -> None:
    t = sub.add_parser("pretrain", help="pretrain emission + transition on a held-out maze")
    t.add_argument("--out", type=Path, default=pretrained.PRETRAINED)
    t.add_argument("--maze", default="moderate-medium")
    t.add_argument("--seed", type=COUNT, default=100)
    t.add_argument("--steps", type=POSITIVE, default=6000)
    t.add_argument("--emission-steps", type=POSITIVE, default=3000)
    t.add_argument("--transition-epochs", type=POSITIVE, default=30)
    t.set_defaults(func=cmd_pretrain)
    d = sub.add_parser("demo", help="simulate the default maze and run SLAM (plots + metrics)")
    d.add_argument("--out", type=Path, default=Path("out"))
    d.add_argument("--maze", default="moderate-medium")
    d.add_argument("--steps", type=POSITIVE, default=3000)
    d.add_argument("--seed", type=COUNT, default=1)
    d.add_argument("--mode", choices=["online", "offline"], default="online")
    d.add_argument("--preset", choices=list(presets.PRESETS), default=presets.DEFAULT)
    d.add_argument("--resume", action="store_true", help="continue the demo run in OUT")
    d.add_argument("--overwrite", action="store_true", help="replace the demo run in OUT")
    d.set_defaults(func=cmd_demo)


def _add_navigate(sub) -> None:
    p = sub.add_parser(
        "navigate", help="plan with hybrid A* in the learned model and execute in the simulator"
    )
    p.add_argument("--maze", default="moderate-medium")
    p.add_argument("--maze-seed", type=COUNT, default=1001)
    p.add_argument("--start", type=FINITE, nargs=3, default=None, help="x y heading")
    p.add_argument("--goal", type=FINITE, nargs=2, default=None, help="x y")
    p.add_argument(
        "--target-scan-from-pose", type=FINITE, nargs=3, default=None, metavar=("X", "Y", "H"),
        help="observation target: render the simulator's scan at this pose and infer the goal "
        "with the inverse model q(z|x) (with --planner ground_truth the truth's own inverse, "
        "GroundTruthEnv.places); overrides --goal",
    )  # fmt: skip
    p.add_argument("--inverse-steps", type=POSITIVE, default=1000, help="ELBO steps of q(z|x)")
    p.add_argument("--inverse-sleep-steps", type=COUNT, default=3000, help="sleep steps of q(z|x)")
    p.add_argument("--planner", choices=["learned", "ground_truth"], default="learned")
    p.add_argument(
        "--map",
        choices=["known_poses", "slam"],
        default="known_poses",
        help="q(M) fitted at the true poses, or at an online SLAM run's pose means",
    )
    p.add_argument("--traversal-steps", type=POSITIVE, default=3000)
    p.add_argument("--fit-steps", type=POSITIVE, default=1500)
    p.add_argument(
        "--emission-steps",
        type=COUNT,
        default=0,
        help="fit the emission on the "
        "mapping traversal for this many steps (0: the shipped one, frozen)",
    )
    p.add_argument(
        "--n-world", type=_number(int, 20), default=20, help="world directions of a fitted emission"
    )
    p.add_argument("--max-expansions", type=POSITIVE, default=3000)
    p.add_argument("--noise", action="store_true", help="execute with actuation noise")
    p.add_argument("--out", type=Path, default=Path("navigate.png"))
    p.set_defaults(func=cmd_navigate)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="pyro-slam", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for add in (_add_simulate, _add_slam, _add_pretrain_and_demo, _add_navigate):
        add(sub)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (DatasetError, FileNotFoundError, ValueError, MissingExtra) as e:
        print(f"pyro-slam {args.command}: error: {e}", file=sys.stderr)
        return 2
    except (OSError, MemoryError) as e:  # the machine refused: disk, permissions, memory
        why = f"{type(e).__name__}: {one_line(e)}"
        print(f"pyro-slam {args.command}: error: {why}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
