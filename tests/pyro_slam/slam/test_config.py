"""The SLAM configuration (:mod:`pyro_slam.slam.config`): component configs, validation, nested
overrides, dict round trips; plain data that loads no torch."""

from __future__ import annotations

import dataclasses
import inspect
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from pyro_slam.slam import (
    ConfigError,
    FilterConfig,
    HeadingConfig,
    ScanInsertionConfig,
    SLAMConfig,
    presets,
    with_overrides,
)
from pyro_slam.slam import config as config_module


# ------------------------------------------------------------------------ overrides
def test_with_overrides_applies_nested_changes_and_keeps_the_rest():
    base = presets.get("raycast").config
    cfg = with_overrides(
        base,
        {
            "filter": {"particles": 512},
            "emission": {"insert": {"gap": 0.1}},
            "beam_stride": 2,
            "transition": {"scale": [1, 2, 3]},
        },
    )
    assert cfg.filter == replace(base.filter, particles=512)
    assert cfg.emission.insert == ScanInsertionConfig(gap=0.1)
    assert cfg.emission.kind == "raycast" and cfg.emission.resolution == base.emission.resolution
    assert cfg.transition.scale == (1.0, 2.0, 3.0) and isinstance(cfg.transition.scale, tuple)
    assert cfg.beam_stride == 2
    assert (cfg.training, cfg.offline, cfg.heading) == (base.training, base.offline, None)
    assert base.filter.particles == 128 and base.beam_stride == 1  # the original is unchanged
    # components are replaced whole when given as objects
    assert with_overrides(base, {"filter": FilterConfig(particles=7)}).filter == FilterConfig(7)


def test_with_overrides_switches_the_heading_observation_on_and_off():
    raycast, manhattan = presets.get("raycast").config, presets.get("manhattan").config
    on = with_overrides(raycast, {"heading": {"sigma": 0.002}})
    assert on.heading == HeadingConfig(sigma=0.002, support=2)  # from the defaults
    assert with_overrides(raycast, {"heading": {}}) == manhattan
    assert with_overrides(manhattan, {"heading": {"support": 3}}).heading == HeadingConfig(1e-3, 3)
    assert with_overrides(manhattan, {"heading": None}) == raycast
    assert with_overrides(raycast, {"emission": {"insert": None}}).emission.insert is None


@pytest.mark.parametrize(
    "changes, field",
    [
        ({"nope": 1}, "nope"),
        ({"filter": {"partcles": 5}}, "filter.partcles"),
        ({"emission": {"insert": {"gapp": 0.1}}}, "emission.insert.gapp"),
        ({"heading": {"tol": 1e-3}}, "heading.tol"),
        ({"training": {"chunk_length": 4, "lr_map": 0.1}}, "training.lr_map"),
    ],
)
def test_unknown_fields_are_rejected_by_their_dotted_name(changes, field):
    with pytest.raises(ConfigError, match=rf"unknown field {field}(;|$)"):
        with_overrides(presets.get("raycast").config, changes)


def test_unknown_fields_list_the_known_ones():
    with pytest.raises(ConfigError, match="FilterConfig has lag, particles, proposal"):
        with_overrides(SLAMConfig(), {"filter": {"partcles": 5}})
    with pytest.raises(ConfigError, match="unknown fields filter.a, filter.b"):
        with_overrides(SLAMConfig(), {"filter": {"b": 1, "a": 2}})


