"""Helpers shared by the benchmark scripts (not a benchmark itself)."""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import torch

from pyro_slam.inference import ParticleFilter
from pyro_slam.runtime import DEFAULT_THREADS
from pyro_slam.slam import ConfigError, build_model, presets
from simulators import simulate_traversal

# the test mazes (moderate-medium) of the SLAM and navigation benchmarks, and the held-out
# mazes on which options are screened (never in the test figures)
MAZE_SEEDS = (1001, 1002, 1003, 1004, 1005, 1006)
TUNING_SEEDS = (991, 992, 993, 994, 995, 996)


def parse_maze_seeds(
    p: argparse.ArgumentParser, text: str, test: tuple[int, ...], tuning: tuple[int, ...] = ()
) -> list[int]:
    """The maze seeds of a ``--maze-seeds`` argument ``"1001,1002"``: each must be one of the
    benchmark's ``test`` mazes or its held-out ``tuning`` mazes; anything else is a usage error
    (``p.error``, exit 2) naming the offending seeds and the allowed ones."""
    try:
        mazes = [int(m) for m in text.split(",")]
    except ValueError:
        p.error(f"--maze-seeds: expected comma-separated integers, got {text!r}")
    if unknown := sorted(set(mazes) - set(test) - set(tuning)):
        allowed = f"not test mazes (these are {list(test)})"
        if tuning:
            allowed += f" or tuning mazes {list(tuning)}"
        p.error(f"--maze-seeds {unknown}: {allowed}")
    return mazes


def add_config_args(p: argparse.ArgumentParser, default: str, prefix: str = "") -> None:
    """``--{prefix}preset NAME`` (a :mod:`pyro_slam.slam.presets` name, default ``default``) and
    ``--{prefix}config JSON`` (nested overrides of the preset's configuration)."""
    p.add_argument(
        f"--{prefix}preset",
        choices=list(presets.PRESETS),
        default=default,
        help=f"the SLAM configuration (pyro_slam.slam.presets; default {default})",
    )
    p.add_argument(
        f"--{prefix}config",
        default="{}",
        metavar="JSON",
        help="nested overrides of the preset's configuration, e.g. "
        '\'{"filter": {"particles": 512}, "transition": {"kind": "kinematic"}}\'',
    )


def add_threads_arg(p: argparse.ArgumentParser, default: int = DEFAULT_THREADS) -> None:
    """``--threads N``: torch intra-op threads of the benchmark's runs, a stated number that
    its results depend on (never read from the machine's load; :mod:`pyro_slam.runtime`)."""

    def positive(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            n = 0
        if n < 1:
            raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
        return n

    p.add_argument(
        "--threads",
        type=positive,
        default=default,
        metavar="N",
        help=f"torch intra-op threads (default {default})",
    )


def print_json_main(parse, run, argv=None) -> int:
    """A benchmark's ``main``: ``args = parse(argv)``, torch's threads set to ``args.threads``,
    then ``run(args)`` printed as JSON."""
    args = parse(argv)
    torch.set_num_threads(args.threads)
    print(json.dumps(run(args)))
    return 0


def slam_config(
    p: argparse.ArgumentParser,
    preset: str,
    text: str,
    flag: str = "--config",
    base: dict | None = None,
):
    """The configuration of ``preset`` with the nested overrides ``base`` (a benchmark's own,
    if any), then the JSON overrides ``text`` applied, as the command line chooses it
    (:func:`pyro_slam.slam.presets.configure`); text that is not JSON or a configuration error
    is a usage error (``p.error``, exit 2) with a one-line message naming the problem."""
    try:
        return presets.configure(preset, overrides=[base, text])[1]
    except ConfigError as e:
        p.error(f"{flag}: {e}")


def _flat(d: dict, prefix: str = "") -> dict:
    """A nested dict as ``{"a.b": value}``."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def check_out_config(path: Path, record: dict) -> None:
    """Write ``record`` (e.g. ``{"config": config.to_dict(), ...}``) to ``path``, or stop with
    an error if ``path`` holds a different one: the runs (and cached networks) next to it were
    made with that configuration, and a resumed benchmark must not mix the two."""
    record = json.loads(json.dumps(record))  # tuples -> lists, as read back
    if path.is_file():
        old = _flat(json.loads(path.read_text()))
        new = _flat(record)
        if old != new:
            diff = sorted(k for k in {**old, **new} if old.get(k, ...) != new.get(k, ...))
            raise SystemExit(
                f"{path}: this output folder holds runs made with another configuration "
                f"(differs in {', '.join(diff)}); choose another --out"
            )
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1))


# ------------------------------------------- the online filter run of filter_speed and reliability
def peak_rss_mib() -> float:
    """This process's peak resident memory (MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def filter_setup(steps: int, seed: int = 0):
    """The fixed filtering problem of ``filter_speed`` and ``reliability``: the default
    configuration's model on a ``steps``-step moderate-medium traversal (``seed``) and a random
    fixed map. Returns ``(model, M, obs [T, B], controls [T - 1, 2], start pose [3])``."""
    tr = simulate_traversal("moderate-medium", steps=steps, seed=seed)
    model, guide = build_model(tr, presets.get("paper").config)  # the emission MLP
    g = torch.Generator().manual_seed(seed)
    M = torch.randn(model.grid.shape, generator=g)  # a fixed map: speed does not depend on it
    obs = torch.as_tensor(tr.observations, dtype=torch.float32)
    ctl = torch.as_tensor(tr.controls, dtype=torch.float32)
    init = torch.as_tensor(tr.poses[0], dtype=torch.float32)
    return model, M, obs, ctl, init


def filter_run(model, M, obs, ctl, init, K, steps, checkpoints=(), autocast_dtype=None):
    """Our particle filter, ``K`` particles, ``steps`` steps (cycling over the traversal) of
    :func:`filter_setup`'s problem; returns (steps/s, {step in ``checkpoints``: peak RSS MiB})."""
    g = torch.Generator().manual_seed(0)
    pf = ParticleFilter(model, generator=g, autocast_dtype=autocast_dtype)
    T = obs.shape[0]
    rss = {}
    with torch.no_grad():
        p, _ = pf.init(init + 1e-3 * torch.randn(K, 3), M, obs[0])
        t0 = time.perf_counter()
        for t in range(1, steps + 1):
            i = t % T  # cycle over the traversal for very long runs
            p, _ = pf.step(p, M, obs[i], ctl[(i - 1) % (T - 1)], step=t)
            _ = p.mean()  # the online estimate
            if t in checkpoints:
                rss[t] = peak_rss_mib()
        rate = steps / (time.perf_counter() - t0)
    return rate, rss
