"""The exploration configuration (:class:`~pyro_slam.planning.exploration.ExploreConfig`):
frozen, checked on construction, changed by nested dicts, written and read as plain dicts."""

from __future__ import annotations

import json
import math
import re
from dataclasses import FrozenInstanceError, replace

import pytest

from pyro_slam.planning.exploration import ExploreConfig, MIConfig, PlanConfig, with_overrides
from pyro_slam.slam.config import ConfigError


def _flat(d: dict, prefix: str = "") -> dict:
    """A nested dict as ``{"a.b": value}``."""
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def test_the_configuration_is_frozen():
    cfg = ExploreConfig.smoke()
    with pytest.raises(FrozenInstanceError):
        cfg.seed = 1
    with pytest.raises(FrozenInstanceError):
        cfg.mi.K = 5
    assert cfg == ExploreConfig.smoke()


def test_the_default_holds_the_papers_values():
    """Appendices D and E: T = 50, F = 40 candidates by 500 Adam steps at 1e-3, L/M/K =
    30/40/100, sigma_T = 4e-4, 500 SVI steps on batches of 128 after each plan."""
    flat = _flat(ExploreConfig().to_dict())
    paper = {
        "plan.horizon": 50,
        "plan.execute_steps": 0,
        "plan.block_radius": 0.0,
        "candidates.count": 40,
        "candidates.steps": 500,
        "candidates.lr": 1e-3,
        "candidates.turn_reg": 2.0,
        "mi.L": 30,
        "mi.M": 40,
        "mi.K": 100,
        "motion.sigma_T": 4e-4,
        "motion.step_length": 0.01,
        "motion.max_turn": math.pi / 4,
        "mapping.train_steps": 500,
        "mapping.batch": 128,
    }
    assert {k: flat[k] for k in paper} == paper


def test_smoke_differs_from_the_default_only_by_the_documented_reduced_budget():
    """docs/exploration.md, "The reduced benchmark configuration"."""
    default, smoke = _flat(ExploreConfig().to_dict()), _flat(ExploreConfig.smoke().to_dict())
    assert set(default) == set(smoke)
    changed = {k: v for k, v in smoke.items() if v != default[k]}
    assert changed == {
        "plan.horizon": 25,
        "plan.execute_steps": 25,
        "plan.max_replans": 1000,
        "plan.block_radius": 0.02,
        "candidates.count": 8,
        "candidates.steps": 200,
        "candidates.lr": 0.02,
        "candidates.init_std": 0.05,
        "mi.L": 20,
        "mi.M": 8,
        "mi.K": 20,
        "mi.obs_stride": 5,
        "mapping.train_steps": 60,
        "mapping.lr_map": 0.02,
    }


def test_smoke_takes_nested_changes_and_keeps_the_rest():
    base = ExploreConfig.smoke()
    cfg = ExploreConfig.smoke(mi={"K": 5}, plan={"horizon": 10}, seed=3)
    assert cfg.mi == replace(base.mi, K=5) and cfg.plan == replace(base.plan, horizon=10)
    assert cfg.seed == 3 and (cfg.candidates, cfg.mapping) == (base.candidates, base.mapping)
    assert ExploreConfig.smoke(mi=MIConfig()).mi == MIConfig()  # a component given whole
    assert with_overrides(base, {}) == base


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"mi": {"K": 0}}, "explore.mi.K must be a positive integer, got 0"),
        ({"mi": {"L": 1}}, "explore.mi.L must exceed explore.mi.knn_k = 1, got 1"),
        ({"plan": {"horizon": 1}}, "explore.plan.horizon must be an integer >= 2, got 1"),
        ({"plan": {"execute_steps": -1}}, "explore.plan.execute_steps must be an integer >= 0"),
        ({"plan": {"block_radius": math.nan}}, "explore.plan.block_radius must be a number >= 0"),
        ({"candidates": {"lr": 0.0}}, "explore.candidates.lr must be a positive number, got 0.0"),
        ({"candidates": {"count": 2.0}}, "explore.candidates.count must be a positive integer"),
        ({"motion": {"max_turn": -1}}, "explore.motion.max_turn must be a positive number"),
        ({"mapping": {"batch": True}}, "explore.mapping.batch must be a positive integer"),
        ({"mapping": {"learn_emission": 1}}, "explore.mapping.learn_emission must be true or"),
        ({"obstacles": {"hist_blur": -0.5}}, "explore.obstacles.hist_blur must be a number >= 0"),
        ({"seed": -1}, "explore.seed must be an integer >= 0, got -1"),
        ({"mi": 3}, "explore.mi must be a MIConfig, got 3"),
    ],
)
def test_bad_values_are_rejected_by_their_dotted_name(changes, message):
    with pytest.raises(ConfigError, match=f"^{re.escape(message)}"):
        with_overrides(ExploreConfig(), changes)
    with pytest.raises(ConfigError, match=f"^{re.escape(message.split()[0])} "):
        ExploreConfig.smoke(**changes)


def test_components_check_themselves():
    with pytest.raises(ConfigError, match="explore.mi.K must be a positive integer"):
        MIConfig(K=0)
    with pytest.raises(ConfigError, match="explore.plan.horizon must be an integer >= 2"):
        PlanConfig(horizon=1)


@pytest.mark.parametrize(
    "changes, field",
    [
        ({"mi": {"k": 5}}, "explore.mi.k"),
        ({"horizon": 10}, "explore.horizon"),  # the fields live in their components
        ({"endpoints": "observed"}, "explore.endpoints"),
        ({"plan": {"T": 5, "steps": 1}}, "explore.plan.T, explore.plan.steps"),
    ],
)
def test_unknown_fields_are_rejected_by_their_dotted_name(changes, field):
    with pytest.raises(ConfigError, match=rf"unknown fields? {re.escape(field)}; "):
        with_overrides(ExploreConfig(), changes)


def test_unknown_fields_list_the_known_ones():
    with pytest.raises(ConfigError, match="MIConfig has K, L, M, knn_k, obs_stride"):
        ExploreConfig.smoke(mi={"N": 5})
    with pytest.raises(ConfigError, match="explore must be a JSON object"):
        with_overrides(ExploreConfig(), [("seed", 1)])


@pytest.mark.parametrize(
    "cfg",
    [ExploreConfig(), ExploreConfig.smoke(), ExploreConfig.smoke(seed=4, mi={"K": 7})],
    ids=["default", "smoke", "changed"],
)
def test_to_dict_and_from_dict_round_trip_through_json(cfg):
    d = cfg.to_dict()
    assert set(d) == {"plan", "candidates", "mi", "motion", "mapping", "obstacles", "seed"}
    assert ExploreConfig.from_dict(d) == cfg
    assert ExploreConfig.from_dict(json.loads(json.dumps(d))) == cfg


def test_from_dict_fills_missing_fields_with_the_defaults():
    assert ExploreConfig.from_dict({}) == ExploreConfig()
    cfg = ExploreConfig.from_dict({"mi": {"K": 7}})
    assert cfg == replace(ExploreConfig(), mi=MIConfig(K=7))
