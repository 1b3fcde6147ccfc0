"""Trace one online SLAM run: position and heading error of SLAM and path integration, and the
particle cloud's std, every ``--every`` steps (the diagnosis in docs/benchmarks.md).

    python benchmarks/slam_trace.py --seed 11 --steps 1300
    python benchmarks/slam_trace.py --seed 11 --steps 1300 --set revisit_gap=200 weighting=tempered
    python benchmarks/slam_trace.py --oracle-map --set svi_steps=4   # map trained at true poses

``--oracle-map`` is a diagnostic: the particle cache the map is trained from holds the true
poses (+ 1e-3 noise) instead of the filter's particles, so the map is learned online at the
right places while the filter still localises against it -- it separates "the filter cannot
use a partially learned map" from "pose errors feed back into the map".

Uses the shipped pretrained emission (frozen) and the engineered kinematic transition on a
``moderate-medium`` traversal ``simulate_traversal(..., seed=SEED)``. Prints one JSON line per
row and a final JSON summary.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--steps", type=int, default=1300)
    ap.add_argument("--every", type=int, default=50)
    ap.add_argument("--oracle-map", action="store_true", help="train the map at true poses")
    ap.add_argument("--set", nargs="*", default=[], help="SLAMConfig overrides key=json-value")
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    from pyro_slam.cli import PRETRAINED, load_emission
    from pyro_slam.geometry import wrap_angle
    from pyro_slam.slam import SLAM, SLAMConfig, path_integration
    from simulators import simulate_traversal

    over = {}
    for kv in args.set:
        k, _, v = kv.partition("=")
        try:
            over[k] = json.loads(v)
        except json.JSONDecodeError:
            over[k] = v
    tr = simulate_traversal("moderate-medium", steps=args.steps, seed=args.seed)
    cfg = SLAMConfig(**{"learn_emission": False, **over, "seed": args.seed})
    em = load_emission(PRETRAINED / "emission_lidar20.pt", tr, cfg)
    slam = SLAM(tr, cfg, emission=em)
    if args.oracle_map:
        true = torch.as_tensor(tr.poses, dtype=slam.cache.z.dtype)
        gen = torch.Generator().manual_seed(args.seed)

        def store_true_poses(t, p, generator=None):  # [C] steps; the particles are ignored
            N = slam.cache.num_particles
            noise = 1e-3 * torch.randn(len(t), N, 3, generator=gen, dtype=true.dtype)
            slam.cache.z[t] = true[t].unsqueeze(-2) + noise
            slam.cache.filled[t] = True

        slam.cache.store = store_true_poses
    res = slam.run("online", progress=True)
    pi = path_integration(tr, slam.model.transition)
    true = tr.poses
    pos = np.linalg.norm(res["mean"][:, :2] - true[:, :2], axis=1)
    pos_pi = np.linalg.norm(pi[:, :2] - true[:, :2], axis=1)
    head = np.abs(np.asarray(wrap_angle(torch.as_tensor(res["mean"][:, 2] - true[:, 2]))))
    head_pi = np.abs(np.asarray(wrap_angle(torch.as_tensor(pi[:, 2] - true[:, 2]))))
    for t in list(range(0, args.steps, args.every)) + [args.steps - 1]:
        row = dict(
            t=t,
            err=round(float(pos[t]), 3),
            err_pi=round(float(pos_pi[t]), 3),
            heading_err=round(float(head[t]), 3),
            heading_err_pi=round(float(head_pi[t]), 3),
            std=[round(float(s), 3) for s in res["std"][t]],
        )
        print(json.dumps(row))
    print(
        json.dumps(
            dict(
                config=over,
                oracle_map=args.oracle_map,
                seed=args.seed,
                final_err=float(pos[-1]),
                final_err_pi=float(pos_pi[-1]),
                max_heading_err=float(head.max()),
                max_heading_err_pi=float(head_pi.max()),
                median_heading_std=float(np.median(res["std"][:, 2])),
            )
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
