"""Paired comparison of two benchmark outputs over the runs they share.

Reads the per-run error curves (``slam`` and ``pi``, ``[T]``) that ``slam_accuracy`` and
``visual_slam`` write to ``OUT/runs/*.npz``, matches the runs of ``A`` and ``B`` by file name
(same maze, traversal and length, hence the same truth), and prints JSON: for each side the final
error (mean, std, median, runs under 0.05, runs beating path integration) and the time-averaged
error; and the paired difference ``A - B`` at the final step and time-averaged (mean, its
standard error, and on how many runs ``A`` is lower).

    python -m benchmarks.compare_runs out/slam_accuracy_raycast out/slam_accuracy_paper \
        --glob "offline_*.npz"
    python -m benchmarks.compare_runs out/visual_slam out/visual_slam_raycast --glob "m*.npz"
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pyro_slam import metrics


def _load(parser, out: Path, pattern: str) -> dict[str, dict]:
    files = sorted((out / "runs").glob(pattern))
    if not files:
        parser.error(f"no runs matching {pattern!r} under {out / 'runs'}")
    runs = {}
    for f in files:
        with np.load(f) as z:
            missing = {"slam", "pi"} - set(z.files)
            if missing:
                parser.error(f"{f}: no {sorted(missing)} error curve")
            runs[f.name] = {"slam": z["slam"].astype(float), "pi": z["pi"].astype(float)}
            if {"std", "estimate", "truth"} <= set(z.files):  # the posterior's calibration
                runs[f.name]["calibration"] = metrics.calibration(
                    z["std"].astype(float),
                    z["estimate"].astype(float),
                    z["truth"].astype(float),
                    metrics.CALIBRATION_START,
                )
    return runs


def _side(runs: list[dict]) -> dict:
    final = np.array([r["slam"][-1] for r in runs])  # [R]
    pi = np.array([r["pi"][-1] for r in runs])
    return {
        "final_mean": float(final.mean()),
        "final_std": float(final.std()),
        "final_median": float(np.median(final)),
        "runs_under_0.05": int((final < 0.05).sum()),
        "runs_beating_pi": int((final < pi).sum()),
        "time_avg_mean": float(np.mean([r["slam"].mean() for r in runs])),
        "pi_final_mean": float(pi.mean()),
        **_calibration(runs),
    }


def _calibration(runs: list[dict]) -> dict:
    """The medians over runs of :func:`pyro_slam.metrics.calibration` (where runs have it)."""
    cal = [r["calibration"] for r in runs if "calibration" in r]
    if len(cal) < len(runs) or not cal:
        return {}
    return {f"{k}_median": float(np.median([c[k] for c in cal])) for k in cal[0]}


def _paired(d: np.ndarray) -> dict:  # d [R] = A - B
    se = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("nan")
    return {"mean": float(d.mean()), "se": se, "a_lower": int((d < 0).sum())}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.compare_runs", description=__doc__.split("\n")[0]
    )
    p.add_argument("a", type=Path, help="a benchmark --out directory")
    p.add_argument("b", type=Path, help="the one to compare against")
    p.add_argument("--glob", default="online_*.npz", help="run files under OUT/runs")
    args = p.parse_args(argv)
    a, b = _load(p, args.a, args.glob), _load(p, args.b, args.glob)
    common = sorted(set(a) & set(b))
    if not common:
        p.error(f"{args.a} and {args.b} share no run matching {args.glob!r}")
    for name in common:
        if len(a[name]["slam"]) != len(b[name]["slam"]):
            p.error(f"{name}: {len(a[name]['slam'])} steps in A, {len(b[name]['slam'])} in B")
    ra, rb = [a[n] for n in common], [b[n] for n in common]
    out = {
        "runs": len(common),
        "a": {"out": str(args.a), "all_runs": len(a), **_side(ra)},
        "b": {"out": str(args.b), "all_runs": len(b), **_side(rb)},
        "paired_final": _paired(np.array([x["slam"][-1] - y["slam"][-1] for x, y in zip(ra, rb)])),
        "paired_time_avg": _paired(
            np.array([x["slam"].mean() - y["slam"].mean() for x, y in zip(ra, rb)])
        ),
    }
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
