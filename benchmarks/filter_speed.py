"""Online filter throughput and memory: our batched particle filter vs ``pyro.infer.SMCFilter``.

Both run the same DVBF-LM time step (paper emission MLP, 4 x 256 softsign, 20 beams; kinematic
transition; a fixed map, as when filtering on a learned map) with K = 1000 particles on one
simulated moderate-medium traversal, in one process, one after the other. Prints JSON with
steps/s of each and their ratio, and the peak RSS of a long online run (our filter) after 10%
and 100% of its steps -- flat memory means the run keeps no per-step history. It also times the
emission MLP alone on the same K particles (``emission_only_steps_per_s``): both filters run it
once per step, so no implementation of the step beats that figure, and ``ceiling_speedup`` is
the most any filter could gain over SMCFilter at that precision.

    python -m benchmarks.filter_speed           # K = 1000, 500 timed steps, 100k-step run
    python -m benchmarks.filter_speed --long-steps 10000   # quicker memory check
"""

from __future__ import annotations

import argparse
import contextlib
import json
import time

import pyro
import torch
from pyro.infer import SMCFilter

from benchmarks._common import filter_run, filter_setup
from pyro_slam.inference import ProposalGuide, TransitionProposal
from pyro_slam.model import FilterModel


def emission_only(model, M, init, K, steps, autocast_dtype=None):
    """The emission MLP alone on K particles' charts, per step: a ceiling for any filter.

    Every filter step of either filter runs ``model.emission_mean`` on all K particles once;
    this times that call by itself (fixed particles, no transition, weights or resampling), so
    ``steps / s`` here bounds what any implementation of the same step can reach.
    """
    g = torch.Generator().manual_seed(0)
    z = init + 1e-2 * torch.randn(K, 3, generator=g)  # [K, 3]
    ctx = (
        torch.autocast(z.device.type, dtype=autocast_dtype)
        if autocast_dtype is not None
        else contextlib.nullcontext()
    )
    with torch.no_grad(), ctx:
        model.emission_mean(M, z)
        t0 = time.perf_counter()
        for _ in range(steps):
            model.emission_mean(M, z)  # [K, B]
        return steps / (time.perf_counter() - t0)


def smcfilter(model, M, obs, ctl, init, K, steps):
    """pyro.infer.SMCFilter running the same model step (pyro_slam.model.FilterModel)."""
    pyro.set_rng_seed(0)
    guide = ProposalGuide(model, TransitionProposal())
    smc = SMCFilter(FilterModel(model, M), guide, K, max_plate_nesting=0)
    with torch.no_grad():
        smc.init(init_pose=init, x=obs[0])
        t0 = time.perf_counter()
        for t in range(1, steps + 1):
            smc.step(t, obs[t], ctl[t - 1])
            _ = smc.get_empirical()["z"].mean
        return steps / (time.perf_counter() - t0)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.filter_speed", description=__doc__.split("\n")[0]
    )
    p.add_argument("--particles", type=int, default=1000)
    p.add_argument("--steps", type=int, default=500, help="timed steps per filter")
    p.add_argument("--long-steps", type=int, default=100_000)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    model, M, obs, ctl, init = filter_setup(max(args.steps + 1, 3000))
    # warm-up both (allocator, lazy init) before timing
    filter_run(model, M, obs, ctl, init, args.particles, 20)
    smcfilter(model, M, obs, ctl, init, args.particles, 20)
    r_smc = smcfilter(model, M, obs, ctl, init, args.particles, args.steps)
    r_ours, _ = filter_run(model, M, obs, ctl, init, args.particles, args.steps)
    filter_run(model, M, obs, ctl, init, args.particles, 20, autocast_dtype=torch.bfloat16)
    r_bf16, _ = filter_run(
        model, M, obs, ctl, init, args.particles, args.steps, autocast_dtype=torch.bfloat16
    )
    r_mlp = emission_only(model, M, init, args.particles, args.steps)
    r_mlp_bf16 = emission_only(
        model, M, init, args.particles, args.steps, autocast_dtype=torch.bfloat16
    )
    n = args.long_steps
    marks = (n // 10, n)
    t0 = time.perf_counter()
    r_long, rss = filter_run(model, M, obs, ctl, init, args.particles, n, checkpoints=marks)
    out = {
        "particles": args.particles,
        "threads": torch.get_num_threads(),
        "ours_steps_per_s": round(r_ours, 1),
        "smcfilter_steps_per_s": round(r_smc, 1),
        "speedup": round(r_ours / r_smc, 2),
        "ours_bf16_emission_steps_per_s": round(r_bf16, 1),
        "speedup_bf16": round(r_bf16 / r_smc, 2),
        # ceiling: the emission MLP alone, which both filters run once per step on K particles
        "emission_only_steps_per_s": round(r_mlp, 1),
        "emission_only_bf16_steps_per_s": round(r_mlp_bf16, 1),
        "ceiling_speedup": round(r_mlp / r_smc, 2),
        "long_run_steps": n,
        "long_run_steps_per_s": round(r_long, 1),
        "long_run_wall_s": round(time.perf_counter() - t0, 1),
        f"peak_rss_mib_at_{marks[0]}": round(rss[marks[0]], 1),
        f"peak_rss_mib_at_{marks[1]}": round(rss[marks[1]], 1),
    }
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
