"""How much of SLAM's and path integration's position error their heading error explains.

Reads the runs a ``slam_accuracy.py`` call exported (``OUT/runs/<mode>_m*_t*_T*.npz``: the
trajectories ``estimate``, ``truth`` and ``pi_poses``) and prints JSON: at each of ``--times``,
the mean over the runs of the position error, of :func:`pyro_slam.metrics.heading_only_error`
(the error the heading error alone causes along the true path) and of the absolute heading error,
for SLAM and for path integration, of :func:`pyro_slam.metrics.along_track_error` (signed: < 0
where the estimate has fallen behind the truth along the path), and the fraction of runs where SLAM
beats path integration.

    python benchmarks/slam_error_sources.py out/s13_shtt_24 --mode online
    python benchmarks/slam_error_sources.py out/s18_v_od057_pn --glob "m*.npz" --times 1000,-1 \
        --per-run                                    # visual_slam.py runs, one row per run

``--glob`` reads other run files that hold the same trajectories (``visual_slam.py`` writes
``OUT/runs/m<maze>*.npz``); ``--per-run`` adds each run's values (runs in name order, ``files``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pyro_slam.metrics import (  # noqa: E402
    along_track_error,
    heading_error,
    heading_only_error,
    localisation_error,
)


def load_runs(
    parser: argparse.ArgumentParser, out: Path, mode: str, pattern: str | None = None
) -> list[dict]:
    """The trajectories ``estimate``, ``truth``, ``pi_poses`` (each ``[T, 3]``) and the file
    ``name`` of every ``OUT/runs/<mode>_m*_t*_T*.npz`` run (or of ``pattern``), in name order; a
    clear parser error if there are none or a run lacks one."""
    pattern = pattern or f"{mode}_m*_t*_T*.npz"
    files = sorted((out / "runs").glob(pattern))
    if not files:
        parser.error(f"no {pattern} runs under {out / 'runs'}")
    runs = []
    for f in files:
        with np.load(f) as z:
            missing = {"estimate", "truth", "pi_poses"} - set(z.files)
            if missing:
                parser.error(f"{f}: no {sorted(missing)} (re-run slam_accuracy.py to export them)")
            runs.append({"name": f.name, **{k: z[k] for k in ("estimate", "truth", "pi_poses")}})
    return runs


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("out", type=Path, help="a slam_accuracy.py --out directory")
    p.add_argument("--mode", default="online", help="online | offline (the runs' file prefix)")
    p.add_argument("--times", default="150,300,450,900,1200,1800,2400,-1")
    p.add_argument("--glob", default=None, help="run files under OUT/runs (default: the mode's)")
    p.add_argument("--per-run", action="store_true", help="also each run's values")
    args = p.parse_args(argv)
    runs = load_runs(p, args.out, args.mode, args.glob)
    rows = {k: [] for k in ("slam", "slam_heading_only", "slam_heading", "pi", "pi_heading_only",
                            "pi_heading", "slam_along_track", "pi_along_track")}  # fmt: skip
    for z in runs:
        truth = z["truth"]
        for name, est in (("slam", z["estimate"]), ("pi", z["pi_poses"])):
            rows[name].append(localisation_error(est, truth))
            rows[f"{name}_heading_only"].append(heading_only_error(est, truth))
            rows[f"{name}_heading"].append(heading_error(est[:, 2], truth[:, 2]))
            rows[f"{name}_along_track"].append(along_track_error(est, truth))
    arr = {k: np.stack(v) for k, v in rows.items()}  # [runs, T]
    T = arr["slam"].shape[1]
    times = [t if t >= 0 else T + t for t in map(int, args.times.split(","))]
    bad = [t for t in times if not 0 <= t < T]
    if bad:
        p.error(f"--times {bad} outside the runs' {T} steps")
    out = {"runs": len(runs), "mode": args.mode, "t": times}
    out.update({f"{k}_mean": [round(float(arr[k][:, t].mean()), 4) for t in times] for k in arr})
    beats = arr["slam"][:, times] < arr["pi"][:, times]
    out["slam_beats_pi_fraction"] = [round(float(b), 3) for b in beats.mean(0)]
    if args.per_run:
        out["files"] = [z["name"] for z in runs]
        out.update({f"{k}_per_run": [[round(float(v), 4) for v in r] for r in arr[k][:, times]]
                    for k in arr})  # fmt: skip
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
