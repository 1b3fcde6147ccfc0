"""Exact perceptual aliasing of the navigation benchmark's observation targets.

The paper's criterion for pose-to-observation navigation is position: a run fails if the agent
ends more than 0.05 from the pose the target scan was taken at. Where another place sees exactly
the same scan, no inverse model reading that scan can know which of the two was meant. This
script measures how often that happens, with the truth itself as the inverse: for each test
maze, the targets of ``benchmarks.navigation`` (its 25 grid points, two random headings each,
the same seed) are inverted by :meth:`pyro_slam.planning.GroundTruthEnv.places` (every place
whose true, noise-free scan matches, refined to float precision). Per maze and in all:

* ``aliased``: the share of targets with a look-alike place more than 0.05 away, one whose true
  scan differs by less than a tolerance (``--tols``, mean absolute range; 1e-6 is exact);
* ``ideal_failure``: the expected failure ratio of an *ideal* inverse -- exact map, exact
  sensor, a uniform choice among the places that see the target scan (within the tolerance).
  With the target's true place as likely as each of its exact look-alikes (the grid does not
  know the maze's symmetries), no inverse reading the scan does better on average, so at
  tolerance 1e-6 a criterion below this number cannot be met on these targets by any planner;
  at 0.01 (a tenth of the model's ``sigma_E``) it is what an inverse that cannot resolve
  smaller differences can expect.

``free_grid`` moves a grid point closer than 0.04 to a wall to its maze cell's centre, the most
symmetric place of a cell; the shares are also given separately for the moved and the kept
points.

Sensor variants (``--sensors``, ``BEAMSxRANGE``) show how much of the ambiguity a richer
observation would remove; the paper's LiDAR is ``20x0.53``.

    python -m benchmarks.aliasing --out out/aliasing --sensors 20x0.53,40x0.53,20x1.0

Output: ``OUT/aliasing.json`` (per sensor and tolerance: ``aliased``, ``ideal_failure``, and both
per maze) and ``OUT/aliasing.png`` (the expected failures per maze against the 2 % criterion).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from tqdm.auto import tqdm

from benchmarks._common import MAZE_SEEDS, parse_maze_seeds
from pyro_slam.planning import free_grid
from pyro_slam.planning.evaluation import aliasing, observation_targets
from simulators import LidarConfig, make_maze


def parse_sensor(text: str) -> tuple[int, float]:
    """``"20x0.53"`` -> ``(20, 0.53)``: beam count and maximum range."""
    try:
        beams, rng = text.split("x")
        return int(beams), float(rng)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"sensor {text!r}: expected BEAMSxRANGE, e.g. 20x0.53"
        ) from None


def main(argv=None) -> int:
    args, mazes, sensors, tols = _parse(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    result = {"args": {k: str(v) for k, v in vars(args).items()}, "sensors": {}}
    for beams, rng in sensors:
        rows = sensor_rows(LidarConfig(n_beams=beams, max_range=rng), mazes, tols, args)
        result["sensors"][f"{beams}x{rng:g}"] = {
            f"{tol:g}": _summary({str(ms): r[tol] for ms, r in rows.items()}) for tol in tols
        }
    result["wall_s"] = time.perf_counter() - t0
    (args.out / "aliasing.json").write_text(json.dumps(result, indent=1))
    _plot(result, args.out / "aliasing.png")
    headline = {
        sensor: {tol: {k: s[k] for k in ("aliased", "ideal_failure")} for tol, s in by_tol.items()}
        for sensor, by_tol in result["sensors"].items()
    }
    print(json.dumps(headline))
    return 0


def _parse(argv) -> tuple[argparse.Namespace, tuple[int, ...], list, list[float]]:
    """The arguments, the mazes, the sensors ``(beams, range)`` and the tolerances; usage
    errors exit 2."""
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.aliasing", description=__doc__.split("\n")[0]
    )
    p.add_argument("--out", type=Path, default=Path("out/aliasing"))
    p.add_argument("--maze-seeds", default=None, help="comma-separated test mazes (default all)")
    p.add_argument("--seed", type=int, default=0, help="the navigation benchmark's --seed")
    p.add_argument(
        "--sensors", default="20x0.53", help="comma-separated BEAMSxRANGE LiDARs (paper: 20x0.53)"
    )
    p.add_argument(
        "--tols",
        default="1e-6,0.01",
        help="comma-separated look-alike tolerances (mean absolute range): 1e-6 is exact; 0.01, "
        "a tenth of the model's sigma_E, is what a learned model can hope to resolve",
    )
    p.add_argument("--spacing", type=float, default=0.01, help="position grid of the search")
    args = p.parse_args(argv)
    mazes = (
        MAZE_SEEDS if args.maze_seeds is None else parse_maze_seeds(p, args.maze_seeds, MAZE_SEEDS)
    )
    try:
        sensors = [parse_sensor(t) for t in args.sensors.split(",")]
    except argparse.ArgumentTypeError as e:
        p.error(str(e))
    try:
        tols = [float(t) for t in args.tols.split(",")]
    except ValueError:
        p.error(f"--tols: expected comma-separated numbers, got {args.tols!r}")
    return args, mazes, sensors, tols


def sensor_rows(lidar, mazes, tols, args) -> dict:
    """Per maze, :func:`~pyro_slam.planning.evaluation.aliasing` of the navigation benchmark's
    observation targets seen by ``lidar``, with whether each target's grid point was moved to
    its cell's centre (``moved``): ``{maze: {tol: per-target lists}}``."""
    rows = {}
    for ms in tqdm(mazes, desc=f"{lidar.n_beams}x{lidar.max_range:g}"):
        maze = make_maze("moderate-medium", ms)
        pts = free_grid(maze)  # [25, 2]
        tposes = observation_targets(pts, ms, args.seed)  # [50, 3]
        rows[ms] = aliasing(maze, tposes, lidar, tols, args.spacing)
        # free_grid moves a grid point near a wall to its cell's centre
        moved = np.abs(pts - free_grid(maze, clearance=0.0)).max(1) > 1e-9  # [25]
        for r in rows[ms].values():
            r["moved"] = np.repeat(moved, 2).tolist()
    return rows


