"""What the model and its filter can do on a real log given the best map: one fused at the
reference poses.

    python -m benchmarks.likelihood_peak                       # Intel, the ``real`` preset
    python -m benchmarks.likelihood_peak --config '{"emission": {"resolution": 0.1}}'

The map belief is written by the preset's scan insertion from every scan of Intel's log placed
at its reference poses (GMapping's), so that pose errors play no part (the log is set up as
:mod:`benchmarks.real_data` runs it, so that the map's grid is the same). Then, at every
``--every``-th scan, the model's log-likelihood of that scan (the particle filter's weight: the
emission marginalised over ``q(M)``, :meth:`pyro_slam.inference.ParticleFilter.log_likelihood`;
the heading factor left out) is searched on a grid of poses around the reference pose: 9 x 9 x
9 poses ``--step`` m and ``--turn`` rad apart, then the same grid a quarter as wide around the
best. How far the peak lies from the reference pose is what the model can do at all, apart from
the filter: its mean offset is a bias (the beams' geometry, where insertion places the walls),
its mean size a resolution. The reference poses carry errors of their own, so an ideal model
does not reach zero. Prints the peak offsets' mean size (m, deg), median size and mean (x, y,
heading) as JSON. Searched at every scan (``--every 1``, the default), the peaks also form a
trajectory, and its Kümmerle relation error (the relations of :mod:`benchmarks.real_data`) is
the floor of a per-scan estimate.

Then the preset's particle filter *localises* on that map, ``--seeds`` times (default 3, seeds
0..N-1): one forward pass over the log with the map held fixed (no insertion), smoothed by
forward filtering, backward smoothing over the whole pass, as offline SLAM ends. Its relation
error (mean ± std over seeds, worst) is the filter's floor on this log: SLAM, which builds its
own map from its own poses, does not do better; its calibration (std / error raw, aligned,
2-sigma coverage) stands beside it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from benchmarks._common import add_config_args, add_threads_arg, print_json_main, slam_config
from benchmarks.real_data import DATA, evaluate, log_config, noisy_odometry
from pyro_slam import metrics
from pyro_slam.io import read_any
from pyro_slam.io.relations import relation_error, relations_from_reference
from pyro_slam.slam import loop
from pyro_slam.slam.runner import SLAM
from pyro_slam.slam.state import Phase

GRID = 4  # the search grid: 2 * GRID + 1 poses per axis


def fused_at_reference(slam: SLAM, poses: torch.Tensor) -> None:
    """Insert every scan of the run at ``poses [T, 3]`` (no placement variance)."""
    with torch.no_grad(), slam.scope():
        for t in range(slam.T):
            slam.inserter.insert(slam.obs[t], slam.valid(t), poses[t], 0.0)


def likelihood_peak(slam: SLAM, t: int, centre: torch.Tensor, step: float, turn: float):
    """The pose ``[3]`` near ``centre [3]`` at which the model's log-likelihood of scan ``t``
    under the map belief peaks: a grid search, then a grid a quarter as wide around its best."""
    belief = slam.map_belief()
    g = torch.arange(-GRID, GRID + 1, dtype=centre.dtype)
    best = centre
    for scale in (1.0, 0.25):
        dx, dy, dh = torch.meshgrid(
            g * step * scale, g * step * scale, g * turn * scale, indexing="ij"
        )
        z = best + torch.stack([dx, dy, dh], -1).reshape(-1, 3)  # [9^3, 3]
        with torch.no_grad(), slam.scope():
            ll = slam.pf.log_likelihood(z, belief, slam.obs[t], slam.valid(t))[0]
        best = z[ll.argmax()]
    return best


def localise(slam: SLAM) -> dict:
    """One filter pass of ``slam`` over its log under its map belief as it stands (nothing
    inserted), smoothed over the whole pass: :meth:`SLAM.result`'s ``mean`` and ``std``."""
    st = slam.state
    st.begin("offline")
    with torch.no_grad(), slam.scope():
        st.estimates, st.stds, st.anchors = loop.filter_pass(
            slam.components, st, slam.data, False, "localise"
        )
        st.phase = Phase.DONE
        return loop.estimates(st, slam.data, slam.model)


