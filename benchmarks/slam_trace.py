"""Trace one online SLAM run: position and heading error of SLAM and path integration, and the
particle cloud's std and its trust in the map (the weights' mean of
``ParticleFilter.trust``, 0.01: flat weights, 1: the map's full weight), every ``--every`` steps
(the diagnosis in docs/benchmarks.md).

    python benchmarks/slam_trace.py --seed 11 --steps 1300
    python benchmarks/slam_trace.py --seed 11 --steps 1300 --set revisit_gap=200 weighting=tempered
    python benchmarks/slam_trace.py --map-poses true --set svi_steps=4   # map trained at true poses
    python benchmarks/slam_trace.py --seed 12 --steps 220 --map-poses pi --frontier
    python benchmarks/slam_trace.py --steps 200 --every 20 --set lidar_emission=raycast \
        map_resolution=0.015873015873015872                 # ray-cast emission (no MLP loaded)
    python benchmarks/slam_trace.py --maze-seed 993 --seed 1 --steps 80 --every 2 --set \
        lidar_emission=raycast map_resolution=0.015873015873015872 ray_insert=2.0 \
        ray_insert_scale=0.3 beam_trust=true outlier_prob=0.1 train_outlier_prob=0.0
        # a slam_accuracy.py run (maze 993, traversal 1) as the benchmark filters it

Diagnostics (they change what the map is trained from, never the filter):

- ``--map-poses true`` (alias ``--oracle-map``): the particle cache the map is trained from holds
  the true poses (+ 1e-3 noise) instead of the filter's particles, so the map is learned online
  at the right places while the filter still localises against it -- it separates "the filter
  cannot use a partially learned map" from "pose errors feed back into the map".
- ``--map-poses pi``: the same with the path-integration poses; the filter should then follow
  path integration (``dev_pi`` columns), and how far it strays is its bias at the map frontier.
- ``--frozen-cache``: the ELBO's chunk filter does not overwrite the cache (the map is trained
  at the online filter's particles only).
- ``--frontier``: after each filter step, score the newest observation against the current map
  belief at the TRUE pose: RMS residual, the heading offset (within +-0.3 rad) that predicts it
  best, and the chart's trust (1 - relative variance); averaged over each ``--every`` window.

Uses the shipped pretrained emission (frozen; or ``--emission PATH``) and the engineered
kinematic transition on a ``moderate-medium`` traversal ``simulate_traversal(..., seed=SEED)``.
With ``--maze-seed N`` it traces a run of ``slam_accuracy.py`` instead: maze ``N``, traversal
``SEED`` with that run's own noise draw, and the benchmark's filter (``shipped_slam``: the
learned transition, scaled as ``SHIPPED_FILTER`` says; ``--set`` overrides it).
Prints one JSON line per row and a final JSON summary.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def parse_overrides(pairs):
    over = {}
    for kv in pairs:
        k, _, v = kv.partition("=")
        try:
            over[k] = json.loads(v)
        except json.JSONDecodeError:
            over[k] = v
    return over


def freeze_cache(slam):
    """The ELBO's chunk filter reads the cache but no longer writes it."""

    class ReadOnly:
        def __init__(self, cache):
            self._cache = cache

        def store(self, *args, **kwargs):
            pass

        def __getattr__(self, name):
            return getattr(self._cache, name)

    slam.elbo.cache = ReadOnly(slam.cache)


