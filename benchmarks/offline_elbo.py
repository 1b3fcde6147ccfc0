"""Does offline SVI raise its own objective? The ELBO of the map belief along offline SVI on a
real log.

    python -m benchmarks.offline_elbo --log intel --seed 2 --steps 50,100,200,400,800
    python -m benchmarks.offline_elbo --log mit-csail --seed 0 --steps 50,100,200,400 --lr 0.005

The online sweep of the ``real`` preset (as :mod:`benchmarks.real_data` runs it: Intel with its
odometry made from the GMapping poses plus noise), then offline SVI steps on chunks from the
whole log, as :func:`pyro_slam.slam.loop.offline_round` takes them, at the preset's map learning
rate or at ``--lr``. At the start and after each number of steps in ``--steps`` the script
estimates the ELBO of ``q(M)`` on the whole log (:func:`traversal_elbo`: one chunk every
``chunk_length`` steps, ``--draws`` draws of the map, the same random numbers at every
evaluation, so that two beliefs compare on the same draws) and prints, as one JSON line per
evaluation, its data term, the map's KL from the prior, their difference, and the median mean
and std of the grid points that the online map holds as walls (mean above 1). The last line is
the whole result as JSON.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np
import torch
from torch.distributions import kl_divergence

from benchmarks._common import add_threads_arg, print_json_main
from benchmarks.real_data import DATA, log_config, noisy_odometry
from pyro_slam.inference import ChunkBatch
from pyro_slam.io import read_any
from pyro_slam.slam import loop
from pyro_slam.slam.runner import SLAM

LOGS = {"intel": "intel.gfs.log", "mit-csail": "mit-csail.clf"}
EVAL_SEED = 12345  # the random numbers of every ELBO evaluation


def traversal_elbo(slam: SLAM, draws: int) -> dict:
    """The ELBO of the run's ``q(M)`` on its whole traversal, estimated as the training
    objective does (:class:`~pyro_slam.inference.ParticleChunkELBO`) on one chunk every
    ``chunk_length`` steps, averaged over ``draws`` draws of the globals: ``data`` (the chunks'
    log evidence scaled to the traversal), ``data_sd`` (over the draws), ``kl`` (the map's) and
    ``elbo``. The random numbers are the same at every call; the particle cache and the run's
    generator are left as they were. Call inside ``slam.scope()``."""
    c, st, data = slam.components, slam.state, slam.data
    L = data.cfg.training.chunk_length
    starts = torch.arange(0, data.T - L + 1, L)
    cache, gen_state = st.cache, st.gen.get_state()
    evs, kls = [], []
    with torch.no_grad(), torch.random.fork_rng(devices=[]):
        torch.manual_seed(EVAL_SEED)
        st.gen.manual_seed(EVAL_SEED)
        for _ in range(draws):
            c.elbo.cache = copy.deepcopy(cache)  # the chunks refresh it
            g, m = c.elbo.global_traces(c.model.handled(), c.guide)
            kls.append(float(kl_divergence(g.nodes["map"]["fn"], m.nodes["map"]["fn"]).sum()))
            frame = m.nodes["frame"]["value"] if "frame" in m.nodes else None
            ev = c.elbo.chunk_log_evidence(g.nodes["map"]["value"], ChunkBatch(starts, L), frame)
            evs.append(float(ev.sum()) * data.T / (len(starts) * L))
    c.elbo.cache = cache
    st.gen.set_state(gen_state)
    d, kl = float(np.mean(evs)), float(np.mean(kls))
    return {"data": d, "data_sd": float(np.std(evs)), "kl": kl, "elbo": d - kl}


def set_map_rate(slam: SLAM, lr: float) -> None:
    """Set the learning rate of the map's parameters in the run's optimiser (created by the
    online sweep's SVI steps)."""
    tc = slam.cfg.training
    for opt in slam.components.optim.optim_objs.values():
        for group in opt.param_groups:
            if group["lr"] == tc.lr:
                group["lr"] = lr


def walls(slam: SLAM) -> torch.Tensor:
    """The grid points the map belief holds as walls (mean above 1, touched by insertion)."""
    b = slam.components.map_belief()
    return (b.loc[..., 0] > 1.0) & ((b.scale[..., 0] - 1).abs() > 1e-3)


def run(args) -> dict:
    """The sweep, then the SVI steps and the evaluations; returns the result."""
    path = args.data / LOGS[args.log]
    tr = read_any(path)
    tr = noisy_odometry(tr) if args.log == "intel" else tr  # (as benchmarks.real_data)
    tr = tr.slice(0, min(args.scans, tr.num_steps)) if args.scans else tr
    slam = SLAM(tr, log_config(tr), seed=args.seed, threads=args.threads)
    c, st, data = slam.components, slam.state, slam.data
    L, rows = data.cfg.training.chunk_length, []
    with slam.scope():
        loop.online_sweep(c, st, data, progress=False)
        if args.lr is not None:
            set_map_rate(slam, args.lr)
        held, done = walls(slam), 0
        for k in [0, *args.steps]:
            for _ in range(k - done):
                loop.svi_step(c, st, data, 0, data.T - L, None)
            done = k
            b = c.map_belief()
            row = {"svi_steps": k, **traversal_elbo(slam, args.draws)}
            row["wall_mean"] = float(b.loc[..., 0][held].median())
            row["wall_std"] = float(b.scale[..., 0][held].median())
            print(json.dumps(row), flush=True)
            rows.append(row)
    lr = args.lr if args.lr is not None else slam.cfg.training.lr
    return {"log": args.log, "seed": args.seed, "lr": lr, "draws": args.draws, "rows": rows}


def parse(argv):
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.offline_elbo", description=__doc__.split("\n")[0]
    )
    p.add_argument("--log", choices=sorted(LOGS), default="intel")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", default="50,100,200,400", help="SVI step counts to evaluate at")
    p.add_argument("--lr", type=float, default=None, help="the map's rate (default: preset's)")
    p.add_argument("--draws", type=int, default=3, help="draws of the map per evaluation")
    p.add_argument("--scans", type=int, default=0, help="the log's first N scans only")
    p.add_argument("--data", type=Path, default=DATA)
    add_threads_arg(p)
    args = p.parse_args(argv)
    try:
        args.steps = sorted({int(s) for s in args.steps.split(",") if s.strip()})
    except ValueError:
        p.error(f"--steps: comma-separated integers, got {args.steps!r}")
    if any(s < 1 for s in args.steps) or args.draws < 1 or args.scans < 0:
        p.error("--steps and --draws must be positive, --scans at least 0")
    if args.lr is not None and not args.lr > 0:
        p.error(f"--lr: must be positive, got {args.lr}")
    return args


def main(argv=None) -> int:
    return print_json_main(parse, run, argv)


if __name__ == "__main__":
    sys.exit(main())
