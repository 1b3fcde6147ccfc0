"""``pyro-slam simulate``: write a simulated traversal (``.npz``) and a plot of it."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from simulators.maze import SCALES
from simulators.traversal import integrate_controls, simulate_traversal


def add_simulate_parser(subparsers) -> argparse.ArgumentParser:
    """Register the ``simulate`` sub-command on an ``argparse`` subparsers object."""
    p = subparsers.add_parser("simulate", help="simulate a maze traversal and save it as .npz")
    p.add_argument("--maze", default="moderate-medium", choices=sorted(SCALES), help="maze scale")
    p.add_argument("--steps", type=int, default=3000, help="number of time steps T")
    p.add_argument("--seed", type=int, default=1, help="seeds maze, noise and driver")
    p.add_argument("--out", type=Path, default=Path("traversal.npz"), help="output .npz")
    p.add_argument("--images", action="store_true", help="also render 32x24 camera frames")
    p.add_argument("--distractors", type=int, default=0, help="boxes not in the floor map")
    p.add_argument(
        "--plot", type=Path, default=None, help="output PNG (default: next to --out, .png)"
    )
    p.add_argument("--no-plot", action="store_true", help="do not write a PNG")
    p.set_defaults(func=run_simulate)
    return p


def run_simulate(args: argparse.Namespace) -> int:
    """Run the ``simulate`` sub-command; prints a one-line summary; returns an exit code."""
    from simulators.plotting import plot_traversal

    tr = simulate_traversal(
        args.maze, args.steps, args.seed, images=args.images, distractors=args.distractors
    )
    out = tr.save(args.out)
    plot = None
    if not getattr(args, "no_plot", False):
        plot = plot_traversal(tr, args.plot or Path(args.out).with_suffix(".png"))
    dead = integrate_controls(tr.poses[0], tr.controls)
    drift = float(np.linalg.norm(dead[-1, :2] - tr.poses[-1, :2]))
    print(
        f"simulate: {args.maze} seed={args.seed} T={tr.num_steps} beams={tr.num_beams} "
        f"coverage={tr.metadata['coverage']:.2f} collisions={tr.metadata['collisions']} "
        f"dead-reckoning drift={drift:.3f} images={'yes' if tr.images is not None else 'no'} "
        f"-> {out}" + (f" (plot {plot})" if plot else "")
    )
    return 0


def main(argv=None) -> int:
    """Stand-alone entry point: ``python -m simulators.cli simulate ...``."""
    parser = argparse.ArgumentParser(prog="simulators")
    add_simulate_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    raise SystemExit(main())