def record_frontier(slam, true_poses, rows):
    """After each filter step, score the newest observation at the true pose (``--frontier``)."""
    import torch

    true = torch.as_tensor(true_poses, dtype=slam.obs.dtype)
    offsets = torch.linspace(-0.3, 0.3, 61, dtype=true.dtype)
    filter_step = slam._filter_step

    def step(t, M):
        filter_step(t, M)
        with torch.no_grad():
            belief, g, z = slam.map_mean(t), slam.model.grid, true[t]
            var = g.attend(belief.scale**2, z[:2], power=2).mean(-1)
            var = var / g.attend(torch.ones_like(belief.scale[..., :1]), z[:2], power=2)[..., 0]
            zs = z.repeat(len(offsets), 1)
            zs[:, 2] += offsets
            mse = (slam.model.emission_mean(belief.loc, zs) - slam.obs[t]).pow(2).mean(-1)
            rows.append((float(mse[len(offsets) // 2].sqrt()), float(offsets[mse.argmin()]),
                         float(1 - var)))  # fmt: skip

    slam._filter_step = step


def record_trust(slam, rows):
    """After each filter step, the cloud's trust in the map belief it was weighed with."""
    import torch

    filter_step = slam._filter_step

    def step(t, M):
        filter_step(t, M)
        with torch.no_grad():
            rows.append(float(slam.pf.cloud_trust(slam.particles, M)))

    slam._filter_step = step


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--steps", type=int, default=1300)
    ap.add_argument("--every", type=int, default=50)
    ap.add_argument("--map-poses", choices=["filter", "true", "pi"], default="filter")
    ap.add_argument("--oracle-map", action="store_true", help="same as --map-poses true")
    ap.add_argument("--frozen-cache", action="store_true", help="chunks do not refresh the cache")
    ap.add_argument("--frontier", action="store_true", help="score the newest step at the truth")
    ap.add_argument("--emission", type=Path, help="pretrained emission .pt (default: shipped)")
    ap.add_argument("--set", nargs="*", default=[], help="SLAMConfig overrides key=json-value")
    ap.add_argument("--maze-seed", type=int, help="trace slam_accuracy.py's run on this maze")
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    from pyro_slam.cli import PRETRAINED, load_emission
    from pyro_slam.geometry import wrap_angle
    from pyro_slam.slam import SLAM, SLAMConfig, path_integration
    from simulators import simulate_traversal

    map_poses = "true" if args.oracle_map else args.map_poses
    over = parse_overrides(args.set)
    if args.maze_seed is not None:  # the benchmark's run: its traversal and shipped filter
        from slam_accuracy import _traversal

        from pyro_slam.cli import shipped_slam

        tr = _traversal(args.maze_seed, args.seed, args.steps, per_maze_noise=True)
        slam = shipped_slam(tr, "learned", **{**over, "seed": args.seed})
    else:
        tr = simulate_traversal("moderate-medium", steps=args.steps, seed=args.seed)
        cfg = SLAMConfig(**{"learn_emission": False, **over, "seed": args.seed})
        em = None  # the ray-cast emission has no pretrained network
        if cfg.observation == "lidar" and cfg.lidar_emission != "raycast":
            em = load_emission(args.emission or PRETRAINED / "emission_lidar20.pt", tr, cfg)
        slam = SLAM(tr, cfg, emission=em)
    pi = path_integration(tr, slam.model.transition)  # [T, 3]
    if map_poses != "filter":
        slam.pin_cache(tr.poses if map_poses == "true" else pi, seed=args.seed)
    if args.frozen_cache:
        freeze_cache(slam)
    frontier, trust = [], []
    record_trust(slam, trust)
    if args.frontier:
        record_frontier(slam, tr.poses, frontier)
    res = slam.run("online", progress=True)
    true = tr.poses

    def heading(a, b):
        return np.abs(np.asarray(wrap_angle(torch.as_tensor(a[:, 2] - b[:, 2]))))

    pos = np.linalg.norm(res["mean"][:, :2] - true[:, :2], axis=1)
    pos_pi = np.linalg.norm(pi[:, :2] - true[:, :2], axis=1)
    dev_pi = np.linalg.norm(res["mean"][:, :2] - pi[:, :2], axis=1)
    head, head_pi = heading(res["mean"], true), heading(pi, true)
    for t in list(range(0, args.steps, args.every)) + [args.steps - 1]:
        row = dict(
            t=t,
            err=round(float(pos[t]), 3),
            err_pi=round(float(pos_pi[t]), 3),
            heading_err=round(float(head[t]), 3),
            heading_err_pi=round(float(head_pi[t]), 3),
            dev_pi=round(float(dev_pi[t]), 3),
            std=[round(float(s), 3) for s in res["std"][t]],
            trust=round(float(np.mean(trust[max(t - args.every + 1, 0) : t + 1])), 3),
        )
        if frontier:
            win = np.asarray(frontier[max(t - args.every + 1, 0) : t + 1])
            row.update(frontier_rms=round(float(win[:, 0].mean()), 3),
                       frontier_best_offset=round(float(win[:, 1].mean()), 3),
                       frontier_trust=round(float(win[:, 2].mean()), 2))  # fmt: skip
        print(json.dumps(row))
    summary = dict(
        config=over,
        map_poses=map_poses,
        maze_seed=args.maze_seed,
        frozen_cache=args.frozen_cache,
        oracle_map=map_poses == "true",
        seed=args.seed,
        final_err=float(pos[-1]),
        final_err_pi=float(pos_pi[-1]),
        mean_err=float(pos.mean()),
        mean_err_pi=float(pos_pi.mean()),
        max_heading_err=float(head.max()),
        max_heading_err_pi=float(head_pi.max()),
        median_heading_std=float(np.median(res["std"][:, 2])),
    )
    if frontier:
        f = np.asarray(frontier)
        summary.update(frontier_rms=float(f[:, 0].mean()),
                       frontier_best_offset=float(f[:, 1].mean()))  # fmt: skip
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
