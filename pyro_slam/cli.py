"""The ``pyro-slam`` command line.

    pyro-slam simulate --maze moderate-medium --steps 3000 --seed 1 --out traversal.npz
    pyro-slam pretrain --out pretrained/            # emission (+ learned transition), held-out maze
    pyro-slam slam traversal.npz --mode online --out run/     # also .clf / .log / ROS bags
    pyro-slam slam traversal.npz --out run/ --resume          # continue from run/checkpoint.pt
    pyro-slam demo --out out/                       # simulate + SLAM + plots + metrics.json

Every sub-command validates its inputs before computing and exits with status 2 and a one-line
message naming the file and problem on bad input.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import fields
from pathlib import Path

import numpy as np
import torch

from .data import DatasetError, Traversal, atomic_write

PRETRAINED = Path(__file__).parent / "pretrained"
EMISSION_FILE = "emission_lidar20.pt"
TRANSITION_FILE = "transition_moderate_medium.pt"
# SLAMConfig.transition_scale for the shipped transition: SLAM filters with its sigma_T scaled by
# these factors (x, y, heading). A stiffer heading keeps the map's frontier from tilting it, more
# position noise lets revisits pull the position back (docs/benchmarks.md, session 10)
TRANSITION_SCALE = (3.0, 3.0, 0.2)
# ... and where the map is established (the cloud's trust in it near 1) the heading gets the
# transition's calibrated noise back, with one trust for the whole cloud ("shared" weights): the
# stiff heading is needed only at the frontier, where a young chart tilts it (session 13)
TRANSITION_SCALE_TRUSTED = (3.0, 3.0, 1.0)
SHIPPED_FILTER = dict(
    transition_scale=TRANSITION_SCALE,
    transition_scale_trusted=TRANSITION_SCALE_TRUSTED,
    weighting="shared",
    # offline SLAM: the paper's cache-started chunk filter for the final poses, no
    # whole-traversal passes (0.058 against 0.063 on the 24 LiDAR runs; session 16)
    offline_estimate="cache",
)


# ----------------------------------------------------------------------------------- helpers
def _is_real_log(traversal: Traversal) -> bool:
    """A metric log from a reader (no walls, robot-frame odometry), not a simulated maze."""
    return not traversal.walls.shape[0] and (
        traversal.metadata.get("control_model") == "odometry_delta"
    )


def _config(args, traversal: Traversal | None = None):
    """SLAMConfig from ``--config`` overrides; real logs start from :func:`real_log_config`
    (beam stride, 0.5 m map, range clip, transition noise from ``--odometry-noise``)."""
    from .slam import SLAMConfig, real_log_config

    over = {}
    if args.config:
        src = Path(args.config)
        text = src.read_text() if src.is_file() else args.config
        try:
            over = json.loads(text)
        except json.JSONDecodeError as e:
            raise DatasetError(f"--config: not a JSON object or file: {e}") from e
        names = {f.name for f in fields(SLAMConfig)}
        bad = sorted(set(over) - names)
        if bad:
            raise DatasetError(f"--config: unknown SLAMConfig fields {bad}; known: {sorted(names)}")
    over["seed"] = args.seed
    noise = getattr(args, "odometry_noise", None)
    if traversal is not None and _is_real_log(traversal):
        return real_log_config(traversal, odometry_noise=0.1 if noise is None else noise, **over)
    if noise is not None and traversal is not None and "transition_sigma" not in over:
        from .slam import odometry_sigma

        over["transition_sigma"] = odometry_sigma(traversal.controls, noise, noise)
    return SLAMConfig(**over)


def load_emission(path, traversal: Traversal, config):
    """A pretrained emission network from ``path`` (``None`` -> learn from scratch)."""
    from .networks import EmissionMLP

    if path is None:
        return None
    blob = torch.load(path, weights_only=True)
    meta = blob.get("meta", {})
    n_world = meta.get("n_world", 20)
    wanted = max(traversal.num_beams, config.n_world)
    if n_world != wanted or meta.get("map_dim", 10) != config.map_dim:
        raise DatasetError(
            f"{path}: emission pretrained for {n_world} world directions / map_dim "
            f"{meta.get('map_dim')}, but the traversal has {traversal.num_beams} beams, "
            f"n_world {config.n_world}, map_dim {config.map_dim}"
        )
    em = EmissionMLP(
        config.map_dim, n_world, config.emission_hidden, config.emission_layers,
        scale=meta.get("scale", traversal.max_range),
    )  # fmt: skip
    em.load_state_dict(blob["state_dict"])
    return em


def load_transition(path):
    from .transitions import LearnedTransition

    blob = torch.load(path, weights_only=True)
    return LearnedTransition.from_state(blob)


def shipped_slam(traversal: Traversal, transition: str = "learned", **overrides):
    """A :class:`~pyro_slam.slam.SLAM` with the shipped (frozen) LiDAR emission and the shipped
    learned transition filtered as :data:`SHIPPED_FILTER` says (``transition="kinematic"``: the
    simulator's kinematics, unscaled, and the :class:`~pyro_slam.slam.SLAMConfig` defaults), as
    the LiDAR benchmarks run it. ``overrides`` are
    :class:`~pyro_slam.slam.SLAMConfig` fields and win over these defaults."""
    from .slam import SLAM, SLAMConfig

    if transition not in ("learned", "kinematic"):
        raise ValueError(f"transition must be 'learned' or 'kinematic', got {transition!r}")
    defaults = {"learn_emission": False}
    tran = None
    if transition == "learned":
        defaults.update(SHIPPED_FILTER)
        tran = load_transition(PRETRAINED / TRANSITION_FILE)
    cfg = SLAMConfig(**{**defaults, **overrides})
    emission = None  # raycast: a RayEmission, which has no weights to load
    if cfg.lidar_emission == "mlp":
        emission = load_emission(PRETRAINED / EMISSION_FILE, traversal, cfg)
    return SLAM(traversal, cfg, transition=tran, emission=emission)


def _default_emission(traversal: Traversal):
    """The shipped emission fits the simulator's 20-beam unit-maze LiDAR only."""
    f = PRETRAINED / EMISSION_FILE
    if f.is_file() and traversal.num_beams == 20 and abs(traversal.max_range - 0.53) < 1e-9:
        return f
    return None


def run_slam(
    traversal: Traversal,
    out: Path,
    mode: str,
    config,
    emission=None,
    transition=None,
    resume: bool = False,
    progress: bool = True,
) -> dict:
    """SLAM on ``traversal`` writing plots, trajectories, metrics and a checkpoint into ``out``."""
    from . import metrics, plotting
    from .slam import SLAM, path_integration

    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "checkpoint.pt"
    slam = SLAM(traversal, config, transition=transition, emission=emission, checkpoint=ckpt)
    if resume:
        if not ckpt.is_file():
            raise DatasetError(f"{ckpt}: no checkpoint to resume from")
        slam.resume(ckpt)
    t0 = time.perf_counter()
    res = slam.run(mode, progress=progress)
    wall = time.perf_counter() - t0
    res["mode"] = mode
    res["path_integration"] = path_integration(traversal, slam.model.transition)
    metrics.write_trajectory_tum(out / "trajectory_slam.tum", res["mean"], traversal.timestamps)
    metrics.write_trajectory_tum(
        out / "trajectory_path_integration.tum", res["path_integration"], traversal.timestamps
    )
    np.savez_compressed(
        out / "posterior.npz",
        pose_mean=res["mean"],
        pose_std=res["std"],
        map_loc=res["map_loc"],
        map_scale=res["map_scale"],
        path_integration=res["path_integration"],
    )
    report = {
        "mode": mode,
        "steps": traversal.num_steps,
        "wall_time_s": wall,
        "seconds_per_step": wall / traversal.num_steps,
        "config": config.to_dict(),
        "metadata": {k: traversal.metadata.get(k) for k in ("source", "seed", "maze")},
    }
    if traversal.poses is not None:
        report["slam"] = metrics.summary(res["mean"], traversal.poses)
        report["path_integration"] = metrics.summary(res["path_integration"], traversal.poses)
        plotting.plot_errors(traversal, res, out / "error.png")
    plotting.plot_slam(traversal, res, slam.model.grid, out / "slam.png")
    if not traversal.walls.shape[0]:  # real log: map image from the reprojected scans
        plotting.plot_scan_map(
            slam.tr, res["mean"], out / "map.png", slam.model.grid, res["map_loc"],
            others={"path integration": res["path_integration"]},
        )  # fmt: skip
        report["scan_consistency"] = {
            "slam": metrics.scan_consistency(slam.tr, res["mean"]),
            "path_integration": metrics.scan_consistency(slam.tr, res["path_integration"]),
        }
    text = json.dumps(report, indent=2, default=float)
    atomic_write(out / "metrics.json", lambda f: f.write(text.encode()))
    return report


def _print_report(report: dict, out: Path) -> None:
    line = f"slam ({report['mode']}): T={report['steps']} {report['wall_time_s']:.0f}s"
    if "slam" in report:
        s, p = report["slam"], report["path_integration"]
        line += (
            f" | final error SLAM {s['final_error']:.4f} vs path integration "
            f"{p['final_error']:.4f} | ATE rmse {s['ate']['rmse']:.4f} vs {p['ate']['rmse']:.4f}"
        )
    if "scan_consistency" in report:
        c = report["scan_consistency"]
        line += (
            f" | scan consistency SLAM {c['slam']['mean']:.3f} vs path integration "
            f"{c['path_integration']['mean']:.3f}"
        )
    print(line + f" -> {out}/ (metrics.json, slam.png, map.png / error.png, checkpoint.pt)")


# ----------------------------------------------------------------------------------- commands
def cmd_slam(args) -> int:
    from .io import read_any

    torch.manual_seed(args.seed)
    tr = read_any(args.traversal)
    if args.steps:
        tr = tr.slice(0, min(args.steps, tr.num_steps))
    config = _config(args, tr)
    em_path = args.emission if args.emission else _default_emission(tr)
    if args.emission == "none":
        em_path = None
    if config.lidar_emission == "raycast":  # a RayEmission has no network to load
        if args.emission not in (None, "none"):
            raise DatasetError(
                "--emission loads an emission MLP; lidar_emission 'raycast' has none"
            )
        em_path = None
    if em_path is not None and "learn_emission" not in (args.config or ""):
        config.learn_emission = False  # a pretrained emission is kept frozen by default
    emission = load_emission(em_path, tr, config)
    transition = load_transition(args.transition) if args.transition else None
    report = run_slam(tr, args.out, args.mode, config, emission, transition, args.resume)
    _print_report(report, args.out)
    return 0


def cmd_pretrain(args) -> int:
    from simulators import simulate_traversal

    from .slam import SLAMConfig, pretrain_emission
    from .transitions import pretrain_transition

    args.out.mkdir(parents=True, exist_ok=True)
    tr = simulate_traversal(args.maze, steps=args.steps, seed=args.seed)
    cfg = SLAMConfig()
    em, stats = pretrain_emission([tr], cfg, steps=args.emission_steps, seed=args.seed)
    blob = {
        "state_dict": em.state_dict(),
        "meta": {"n_world": em.n_world, "map_dim": cfg.map_dim, "scale": tr.max_range,
                 "maze": args.maze, "seed": args.seed, **stats},
    }  # fmt: skip
    torch.save(blob, args.out / EMISSION_FILE)
    tran, tstats = pretrain_transition([tr], epochs=args.transition_epochs, seed=args.seed)
    torch.save(tran.to_state(), args.out / TRANSITION_FILE)
    print(json.dumps({"emission": stats, "transition": tstats}, default=float))
    return 0


def cmd_demo(args) -> int:
    """Simulate the default maze, run online SLAM, write plots and metrics into ``args.out``."""
    from simulators import simulate_traversal
    from simulators.plotting import plot_traversal

    from .slam import SLAMConfig

    torch.manual_seed(args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tr = simulate_traversal(args.maze, steps=args.steps, seed=args.seed)
    tr.save(out / "traversal.npz")
    plot_traversal(tr, out / "traversal.png")
    cfg = SLAMConfig(seed=args.seed, learn_emission=False, **SHIPPED_FILTER)
    emission = load_emission(_default_emission(tr), tr, cfg)
    transition = load_transition(PRETRAINED / TRANSITION_FILE)
    report = run_slam(tr, out, args.mode, cfg, emission, transition, resume=args.resume)
    _print_report(report, out)
    return 0


def build_parser() -> argparse.ArgumentParser:
    from simulators.cli import add_simulate_parser

    p = argparse.ArgumentParser(prog="pyro-slam", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    add_simulate_parser(sub)

    s = sub.add_parser("slam", help="run DVBF-LM SLAM on a traversal (.npz, CARMEN, ROS bag)")
    s.add_argument("traversal", type=Path)
    s.add_argument("--mode", choices=["online", "offline"], default="online")
    s.add_argument("--out", type=Path, default=Path("run"))
    s.add_argument("--steps", type=int, default=0, help="use only the first N steps")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--config", help="JSON object (or file) of SLAMConfig overrides")
    s.add_argument(
        "--emission",
        help="pretrained emission .pt ('none': learn from scratch; default: the shipped one "
        "when the sensor matches the simulator's)",
    )
    s.add_argument(
        "--transition",
        help="pretrained LearnedTransition .pt (default: kinematic); the demo and benchmarks "
        f"filter the shipped one with {SHIPPED_FILTER} (--config)",
    )
    s.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    s.add_argument(
        "--odometry-noise",
        type=float,
        help="transition std as this fraction of the RMS odometry step (relative-odometry "
        "model; default 0.1 for real logs, the config's transition_sigma otherwise)",
    )
    s.set_defaults(func=cmd_slam)

    t = sub.add_parser("pretrain", help="pretrain emission + transition on a held-out maze")
    t.add_argument("--out", type=Path, default=PRETRAINED)
    t.add_argument("--maze", default="moderate-medium")
    t.add_argument("--seed", type=int, default=100)
    t.add_argument("--steps", type=int, default=6000)
    t.add_argument("--emission-steps", type=int, default=3000)
    t.add_argument("--transition-epochs", type=int, default=30)
    t.set_defaults(func=cmd_pretrain)

    d = sub.add_parser("demo", help="simulate the default maze and run SLAM (plots + metrics)")
    d.add_argument("--out", type=Path, default=Path("out"))
    d.add_argument("--maze", default="moderate-medium")
    d.add_argument("--steps", type=int, default=3000)
    d.add_argument("--seed", type=int, default=1)
    d.add_argument("--mode", choices=["online", "offline"], default="online")
    d.add_argument("--resume", action="store_true")
    d.set_defaults(func=cmd_demo)

    from .planning import add_navigate_parser

    add_navigate_parser(sub)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (DatasetError, FileNotFoundError, ValueError) as e:
        print(f"pyro-slam {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