def peaks(tr, cfg, args) -> tuple[dict, np.ndarray]:
    """The likelihood's peak at every ``--every``-th scan: the offsets' summary, and the
    peaks ``[n, 3]``."""
    slam = SLAM(tr, cfg, seed=0, threads=args.threads)
    if slam.inserter is None:
        raise SystemExit("likelihood_peak: the configuration has no scan insertion")
    ref = torch.as_tensor(np.asarray(tr.poses), dtype=slam.obs.dtype)  # [T, 3]
    fused_at_reference(slam, ref)
    found = [
        likelihood_peak(slam, t, ref[t], args.step, args.turn).tolist()
        for t in range(args.every // 2, slam.T, args.every)
    ]
    found = np.asarray(found, dtype=np.float64)  # [n, 3]
    d = found - np.asarray(tr.poses, dtype=np.float64)[args.every // 2 :: args.every]
    size = np.hypot(d[:, 0], d[:, 1])
    turn = np.degrees(np.abs(d[:, 2]))
    return {
        "scans": len(d),
        "resolution_m": cfg.emission.resolution,
        "beam_angles_deg": [float(np.degrees(a)) for a in tr.beam_angles[[0, 1, -1]]],
        "peak_offset_mean_m": float(size.mean()),
        "peak_offset_median_m": float(np.median(size)),
        "peak_turn_mean_deg": float(turn.mean()),
        "peak_turn_median_deg": float(np.median(turn)),
        "peak_offset_bias": [float(v) for v in d.mean(0)],  # x m, y m, heading rad
    }, found


def run(args) -> dict:
    tr = noisy_odometry(read_any(args.data / "intel.gfs.log"))  # the grid spans its path
    cfg = log_config(tr, args.preset, json.loads(args.config))
    out, found = peaks(tr, cfg, args)
    rel = relations_from_reference(tr.timestamps, tr.poses, n_random=1000, max_steps=50)
    if args.every == 1:
        err = relation_error(tr.timestamps, found, rel)["trans_mean"]
        out["peak_relation_error_trans_m"] = err
    runs = []
    for seed in range(args.seeds):
        slam = SLAM(tr, cfg, seed=seed, threads=args.threads)
        fused_at_reference(slam, torch.as_tensor(np.asarray(tr.poses), dtype=slam.obs.dtype))
        est = localise(slam)
        row = evaluate(tr, metrics.consistency_scans(tr), est["mean"], tr.poses, rel, est["std"])
        runs.append([row["relation_error"]["trans_mean"], *row["calibration"].values()])
        print(f"localise seed {seed}: {runs[-1][0]:.4f} m", file=sys.stderr)
    if runs:
        r = np.asarray(runs, dtype=np.float64)  # [seeds, 4]
        out["localisation_relation_error_trans_m"] = float(r[:, 0].mean())
        out["localisation_relation_error_std_m"] = float(r[:, 0].std(ddof=1)) if len(r) > 1 else 0.0
        out["localisation_relation_error_worst_m"] = float(r[:, 0].max())
        out["localisation_calibration"] = dict(zip(row["calibration"], r[:, 1:].mean(0).tolist()))
    return out


def parse(argv):
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.likelihood_peak", description=__doc__.split("\n")[0]
    )
    p.add_argument("--every", type=int, default=1, help="search at every N-th scan")
    p.add_argument(
        "--seeds", type=int, default=3, help="filter runs localising on the map (0: none)"
    )
    p.add_argument("--step", type=float, default=0.02, help="the grid's position step (m)")
    p.add_argument("--turn", type=float, default=0.01, help="the grid's heading step (rad)")
    p.add_argument("--data", type=Path, default=DATA)
    add_config_args(p, "real")
    add_threads_arg(p)
    args = p.parse_args(argv)
    if args.every < 1 or args.seeds < 0 or not (args.step > 0 and args.turn > 0):
        p.error("--every, --step and --turn must be positive, --seeds not negative")
    slam_config(p, args.preset, args.config)  # a bad --preset / --config: a usage error now
    return args


def main(argv=None) -> int:
    return print_json_main(parse, run, argv)


if __name__ == "__main__":
    sys.exit(main())
