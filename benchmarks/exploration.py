"""Exploration benchmark (paper Fig. 9): MI active SLAM vs PEMA vs a random walker.

For each Table II scale and seed, each agent runs ``steps`` steps (``--step-fraction`` of the
Table II budget); every ``horizon`` steps the mapper trains and infogain KL(q(M) || p(M)) and the
exploration ratio (visited tiles / Table II tiles) are recorded. PEMA is trained once with ARS on
moderate-medium training mazes (seeds 1000+, disjoint from the evaluation mazes 0, 1, ...).

Full run (paper budget, days of CPU)::

    python -m benchmarks.exploration --paper --scales all --seeds 2

Reduced run used in docs/exploration.md (plan horizon T = 50 as in the paper; ``--workers 2``
runs two agents at a time, one thread each)::

    python -m benchmarks.exploration --scales all --seeds 2 --step-fraction 0.2 \
        --max-steps 1800 --ars-iterations 20 --ars-directions 8 --ars-mazes 3 \
        --ars-steps 200 --workers 2 --out out/exploration

An interrupted run resumes: the trained PEMA policy (``OUT/pema.pt``) and every finished agent
run (``OUT/runs/<scale>_<agent>_s<seed>.json``) are reused when the settings match.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import torch
from tqdm.auto import tqdm

from pyro_slam.data import load_tensors
from pyro_slam.planning.exploration import ExploreConfig, run_agent, with_overrides
from pyro_slam.planning.pema import ARSConfig, PEMAPolicy, train_pema
from pyro_slam.slam.config import ConfigError
from simulators import SCALES, make_maze

AGENTS = ("mi", "pema", "random")
COLOURS = {"mi": "tab:blue", "pema": "tab:purple", "random": "tab:gray"}


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")  # the library's progress
    parser = _parser()
    args = parser.parse_args(argv)
    if args.merge:
        summary = merge(args.merge, Path(args.out))
        print(json.dumps(summary["final"], indent=1))
        return 0
    torch.set_num_threads(1)
    scales = list(SCALES) if args.scales == ["all"] else args.scales
    cfg, (ars_cfg, n_mazes, ars_steps) = _configs(parser, args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    per_job = ("out", "workers", "seeds", "first_seed", "scales")  # not in a run's settings
    settings = {k: str(v) for k, v in vars(args).items() if k not in per_job}
    policy = PEMAPolicy(step_length=cfg.motion.step_length, max_turn=cfg.motion.max_turn)
    ars_hist, t_ars = _trained_pema(policy, out / "pema.pt", settings, ars_cfg, n_mazes, ars_steps)
    jobs = _jobs(args, scales, cfg, policy)
    ars = {"ars_cfg": ars_cfg, "n_mazes": n_mazes, "ars_steps": ars_steps, "ars_hist": ars_hist}
    finished = partial(save, out=out, args=args, cfg=cfg, **ars, t_ars=t_ars, t0=t0)
    summary = run_agents(jobs, out, settings, args, finished)
    print(f"total {summary['seconds']:.0f} s (ARS {t_ars:.0f} s)", file=sys.stderr)
    print(json.dumps(summary["final"], indent=1))
    return 0


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m benchmarks.exploration", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--scales", nargs="+", default=["simple-small", "simple-medium"])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--first-seed", type=int, default=0, help="evaluation mazes first..+seeds-1")
    ap.add_argument(
        "--merge",
        nargs="+",
        metavar="JSON",
        help="combine the seeds of several runs' exploration.json into --out (no agents run)",
    )
    ap.add_argument("--step-fraction", type=float, default=0.2)
    ap.add_argument("--max-steps", type=int, default=None, help="cap on steps per run")
    ap.add_argument("--paper", action="store_true", help="paper budgets (Appendix D/E/F)")
    ap.add_argument("--ars-iterations", type=int, default=25)
    ap.add_argument("--ars-directions", type=int, default=8)
    ap.add_argument("--ars-mazes", type=int, default=3)
    ap.add_argument("--ars-steps", type=int, default=300)
    ap.add_argument("--horizon", type=int, default=50, help="plan horizon T (paper: 50)")
    ap.add_argument(
        "--execute-steps",
        type=int,
        default=None,
        help="steps of each plan executed before replanning (default: 25, --paper: all T)",
    )
    ap.add_argument("--workers", type=int, default=1, help="agents run in parallel (1 thread each)")
    ap.add_argument("--out", default="out/exploration")
    return ap


def _configs(parser, args) -> tuple[ExploreConfig, tuple[ARSConfig, int, int]]:
    """The agents' configuration, and PEMA's ARS configuration, training mazes and steps; a bad
    ``--horizon`` or ``--execute-steps`` is a usage error (``parser.error``, exit 2)."""
    cfg = ExploreConfig() if args.paper else ExploreConfig.smoke()
    plan = {"horizon": args.horizon}
    if args.execute_steps is not None:
        plan["execute_steps"] = args.execute_steps
    try:
        cfg = with_overrides(cfg, {"plan": plan})
    except ConfigError as e:
        parser.error(f"--horizon / --execute-steps: {e}")
    if args.paper:
        return cfg, (ARSConfig(), 10, 1000)
    ars_cfg = ARSConfig(args.ars_iterations, args.ars_directions, args.ars_directions // 2)
    return cfg, (ars_cfg, args.ars_mazes, args.ars_steps)


def _jobs(args, scales, cfg, policy) -> list[tuple]:
    """The agent runs ``(scale, agent, steps, cfg, seed, policy)``: every scale, agent and
    seed, each run ``--step-fraction`` of the scale's Table II budget (``--paper``: all of it),
    at most ``--max-steps``."""
    steps_of = {}
    for name in scales:
        steps = SCALES[name].steps if args.paper else int(SCALES[name].steps * args.step_fraction)
        steps_of[name] = min(steps, args.max_steps or steps)
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    return [(n, a, steps_of[n], cfg, s, policy) for n in scales for a in AGENTS for s in seeds]


def run_agents(jobs, out: Path, settings: dict, args, finished) -> dict:
    """Run each job (:func:`_timed_run`, in ``--workers`` processes), or load its curve from a
    finished run with the same ``settings`` (``OUT/runs``); each computed curve is saved there.
    ``finished(results)`` is called whenever a scale has every agent's runs, and its last value
    is returned."""
    (out / "runs").mkdir(exist_ok=True)
    cached = {}
    for job in jobs:  # finished runs of an interrupted benchmark with the same settings
        f = _run_file(out, job)
        if f.exists() and (saved := json.loads(f.read_text()))["settings"] == settings:
            cached[f] = saved["curve"]
    bar = tqdm(total=sum(job[2] for job in jobs), desc="agent steps")
    results, summary = {}, None
    with ProcessPoolExecutor(args.workers) if args.workers > 1 else _Serial() as pool:
        futures = [
            None if _run_file(out, j) in cached else pool.submit(_timed_run, *j) for j in jobs
        ]
        for job, fut in zip(jobs, futures):
            name, agent, steps, _, seed, _ = job
            f = _run_file(out, job)
            c = cached[f] if fut is None else fut.result()
            if fut is not None:
                tmp = f.with_suffix(".tmp")  # written whole, then renamed
                tmp.write_text(json.dumps({"settings": settings, "curve": c}))
                tmp.replace(f)
            bar.update(steps)
            results.setdefault(name, {}).setdefault(agent, []).append(c)
            msg = f"ratio {c['ratio'][-1]:.3f} infogain {c['infogain'][-1]:.1f}"
            bar.write(f"{name} {agent} seed {seed}: {msg} ({c['seconds']:.0f} s)")
            if all(len(results.get(name, {}).get(a, [])) == args.seeds for a in AGENTS):
                summary = finished(results)
    bar.close()
    return summary


def _run_file(out: Path, job) -> Path:
    name, agent, _, _, seed, _ = job
    return out / "runs" / f"{name}_{agent}_s{seed}.json"


def _trained_pema(policy, path: Path, settings, ars_cfg, n_mazes, ars_steps):
    """Train PEMA with ARS, or load it from ``path`` if trained there with the same settings.

    Returns ``(ars_history, seconds)``; ``policy.theta`` is set.
    """
    if path.exists():
        saved = load_tensors(path, "a PEMA policy file")
        if saved["settings"] == settings:
            policy.theta = saved["theta"]
            return saved["history"], saved["seconds"]
    t = time.time()
    hist = train_pema(policy, ars_cfg, n_mazes=n_mazes, steps=ars_steps, progress=True)
    t = time.time() - t
    tmp = path.with_suffix(".tmp")
    torch.save({"settings": settings, "theta": policy.theta, "history": hist, "seconds": t}, tmp)
    tmp.replace(path)
    return hist, t


def _timed_run(name, agent, steps, cfg, seed, policy) -> dict:
    torch.set_num_threads(1)
    t = time.time()
    c = run_agent(name, agent, steps, cfg, seed, policy)
    c["seconds"] = time.time() - t
    return c


class _Serial:
    """``ProcessPoolExecutor``'s interface, running each job here when its result is asked for."""

    class _Job:
        def __init__(self, fn, args):
            self.fn, self.args = fn, args

        def result(self):
            return self.fn(*self.args)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def submit(self, fn, *args):
        return self._Job(fn, args)


