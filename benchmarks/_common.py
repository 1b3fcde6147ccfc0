"""Helpers shared by the benchmark scripts (not a benchmark itself)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from pyro_slam.slam import ConfigError, presets, with_overrides

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


def slam_config(
    p: argparse.ArgumentParser,
    preset: str,
    text: str,
    flag: str = "--config",
    base: dict | None = None,
):
    """The configuration of ``preset`` with the nested overrides ``base`` (a benchmark's own,
    if any), then the JSON overrides ``text`` applied (:func:`pyro_slam.slam.with_overrides`);
    text that is not JSON or a configuration error is a usage error (``p.error``, exit 2) with a
    one-line message naming the problem."""
    try:
        changes = json.loads(text)
    except json.JSONDecodeError as e:
        p.error(f"{flag}: not JSON ({e})")
    config = with_overrides(presets.get(preset).config, base or {})
    try:
        return with_overrides(config, changes)
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
