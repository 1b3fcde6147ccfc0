"""Navigation's defaults are read from one place: the planner, the learned map and the
``navigate`` command take :data:`~pyro_slam.planning.NAVIGATION`'s."""

from __future__ import annotations

import dataclasses
import inspect

import pytest

from pyro_slam import cli
from pyro_slam.planning import NAVIGATION, NavigationConfig, learned_env, plan, seek_observation


def _defaults(fn) -> dict:
    return {k: p.default for k, p in inspect.signature(fn).parameters.items()}


def test_navigation_defaults_come_from_navigation_config():
    assert plan.__kwdefaults__["max_expansions"] == NAVIGATION.max_expansions
    assert seek_observation.__kwdefaults__["rounds"] == NAVIGATION.observe_rounds
    env = _defaults(learned_env)
    assert env["steps"] == NAVIGATION.traversal_steps
    for name in ("fit_steps", "emission_steps", "n_world", "max_std", "hit_margin"):
        assert env[name] == getattr(NAVIGATION, name), name
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.dest == "command" or a.choices).choices
    args = sub["navigate"].parse_args([])
    assert args.max_expansions == NAVIGATION.max_expansions
    assert args.traversal_steps == NAVIGATION.traversal_steps
    assert (args.fit_steps, args.emission_steps) == (
        NAVIGATION.fit_steps,
        NAVIGATION.emission_steps,
    )
    assert args.n_world == NAVIGATION.n_world


def test_navigation_config_is_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        NAVIGATION.max_expansions = 1
    assert NavigationConfig() == NAVIGATION
