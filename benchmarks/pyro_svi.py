"""Pyro's SVI on the model, as a Pyro user runs it: ``SVI(model.model, guide, Adam,
Trace_ELBO())`` on a default-preset traversal, with the SLAM guide and with ``AutoNormal`` over
the blocked model.

    python -m benchmarks.pyro_svi --out out/pyro_svi
    python -m benchmarks.pyro_svi --preset raycast --steps 300 --svi-steps 300

The traversal is ``--steps`` steps on a tuning maze (``--maze-seed``, driver ``--seed``; the
SLAM run is built, not run, so the map starts at the prior). Each guide is trained for
``--svi-steps`` steps of ``svi.step(*slam.model_inputs())``:

* ``slam``: ``slam.sequence_guide()``, the SLAM run's map (and frame) guide, then each pose from
  its proposal;
* ``autonormal``: ``AutoNormal(poutine.block(model.model, expose=["map"]))`` as the map's guide,
  with the run's frame guide and proposal around it (``sequence_guide``).

Every ``--every`` steps the map belief's error against the true walls is measured: the mean
absolute difference between the ranges its mean predicts at the true poses and the traversal's
noise-free scans there (:func:`pyro_slam.inference.scan_error`). The JSON gives, per guide, the
loss's moving average (``--window`` steps) at the start and the end, whether any loss or
parameter was NaN, and the map error at the start and the end (``OUT/<guide>.json`` also
holds the curves); ``OUT/pyro_svi_<guides>.png`` plots both curves.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pyro
import torch
from pyro import poutine
from pyro.infer import SVI, Trace_ELBO
from pyro.infer.autoguide import AutoNormal
from pyro.optim import Adam
from tqdm import tqdm

from benchmarks._common import add_threads_arg, print_json_main
from benchmarks.slam_accuracy import _traversal
from pyro_slam.inference import scan_error, sequence_guide
from pyro_slam.model import GlobalGuide
from pyro_slam.slam import SLAM, presets


def parse(argv):
    p = argparse.ArgumentParser(prog="python -m benchmarks.pyro_svi", description=__doc__)
    p.add_argument("--out", type=Path, default=Path("out/pyro_svi"))
    p.add_argument("--preset", default=presets.DEFAULT, choices=sorted(presets.PRESETS))
    p.add_argument("--maze-seed", type=int, default=991)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--svi-steps", type=int, default=300)
    p.add_argument("--lr", type=float, default=0.05)
    p.add_argument("--every", type=int, default=25)
    p.add_argument("--window", type=int, default=20)
    p.add_argument("--guides", default="slam,autonormal", help="comma-separated: slam, autonormal")
    add_threads_arg(p)
    return p.parse_args(argv)


def _guides(slam: SLAM) -> dict:
    """The guides to train, each ``(guide, map_mean)``: ``map_mean()`` reads the map belief's
    mean ``[w, h, D_m]``."""
    m, args = slam.model, slam.model_inputs()
    auto = AutoNormal(poutine.block(m.model, expose=["map"]), init_scale=1.0)
    auto(*args)  # (its parameters, so that its median reads before the first step)
    frame = getattr(slam.guide, "frame", None)
    return {
        "slam": (slam.sequence_guide(), lambda: slam.map_belief().loc),
        "autonormal": (
            sequence_guide(m, slam.proposal, GlobalGuide(auto, frame)),
            lambda: auto.median(*args)["map"],
        ),
    }


def _train(slam: SLAM, guide, map_mean, args) -> dict:
    """``args.svi_steps`` SVI steps with ``guide``; the losses and the map errors."""
    tr, m, inputs = slam.tr, slam.model, slam.model_inputs()

    def error() -> float:
        return scan_error(m, map_mean(), tr.poses, slam.obs, slam.mask)

    svi = SVI(m.model, guide, Adam({"lr": args.lr}), Trace_ELBO())
    losses, errors = [], []
    for i in tqdm(range(args.svi_steps), desc="svi", leave=False):
        if i % args.every == 0:
            errors.append((i, error()))
        losses.append(svi.step(*inputs))
    errors.append((args.svi_steps, error()))
    finite = all(math.isfinite(v) for v in losses) and all(
        bool(torch.isfinite(p).all()) for p in pyro.get_param_store().values()
    )
    return {"losses": losses, "errors": errors, "finite": finite}


def _summary(run: dict, window: int) -> dict:
    ma = np.convolve(run["losses"], np.ones(window) / window, mode="valid")
    return {
        "loss_ma_first": float(ma[0]),
        "loss_ma_last": float(ma[-1]),
        "loss_ma_falls": bool(ma[-1] < ma[0]),
        "finite": run["finite"],
        "map_error_first": run["errors"][0][1],
        "map_error_last": run["errors"][-1][1],
        "map_error_falls": bool(run["errors"][-1][1] < run["errors"][0][1]),
    }


def _plot(runs: dict, window: int, path: Path) -> None:
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    for name, run in runs.items():
        ma = np.convolve(run["losses"], np.ones(window) / window, mode="valid")
        a.plot(np.arange(len(ma)) + window, ma, label=name)
        steps, errs = zip(*run["errors"])
        b.plot(steps, errs, marker="o", label=name)
    a.set(xlabel="SVI step", ylabel=f"loss, moving average of {window}", title="Trace_ELBO loss")
    b.set(xlabel="SVI step", ylabel="mean |range error| (m)", title="map belief vs true walls")
    a.legend(), b.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args) -> dict:
    tr = _traversal(args.maze_seed, args.seed, args.steps)
    out = {"preset": args.preset, "steps": args.steps, "svi_steps": args.svi_steps}
    args.out.mkdir(parents=True, exist_ok=True)
    runs = {}
    for name in args.guides.split(","):
        slam = SLAM(tr, args.preset, seed=args.seed)
        with slam.scope():
            pyro.set_rng_seed(args.seed)
            guide, map_mean = _guides(slam)[name]
            runs[name] = _train(slam, guide, map_mean, args)
        out[name] = _summary(runs[name], args.window)
        (args.out / f"{name}.json").write_text(json.dumps({**out[name], **runs[name]}))
    _plot(runs, args.window, args.out / f"pyro_svi_{'_'.join(runs)}.png")
    return out


def main(argv=None) -> int:
    return print_json_main(parse, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
