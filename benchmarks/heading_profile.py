"""How sharply does a ray-cast map pin the heading? The LiDAR log-likelihood (Gaussian, std
``--sigma``, summed over beams and over steps ``[a, b)`` of a window) at the TRUE poses with
the heading offset by ``-0.12 .. 0.12`` rad, under three maps on the ``slam_accuracy.py``
traversal of one maze (per-maze noise, driver seed ``--traversal``):

- ``first scan``: only the scan at the known start pose, written as an occupancy grid (walls at
  its hits, joined into polylines; free space along its beams), as ``SLAMConfig.ray_anchor``
  writes it;
- ``true walls``: the maze's walls (``RayEmission.wall_map``), an oracle;
- ``after SLAM``: q(M)'s mean after online SLAM over the ``--steps`` steps with
  ``--config`` (the shipped learned transition and filter, as the benchmark runs it).

Prints, per map and window, the offset of the best heading and how many nats the true heading
is below it (0: the truth is the optimum), as JSON lines (session 27 in docs/benchmarks.md):

    python benchmarks/heading_profile.py --maze 993 --steps 8 --windows 0:4,4:8

With ``--young N`` it instead asks whether the young map itself is what misleads the filter
(session 28): on each of ``--mazes``, for ``s = 1 .. N``, the map is the ``ray_insert`` scans
of steps ``0 .. s-1`` written at the TRUE poses (no SVI), and the filter's own log-weights
(``ParticleFilter._weigh``: trust, outlier mixture and weighting of ``--config``) are taken at
the true position of step ``s`` over heading offsets ``-0.15 .. 0.15``; the same under the
maze's true walls (scale 0.05). Prints one JSON line per step window ``--young-windows``: the
mean ``|best offset|``, its mean (a shared bias), and the std of the heading under the
normalised weights (how sharply one scan pins the heading):

    python benchmarks/heading_profile.py --young 40 --config '{"ray_insert": 2.0, ...}'
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

RAYCAST = {"lidar_emission": "raycast", "map_resolution": 1 / 63}


def profile(slam, M, poses, windows, offsets, sigma):
    """``[(window, best offset, loglik(truth) - max)]`` under map mean ``M [w, h, 1]``."""
    em, g = slam.model.emission, slam.model.grid
    out = []
    for a, b in windows:
        ll = torch.zeros(len(offsets), dtype=M.dtype)
        for t in range(a, b):
            z = poses[t].expand(len(offsets), 3).clone()  # [O, 3]
            z[:, 2] += offsets
            ll += (-0.5 * ((em.read(g, M, z) - slam.obs[t]) / sigma) ** 2).sum(-1)
        k0 = int(torch.argmin(offsets.abs()))
        out.append(((a, b), float(offsets[int(ll.argmax())]), float(ll[k0] - ll.max())))
    return out


def young_profile(args, config: dict) -> list[dict]:
    """``--young``: the filter's heading weights on maps written at the true poses."""
    from slam_accuracy import BENCH_CONFIG, _traversal

    from pyro_slam.cli import shipped_slam
    from pyro_slam.filtering import MapBelief, Particles
    from pyro_slam.networks import RayEmission
    from simulators.maze import make_maze

    if config.get("ray_insert") is None:
        raise SystemExit("--young writes the map with ray_insert: set it in --config")
    torch.set_num_threads(1)  # small tensors: more threads only contend (10x slower on 2 cores)
    N, mazes = args.young, [int(m) for m in args.mazes.split(",")]
    windows = [tuple(int(v) for v in w.split(":")) for w in args.young_windows.split(",")]
    if not all(1 <= a < b <= N + 1 for a, b in windows):
        raise SystemExit(
            f"--young-windows must lie within steps 1..{N}, got {args.young_windows!r}"
        )
    rows = {m: np.zeros((len(mazes), N, 2)) for m in ("young map", "true walls")}  # best, std
    for r, maze in enumerate(mazes):
        tr = _traversal(maze, args.traversal, N + 1, True)
        slam = shipped_slam(tr, "learned", **{**BENCH_CONFIG, **config, "seed": args.traversal})
        dt = slam.obs.dtype
        poses = torch.as_tensor(tr.poses, dtype=dt)  # [N + 1, 3]
        offs = torch.linspace(-0.15, 0.15, 61, dtype=dt)  # [O]
        walls = RayEmission.wall_map(
            slam.model.grid, np.asarray(make_maze("moderate-medium", maze).walls)
        )
        walls = MapBelief(walls.to(dt), torch.full_like(walls.to(dt), 0.05))
        logw = torch.full((len(offs),), -math.log(len(offs)), dtype=dt)  # [O]
        for s in range(1, N + 1):
            slam.particles = Particles(poses[s - 1 : s], torch.zeros(1, dtype=dt))
            slam._insert_scan(s - 1)  # written at the true pose of step s - 1
            z = poses[s].expand(len(offs), 3).clone()  # [O, 3]
            z[:, 2] += offs
            m = None if slam.mask is None else slam.mask[s]
            for name, M in (("young map", slam.map_mean(s)), ("true walls", walls)):
                with torch.no_grad():
                    lw = slam.pf._weigh(z, M, slam.obs[s], m, logw, s)[0].logw  # [O] normalised
                w = lw.exp()
                std = (w * (offs - (w * offs).sum()) ** 2).sum().sqrt()
                rows[name][r, s - 1] = float(offs[int(lw.argmax())]), float(std)
    out = []
    for name, a in rows.items():
        for lo, hi in windows:
            best, std = a[:, lo - 1 : hi - 1, 0], a[:, lo - 1 : hi - 1, 1]
            out.append(
                {
                    "map": name,
                    "steps": [lo, hi],
                    "abs_best_offset": round(float(np.abs(best).mean()), 4),
                    "mean_best_offset": round(float(best.mean()), 4),
                    "weights_heading_std": round(float(std.mean()), 4),
                }
            )
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--maze", type=int, default=993)
    p.add_argument("--traversal", type=int, default=1)
    p.add_argument("--steps", type=int, default=8, help="traversal length (SLAM runs over all)")
    p.add_argument("--windows", default="0:4,4:8", help="step windows a:b, comma-separated")
    p.add_argument("--sigma", type=float, default=0.05)
    p.add_argument("--config", default="{}", help="JSON SLAMConfig overrides (ray-cast added)")
    p.add_argument("--young", type=int, default=0, help="N > 0: the young-map weight profile")
    p.add_argument("--mazes", default="991,992,993,994,995,996", help="--young: maze seeds")
    p.add_argument("--young-windows", default="1:6,6:16,16:41", help="--young: step windows")
    args = p.parse_args(argv)
    if args.young > 0:
        for row in young_profile(args, {**RAYCAST, **json.loads(args.config)}):
            print(json.dumps(row))
        return 0
    from slam_accuracy import BENCH_CONFIG, _traversal

    from pyro_slam.cli import shipped_slam
    from pyro_slam.filtering import Particles
    from pyro_slam.networks import RayEmission
    from simulators.maze import make_maze

    windows = [tuple(int(v) for v in w.split(":")) for w in args.windows.split(",")]
    T = args.steps
    if not all(0 <= a < b <= T for a, b in windows):
        p.error(f"--windows must lie within the {T} steps, got {args.windows!r}")
    tr = _traversal(args.maze, args.traversal, T, True)
    over = {**BENCH_CONFIG, **RAYCAST, **json.loads(args.config), "seed": args.traversal}
    offsets = torch.linspace(-0.12, 0.12, 25, dtype=torch.float64)

    slam = shipped_slam(tr, "learned", **{**over, "ray_anchor": 1})
    poses = torch.as_tensor(tr.poses, dtype=slam.obs.dtype)
    offsets = offsets.to(slam.obs.dtype)
    slam.particles = Particles(poses[:1], torch.zeros(1, dtype=slam.obs.dtype))
    slam._anchor_scan(0)
    maps = {"first scan": slam.guide.params()[0].detach().clone()}
    walls = np.asarray(make_maze("moderate-medium", args.maze).walls)
    maps["true walls"] = RayEmission.wall_map(slam.model.grid, walls).to(slam.obs.dtype)
    run = shipped_slam(tr, "learned", **over)
    res = run.run("online", progress=False)
    maps["after SLAM"] = run.guide.params()[0].detach().clone()
    est = np.asarray(res["mean"])
    dh = np.angle(np.exp(1j * (est[:, 2] - tr.poses[:, 2])))
    print(json.dumps({"slam_heading_error": [round(float(v), 4) for v in dh]}))
    for name, M in maps.items():
        for (a, b), best, drop in profile(slam, M, poses, windows, offsets, args.sigma):
            row = {"map": name, "steps": [a, b], "best_offset": round(best, 3),
                   "truth_below_best_nats": round(drop, 2)}  # fmt: skip
            print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
