"""Analog of Table I of PF-net (Karkus et al. 2018) on held-out moderate-medium mazes.

For each setting (walls only / distractors) and sensor (LiDAR / depth image), train PF-net, the
histogram filter network and the LSTM network on trajectories of the training mazes, tune the
beam-model PF on walls-only LiDAR data, and report the (x, y) RMSE in cm (1 m = 1/6 maze units)
on trajectories of separate test mazes. Prints a Markdown table (on stderr) and the RMSE per
method, setting and sensor as JSON, and writes everything to ``OUT/pfnet_table.json``.

    python -m benchmarks.pfnet_table --smoke            # seconds: plumbing check
    python -m benchmarks.pfnet_table --out out/pfnet    # full: ~22 min on 1 core

Full-mode budget (single thread): 400 training trajectories (40 mazes x 10) and 100 test
trajectories (10 unseen mazes x 10) per setting, 24 steps each. PF-net: 400 warm-start steps
of the observation model (32 poses x 16 candidates) + 2 epochs of end-to-end BPTT (2 x 50
batches of 8, K = 30, ESS-triggered soft resampling alpha = 0.5); histogram filter: 4 epochs;
LSTM: 6 epochs (HF / LSTM get roughly half of PF-net's training wall time). Trained models
are checkpointed under ``--out`` and reused when the script is run again.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

import simulators
from pyro_slam import pfnet
from pyro_slam.data import load_tensors
from pyro_slam.pfnet import baselines as bl
from pyro_slam.pfnet import data as pfnet_data


@dataclass
class Budget:
    train_mazes: int = 40
    traj_per_train_maze: int = 10
    test_mazes: int = 10
    traj_per_test_maze: int = 10
    pretrain_steps: int = 400
    pfnet_epochs: int = 2
    hf_epochs: int = 4
    lstm_epochs: int = 6
    batch_size: int = 8
    K_train: int = 30
    K_eval: tuple = (30, 300)
    beam_tune_traj: int = 40
    beam_tune_K: int = 100


SMOKE = Budget(
    train_mazes=3,
    traj_per_train_maze=4,
    test_mazes=2,
    traj_per_test_maze=2,
    pretrain_steps=5,
    pfnet_epochs=1,
    hf_epochs=1,
    lstm_epochs=1,
    batch_size=4,
    K_train=8,
    K_eval=(30, 60),
    beam_tune_traj=4,
    beam_tune_K=20,
)

SETTINGS = {"walls only": 0, "distractors": pfnet_data.N_DISTRACTORS}
SENSORS = ("lidar", "depth")


def make_data(budget: Budget, distractors: int, seed: int):
    def world(maze, s):
        return pfnet_data.SimWorld(maze, distractors=distractors, seed=s)

    train_mazes = [simulators.make_maze("moderate-medium", s) for s in range(budget.train_mazes)]
    test_mazes = [
        simulators.make_maze("moderate-medium", 10_000 + s) for s in range(budget.test_mazes)
    ]
    train = pfnet_data.generate(train_mazes, world, budget.traj_per_train_maze, seed=seed)
    test = pfnet_data.generate(test_mazes, world, budget.traj_per_test_maze, seed=seed + 1)
    return train, test


def fit(model, train, epochs, budget, ckpt, lr, desc, progress):
    cfg = pfnet.TrainConfig(
        epochs=epochs, batch_size=budget.batch_size, lr=lr, K=budget.K_train, progress=progress
    )
    t0 = time.monotonic()
    pfnet.train(model, train, cfg, checkpoint=ckpt, desc=desc)
    return time.monotonic() - t0


def run(budget: Budget, out: Path, progress: bool, seed: int = 0) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    results: dict = {"budget": budget.__dict__, "rmse_cm": {}, "train_seconds": {}}
    rm = results["rmse_cm"]
    beam_params = None
    for setting, k in SETTINGS.items():
        t0 = time.monotonic()
        train, test = make_data(budget, k, seed)
        print(
            f"[{setting}] data: {len(train)} train / {len(test)} test trajectories "
            f"({time.monotonic() - t0:.0f}s)",
            flush=True,
        )
        prop = pfnet.evaluate(bl.propagated_uncertainty(), test.with_sensor("lidar"), K=300)
        for sensor in SENSORS:
            rm[f"Propagated uncertainty|{setting}|{sensor}"] = prop
        # beam model: tuned on walls-only training data, LiDAR only
        if beam_params is None:
            beam_params, _ = bl.tune_beam_model(
                train.with_sensor("lidar"), K=budget.beam_tune_K, n_traj=budget.beam_tune_traj
            )
            results["beam_model_params"] = beam_params
        beam = pfnet.evaluate(bl.BeamModelPF(**beam_params), test.with_sensor("lidar"), K=300)
        rm[f"Beam-model PF, K=300|{setting}|lidar"] = beam
        for sensor in SENSORS:
            tr = train.with_sensor(sensor, fresh_init=True)
            te = test.with_sensor(sensor)
            ocfg = train.obs_model_config(sensor)
            learned_filters(results, (setting, sensor), tr, te, ocfg, budget, out, progress, seed)
            row = ", ".join(
                f"{key.split('|')[0]}: {v:.1f}"
                for key, v in rm.items()
                if key.endswith(f"|{setting}|{sensor}")
            )
            print(f"[{setting} / {sensor}] {row}", flush=True)
    return results


def learned_filters(results, case, tr, te, ocfg, budget, out, progress, seed) -> None:
    """Train PF-net, the histogram filter network and the LSTM network on ``tr`` (checkpoints
    under ``out``) for ``case`` ``(setting, sensor)``, and add their RMSE on ``te`` and their
    training times to ``results``."""
    setting, sensor = case
    rm, secs_of = results["rmse_cm"], results["train_seconds"]
    tag = f"{setting.replace(' ', '_')}-{sensor}"
    # PF-net
    torch.manual_seed(seed)
    om = pfnet.ObservationModel(ocfg)
    pre = out / f"pfnet-{tag}-pretrain.pt"
    t0 = time.monotonic()
    if pre.exists():
        om.load_state_dict(load_tensors(pre, "a PF-net observation model"))
    else:
        pfnet.pretrain_observation_model(
            om, tr, budget.pretrain_steps, seed=seed, progress=progress
        )
        torch.save(om.state_dict(), pre)
    net = pfnet.PFNet(om, resample="ess", alpha=0.5)
    secs = time.monotonic() - t0
    ckpt = out / f"pfnet-{tag}.pt"
    secs += fit(net, tr, budget.pfnet_epochs, budget, ckpt, 3e-4, f"PF-net {tag}", progress)
    secs_of[f"PF-net|{tag}"] = secs
    for K in budget.K_eval:
        rm[f"PF-net, K={K}|{setting}|{sensor}"] = pfnet.evaluate(net, te, K=K)
    # histogram filter network
    torch.manual_seed(seed)
    hf = bl.HistogramFilterNet(ocfg)
    ckpt = out / f"hf-{tag}.pt"
    secs_of[f"HF|{tag}"] = fit(hf, tr, budget.hf_epochs, budget, ckpt, 1e-3, f"HF {tag}", progress)
    rm[f"Histogram filter network|{setting}|{sensor}"] = pfnet.evaluate(hf, te)
    # LSTM network
    torch.manual_seed(seed)
    lstm = bl.LSTMNet(ocfg)
    ckpt = out / f"lstm-{tag}.pt"
    epochs = budget.lstm_epochs
    secs_of[f"LSTM|{tag}"] = fit(lstm, tr, epochs, budget, ckpt, 1e-3, f"LSTM {tag}", progress)
    rm[f"LSTM network|{setting}|{sensor}"] = pfnet.evaluate(lstm, te)


def markdown(results: dict, K_eval) -> str:
    rm = results["rmse_cm"]
    cols = [(s, x) for s in SETTINGS for x in SENSORS]
    rows = [
        "Propagated uncertainty",
        "Beam-model PF, K=300",
        "Histogram filter network",
        "LSTM network",
        *[f"PF-net, K={K}" for K in K_eval],
    ]
    head = "| method | " + " | ".join(f"{s}: {x}" for s, x in cols) + " |"
    lines = [head, "|" + "---|" * (len(cols) + 1)]
    for r in rows:
        vals = [rm.get(f"{r}|{s}|{x}") for s, x in cols]
        lines.append(
            f"| {r} | " + " | ".join("—" if v is None else f"{v:.1f}" for v in vals) + " |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")  # the library's progress
    ap = argparse.ArgumentParser(
        prog="python -m benchmarks.pfnet_table", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--smoke", action="store_true", help="tiny fast run (plumbing check)")
    ap.add_argument("--out", default=None, help="output folder (JSON, checkpoints)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    pfnet.seed_everything(args.seed)
    budget = SMOKE if args.smoke else Budget()
    out = Path(args.out or ("out/pfnet_table_smoke" if args.smoke else "out/pfnet_table"))
    t0 = time.monotonic()
    results = run(budget, out, progress=not args.no_progress, seed=args.seed)
    results["total_seconds"] = time.monotonic() - t0
    results["markdown"] = markdown(results, budget.K_eval)
    (out / "pfnet_table.json").write_text(json.dumps(results, indent=2, default=float))
    print(results["markdown"], file=sys.stderr)
    print(
        f"total {results['total_seconds']:.0f}s; JSON: {out / 'pfnet_table.json'}", file=sys.stderr
    )
    summary = {"rmse_cm": results["rmse_cm"], "total_seconds": results["total_seconds"]}
    print(json.dumps(summary, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