def save(results, out, args, cfg, ars_cfg, n_mazes, ars_steps, ars_hist, t_ars, t0) -> dict:
    """Write exploration.json and the figures for the scales finished so far."""
    summary = {
        "config": cfg.to_dict(),
        "ars": {
            **ars_cfg.to_dict(),
            "mazes": n_mazes,
            "steps": ars_steps,
            "history": ars_hist,
            "seconds": t_ars,
        },
        "step_fraction": 1.0 if args.paper else args.step_fraction,
        "workers": args.workers,
        "max_steps": args.max_steps,
        "seeds": args.seeds,
        "first_seed": args.first_seed,
        "steps": {n: len(r["mi"][0]["path"]) - 1 for n, r in results.items()},
        "seconds": time.time() - t0,
        "final": finals(results),
    }
    keys = ("steps", "ratio", "infogain", "mi", "collisions")
    curves = {
        n: {a: [{k: c[k] for k in keys} for c in r[a]] for a in AGENTS} for n, r in results.items()
    }
    (out / "exploration.json").write_text(json.dumps({**summary, "curves": curves}, indent=1))
    plot(results, out / "exploration_curves.png")
    plot_paths(results, out / "exploration_paths.png")
    return summary


def finals(results) -> dict:
    """Per scale and agent: mean and std over seeds of the final exploration ratio and infogain,
    mean blocked moves (and mean run time where recorded)."""
    out = {}
    for n, r in results.items():
        out[n] = {}
        for a in AGENTS:
            row = {}
            for key in ("ratio", "infogain"):
                v = [c[key][-1] for c in r[a]]
                row[f"{key}_mean"], row[f"{key}_std"] = float(np.mean(v)), float(np.std(v))
            row["collisions_mean"] = float(np.mean([c["collisions"] for c in r[a]]))
            if all("seconds" in c for c in r[a]):
                row["seconds_mean"] = float(np.mean([c["seconds"] for c in r[a]]))
            row["seeds"] = len(r[a])
            out[n][a] = row
    return out