@pytest.mark.parametrize("value", [-5, 0, "abc", None, 2.5, True])
def test_bad_particle_counts_are_rejected_by_name(value):
    msg = rf"filter\.particles must be a positive integer, got {value!r}"
    with pytest.raises(ConfigError, match=msg):
        with_overrides(SLAMConfig(), {"filter": {"particles": value}})
    with pytest.raises(ConfigError, match=msg):
        FilterConfig(particles=value)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"emission": {"resolution": 0}}, "emission.resolution must be a positive number, got 0"),
        ({"emission": {"resolution": math.inf}}, "emission.resolution must be a positive"),
        ({"emission": {"sigma": -0.1}}, "emission.sigma must be a positive number"),
        ({"emission": {"margin": -1}}, "emission.margin must be a number >= 0"),
        ({"emission": {"kind": "nerf"}}, "emission.kind must be one of"),
        (
            {"emission": {"kind": "mlp", "insert": {}}},
            "emission.insert .* needs a ray-cast LiDAR emission.kind .*got 'mlp'",
        ),
        ({"emission": {"outlier_prob": 1.0}}, r"emission.outlier_prob must be in \[0, 1\)"),
        ({"emission": {"ray_spacing": 0}}, "emission.ray_spacing must be a positive number"),
        ({"emission": {"march_tolerance": 1}}, r"emission.march_tolerance must be in \[0, 1\)"),
        ({"emission": {"insert": {"kind": "tsdf"}}}, "emission.insert.kind must be one of"),
        ({"emission": {"insert": {"occupancy": -2}}}, "emission.insert.occupancy must be a pos"),
        ({"emission": {"insert": {"noise": 0}}}, "emission.insert.noise must be a positive"),
        ({"emission": {"insert": {"occupancy": "high"}}}, "emission.insert.occupancy must be"),
        ({"transition": {"scale": [1, 1]}}, r"transition.scale must be 3 positive numbers"),
        ({"transition": {"sigma": [1, 0, 1]}}, r"transition.sigma must be 3 positive numbers"),
        ({"transition": {"kind": "neural"}}, "transition.kind must be one of"),
        ({"filter": {"proposal": "predictive"}}, "filter.proposal must be one of"),
        ({"filter": {"lag": -1}}, "filter.lag must be an integer >= 0"),
        ({"training": {"cache_particles": 0}}, "training.cache_particles must be a positive"),
        ({"training": {"lr_emission": 0}}, "training.lr_emission must be a positive number"),
        ({"training": {"chunk_length": 0}}, "training.chunk_length must be a positive integer"),
        ({"training": {"every": 1.5}}, "training.every must be an integer >= 0"),
        ({"training": {"lr": -1}}, "training.lr must be a positive number"),
        ({"offline": {"rounds": -1}}, "offline.rounds must be an integer >= 0"),
        ({"offline": {"estimate": "smooth"}}, "offline.estimate must be one of"),
        ({"heading": {"sigma": 0}}, "heading.sigma must be a positive number"),
        ({"heading": {"support": 1}}, "heading.support must be an integer >= 2"),
        ({"beam_stride": 0}, "beam_stride must be a positive integer"),
        ({"range_clip": -2.0}, "range_clip must be a positive number"),
        ({"filter": 5}, "filter must be a FilterConfig, got 5"),
        ({"heading": "on"}, "heading must be a HeadingConfig"),
    ],
)
def test_bad_values_are_rejected_naming_the_field(changes, message):
    with pytest.raises(ConfigError, match=message):
        with_overrides(presets.get("raycast").config, changes)


def test_config_errors_are_value_errors_and_configs_are_frozen():
    assert issubclass(ConfigError, ValueError)
    with pytest.raises(ConfigError, match="must be a JSON object"):
        with_overrides(SLAMConfig(), [1, 2])
    cfg = SLAMConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.beam_stride = 2
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.filter.particles = 2


def test_the_configuration_imports_no_torch():
    """Reading the configuration (plain data) loads neither torch nor the networks."""
    code = (
        "import sys; import pyro_slam.slam.config as c; c.SLAMConfig(); "
        "print(sorted(m for m in sys.modules if m == 'torch' or m.startswith('pyro_slam.')))"
    )
    root = Path(__file__).resolve().parents[3]
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    loaded = eval(out.stdout)
    assert "torch" not in loaded, loaded
    assert loaded == ["pyro_slam.slam", "pyro_slam.slam.config", "pyro_slam.slam.kinds"]


def test_the_configuration_has_at_most_40_fields():
    classes = [
        cls
        for name, cls in inspect.getmembers(config_module, inspect.isclass)
        if name.endswith("Config") and cls.__module__ == config_module.__name__
    ]
    assert SLAMConfig in classes and ScanInsertionConfig in classes and HeadingConfig in classes
    assert all(dataclasses.is_dataclass(cls) for cls in classes)
    assert sum(len(dataclasses.fields(cls)) for cls in classes) <= 40
