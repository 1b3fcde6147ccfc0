"""Reliability figures, printed as JSON.

* ``bad_input``: each malformed input and the exception it raises at the API boundary.
* ``nan_free``: online SLAM on the default maze with 10 seeds: all losses and estimates finite.
  SLAM runs a preset (``--preset``, default ``raycast``) with fewer particles (``SMALL``) and
  ``--config`` overrides on top.
* ``kill_resume``: an online SLAM process killed with SIGKILL mid-training (at a random moment,
  not right after a checkpoint) is resumed from its last checkpoint in a new process and
  finishes with the same map parameters and poses as an uninterrupted run (max abs difference).
* ``memory``: peak RSS of a long online particle-filter run after 10% and 100% of its steps.

    python -m benchmarks.reliability                    # full (100k-step filter run)
    python -m benchmarks.reliability --long-steps 10000 --nan-seeds 3
    python -m benchmarks.reliability --preset paper --long-steps 10000
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks._common import add_config_args, filter_run, filter_setup, slam_config
from pyro_slam.data import load
from pyro_slam.slam import SLAM, checkpoint, presets
from simulators import simulate_traversal

REPO = Path(__file__).resolve().parents[1]

# fewer particles than the presets' for quicker runs (overrides applied before --config's)
SMALL = {"filter": {"particles": 64}, "training": {"particles": 8, "chunks": 4, "chunk_length": 4}}


def bad_input_cases(tmp: Path) -> list[dict]:
    tr = simulate_traversal("simple-small", steps=20, seed=0)
    good = tr.save(tmp / "good.npz")
    d = dict(np.load(good))

    def variant(name, **change):
        arrays = {**d, **change}
        path = tmp / f"{name}.npz"
        np.savez(path, **arrays)
        return path

    obs = d["observations"]
    cases = {
        "nan observation": variant("nan", observations=np.where(np.eye(*obs.shape), np.nan, obs)),
        "inf observation": variant("inf", observations=np.full_like(obs, np.inf)),
        "negative range": variant("neg", observations=-obs),
        "wrong beam count": variant("beams", observations=obs[:, :7]),
        "controls length": variant("ctl", controls=d["controls"][:-3]),
        "poses length": variant("poses", poses=d["poses"][:5]),
        "string dtype": variant("dtype", observations=obs.astype(str)),
        "empty sequence": variant("empty", observations=obs[:0], controls=d["controls"][:0]),
    }
    raw = good.read_bytes()
    (tmp / "truncated.npz").write_bytes(raw[: len(raw) // 2])
    cases["truncated file"] = tmp / "truncated.npz"
    (tmp / "garbage.npz").write_bytes(b"\x00garbage" * 10)
    cases["garbage file"] = tmp / "garbage.npz"
    out = []
    for name, path in cases.items():
        try:
            load(path)
            out.append({"case": name, "raised": None})
        except Exception as e:  # noqa: BLE001 -- we report whatever is raised
            out.append({"case": name, "raised": type(e).__name__, "message": str(e)[:160]})
    return out


def nan_free(config, seeds: int, steps: int) -> dict:
    tr = simulate_traversal("moderate-medium", steps=steps, seed=1)
    finite = []
    for s in range(seeds):
        res = SLAM(tr, config, seed=s).run("online", progress=False)
        ok = all(np.isfinite(res[k]).all() for k in ("mean", "std", "losses", "map_loc"))
        finite.append(bool(ok))
    return {"runs": seeds, "steps": steps, "all_finite": all(finite), "finite": finite}


# run with the repository as the working directory (its packages first on the path)
SCRIPT = """
import torch
torch.set_num_threads(1)
from simulators import simulate_traversal
from pyro_slam.slam import SLAM, from_dict
tr = simulate_traversal("moderate-medium", steps={steps}, seed=1)
config = from_dict({config!r})
slam = SLAM(tr, config, checkpoint={ckpt!r}, checkpoint_every=25, seed=3)
if {resume}:
    slam.resume({ckpt!r})
res = slam.run("online", progress=False)
import numpy as np
np.savez({out!r}, mean=res["mean"], map_loc=res["map_loc"], map_scale=res["map_scale"])
"""


def kill_resume(config, tmp: Path, steps: int, kill_after: float) -> dict:
    def script(ckpt, out, resume):
        return textwrap.dedent(
            SCRIPT.format(
                steps=steps, config=config.to_dict(), ckpt=str(ckpt), out=str(out), resume=resume
            )
        )

    ref_out, res_out, ckpt = tmp / "ref.npz", tmp / "res.npz", tmp / "ckpt.pt"
    py = [sys.executable, "-c"]
    subprocess.run([*py, script(tmp / "ref.pt", ref_out, False)], check=True, cwd=REPO)
    proc = subprocess.Popen([*py, script(ckpt, res_out, False)], cwd=REPO)
    while not ckpt.exists() and proc.poll() is None:  # wait for the first checkpoint
        time.sleep(0.05)
    time.sleep(kill_after)  # then kill mid-way between checkpoints
    if proc.poll() is not None:
        raise RuntimeError("the run finished before it could be killed: lower --kill-after")
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    t_ckpt = int(checkpoint.read(ckpt)["state"]["t"])
    subprocess.run([*py, script(ckpt, res_out, True)], check=True, cwd=REPO)
    a, b = np.load(ref_out), np.load(res_out)
    diff = max(float(np.abs(a[k] - b[k]).max()) for k in ("mean", "map_loc", "map_scale"))
    return {
        "steps": steps,
        "killed_with": "SIGKILL",
        "killed_returncode": proc.returncode,
        "resumed_from_step": t_ckpt,
        "max_abs_diff": diff,
    }


def memory(long_steps: int, particles: int) -> dict:
    model, M, obs, ctl, init = filter_setup(3000)
    marks = (long_steps // 10, long_steps)
    rate, rss = filter_run(model, M, obs, ctl, init, particles, long_steps, checkpoints=marks)
    return {
        "steps": long_steps,
        "particles": particles,
        "steps_per_s": round(rate, 1),
        **{f"peak_rss_mib_at_{k}": round(v, 1) for k, v in rss.items()},
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.reliability", description=__doc__.split("\n")[0]
    )
    p.add_argument("--nan-seeds", type=int, default=10)
    p.add_argument("--nan-steps", type=int, default=300)
    p.add_argument("--kill-steps", type=int, default=400)
    p.add_argument(
        "--kill-after", type=float, default=1.5, help="seconds after the first checkpoint"
    )
    p.add_argument("--long-steps", type=int, default=100_000)
    p.add_argument("--particles", type=int, default=1000, help="of the memory run's filter")
    add_config_args(p, presets.DEFAULT)
    args = p.parse_args(argv)
    config = slam_config(p, args.preset, args.config, base=SMALL)
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        out = {"preset": args.preset, "config": config.to_dict()}
        out["bad_input"] = bad_input_cases(tmp)
        out["nan_free"] = nan_free(config, args.nan_seeds, args.nan_steps)
        out["kill_resume"] = kill_resume(config, tmp, args.kill_steps, args.kill_after)
    out["memory"] = memory(args.long_steps, args.particles)
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    os.environ.setdefault("MPLBACKEND", "Agg")
    main()