def merge(paths, out: Path) -> dict:
    """Concatenate the per-seed curves of several ``exploration.json`` (same config, disjoint
    seeds) and write the combined summary and curves figure to ``out``."""
    runs = [json.loads(Path(p).read_text()) for p in paths]
    cfg0 = runs[0]["config"]
    for p, r in zip(paths, runs):
        if r["config"] != cfg0 or r["steps"] != runs[0]["steps"]:
            raise ValueError(f"{p}: config or steps differ from {paths[0]}; cannot merge")
    curves = {}
    for r in runs:
        for n, by_agent in r["curves"].items():
            for a, cs in by_agent.items():
                curves.setdefault(n, {}).setdefault(a, []).extend(cs)
    summary = {
        **{k: v for k, v in runs[0].items() if k not in ("curves", "final", "seconds")},
        "merged_from": [str(p) for p in paths],
        "seeds": sum(r["seeds"] for r in runs),
        "seconds": sum(r["seconds"] for r in runs),
        "final": finals(curves),
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "exploration.json").write_text(json.dumps({**summary, "curves": curves}, indent=1))
    plot(curves, out / "exploration_curves.png")
    return summary


def replot(json_path, png_path) -> None:
    """Redraw the curves figure from a saved ``exploration.json``."""
    plot(json.loads(Path(json_path).read_text())["curves"], png_path)


def plot(results, path):
    matplotlib.use("Agg")
    names = list(results)
    ncol = min(3, len(names))
    nrow = 2 * math.ceil(len(names) / ncol)  # per scale: infogain above exploration ratio
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 2.9 * nrow), squeeze=False)
    for ax in axes[:, :].flat:
        ax.set_visible(False)
    for j, name in enumerate(names):
        for i, key in enumerate(("infogain", "ratio")):
            ax = axes[2 * (j // ncol) + i, j % ncol]
            ax.set_visible(True)
            for agent in AGENTS:
                runs = results[name][agent]
                x = np.asarray(runs[0]["steps"])
                y = np.asarray([np.interp(x, r["steps"], r[key]) for r in runs])
                m, s = y.mean(0), y.std(0)
                ax.plot(x, m, color=COLOURS[agent], label=agent)
                ax.fill_between(x, m - s, m + s, color=COLOURS[agent], alpha=0.2)
            ax.set_title(f"{name}: {'infogain (nats)' if key == 'infogain' else 'exploration'}")
            ax.set_xlabel("steps")
            if i == 0 and j == 0:
                ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_paths(results, path):
    matplotlib.use("Agg")
    names = list(results)
    fig, axes = plt.subplots(len(names), 3, figsize=(9, 3 * len(names)), squeeze=False)
    for i, name in enumerate(names):
        maze = make_maze(name, 0)
        for j, agent in enumerate(AGENTS):
            ax = axes[i, j]
            for x0, y0, x1, y1 in maze.walls:
                ax.plot([x0, x1], [y0, y1], "k-", lw=1)
            p = np.asarray(results[name][agent][0]["path"])
            ax.plot(p[:, 0], p[:, 1], color=COLOURS[agent], lw=0.8)
            ax.set_title(f"{name} {agent} (seed 0)")
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