def _summary(per_maze: dict) -> dict:
    """Shares over the targets of each maze and of all: with a look-alike, and the ideal
    inverse's expected failure ratio; over all, also split by whether the target's grid point
    was moved to its cell's centre (``moved_to_cell_centre``) or kept (``kept``)."""

    def share(r, sel=None):
        sel = np.ones(len(r["ideal_failure"]), bool) if sel is None else sel
        return {
            "targets": int(sel.sum()),
            "aliased": float(np.mean(np.array(r["lookalikes"])[sel] > 0)),
            "ideal_failure": float(np.mean(np.array(r["ideal_failure"])[sel])),
        }

    keys = ("lookalikes", "ideal_failure", "moved")
    every = {k: sum((r[k] for r in per_maze.values()), []) for k in keys}
    moved = np.array(every["moved"], bool)
    return {
        **share(every),
        "kept": share(every, ~moved),
        "moved_to_cell_centre": share(every, moved),
        "per_maze": {ms: share(r) for ms, r in per_maze.items()},
    }


def _plot(result: dict, path: Path) -> None:
    matplotlib.use("Agg")
    bars = [
        (f"LiDAR {sensor}, look-alike < {tol}", s)
        for sensor, by_tol in result["sensors"].items()
        for tol, s in by_tol.items()
    ]
    mazes = list(bars[0][1]["per_maze"])
    fig, ax = plt.subplots(figsize=(10, 4))
    width = 0.8 / len(bars)
    for k, (label, s) in enumerate(bars):
        vals = [s["per_maze"][m]["ideal_failure"] for m in mazes] + [s["ideal_failure"]]
        ax.bar(np.arange(len(mazes) + 1) + k * width, vals, width, label=label)
    ax.axhline(0.02, color="k", ls="--", lw=1, label="criterion: <= 2 % failures")
    ax.set_xticks(np.arange(len(mazes) + 1) + 0.4 - width / 2, [*mazes, "all"])
    ax.set_xlabel("test maze")
    ax.set_ylabel("expected failure ratio")
    ax.set_title("observation targets: expected failures of an ideal inverse")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
