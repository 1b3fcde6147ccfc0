"""The named presets (:mod:`pyro_slam.slam.presets`): the documented ones, how they differ,
their adaptation to a real log, and a SLAM run of each for its sensor."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pyro
import pytest
import torch

from pyro_slam.data import Traversal
from pyro_slam.model import (
    EndPointEmission,
    ImageEmission,
    KinematicTransition,
    LearnedTransition,
    LidarEmission,
    RayEmission,
    RayImageEmission,
)
from pyro_slam.pretrained import (
    EMISSION_FILE,
    PRETRAINED,
    TRANSITION_FILE,
    load_emission,
    load_transition,
)
from pyro_slam.slam import (
    SLAM,
    EmissionConfig,
    FilterConfig,
    HeadingConfig,
    OfflineConfig,
    ScanInsertionConfig,
    SLAMConfig,
    TrainingConfig,
    TransitionConfig,
    from_dict,
    presets,
    with_overrides,
)
from pyro_slam.slam.insertion import ScanInserter
from pyro_slam.slam.presets import REAL_LOG, odometry_sigma
from simulators import simulate_traversal

NOISE = (REAL_LOG.odometry_noise, REAL_LOG.heading_noise)  # the real-log noise fractions

PRESET_NAMES = [
    "paper",
    "raycast",
    "manhattan",
    "visual",
    "visual-raycast",
    "visual-manhattan",
    "real",
]
NO_RETURN = 81.91


def real_log(T: int = 20, B: int = 361, seed: int = 0) -> Traversal:
    """A metric laser log as the readers produce it: no walls, robot-frame odometry, a 180 deg
    scanner of ``B`` beams with some no-return readings (masked)."""
    rng = np.random.default_rng(seed)
    obs = rng.uniform(0.5, 8.0, (T, B))
    obs[:, ::17] = NO_RETURN
    controls = np.column_stack(
        [rng.uniform(0.1, 0.3, T - 1), np.zeros(T - 1), rng.normal(0.0, 0.05, T - 1)]
    )
    return Traversal(
        observations=obs,
        controls=controls,
        walls=np.zeros((0, 4)),
        beam_angles=np.linspace(-math.pi / 2, math.pi / 2, B),
        max_range=NO_RETURN,
        obs_mask=obs < NO_RETURN,
        timestamps=0.2 * np.arange(T),
        metadata={"control_model": "odometry_delta", "odometry_origin": [0.0, 0.0, 0.0]},
    )


@pytest.fixture(scope="module")
def maze_traversal():
    """The simulator's 20-beam, 0.53-range LiDAR (the shipped networks' sensor)."""
    return simulate_traversal("simple-small", steps=8, seed=0)


EMISSIONS = {
    "mlp": LidarEmission,
    "raycast": RayEmission,
    "endpoint": EndPointEmission,
    "image_mlp": ImageEmission,
    "ray_camera": RayImageEmission,
}


def test_presets_are_the_documented_ones():
    assert list(presets.PRESETS) == PRESET_NAMES
    assert presets.DEFAULT == "manhattan"
    for name, preset in presets.PRESETS.items():
        assert preset.name == name and preset.summary and isinstance(preset.config, SLAMConfig)
        assert presets.get(name) is preset
        assert name in presets.describe()


@pytest.mark.parametrize("name", PRESET_NAMES)
def test_every_preset_round_trips_through_a_plain_dict(name):
    cfg = presets.get(name).config
    d = cfg.to_dict()
    assert json.loads(json.dumps(d)) == d  # plain JSON data (tuples as lists)
    assert from_dict(d) == cfg
    assert from_dict(json.loads(json.dumps(d))) == cfg
    assert with_overrides(cfg, {}) == cfg


def test_adapted_real_preset_round_trips_through_a_plain_dict():
    cfg = presets.get("real").for_traversal(real_log())
    assert cfg != presets.get("real").config
    assert from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


def test_slamconfig_is_the_default_preset():
    """Every default is written once: ``SLAMConfig()`` is the default preset, its components'
    defaults included."""
    default = SLAMConfig()
    assert default == presets.get(presets.DEFAULT).config == presets.default_for(None)
    assert default.emission == EmissionConfig(insert=ScanInsertionConfig())
    assert default.heading == HeadingConfig() and default.filter == FilterConfig()
    assert default.transition == TransitionConfig() and default.training == TrainingConfig()


def test_presets_differ_from_each_other_as_documented():
    manhattan, raycast = presets.get("manhattan").config, presets.get("raycast").config
    assert manhattan.emission == EmissionConfig(
        "raycast", resolution=1 / 63, sigma=0.05, outlier_prob=0.1, insert=ScanInsertionConfig()
    )
    assert manhattan.transition == TransitionConfig("learned", scale=(3.0, 3.0, 1.0))
    assert manhattan.filter.proposal == "scan-match" and manhattan.training.every == 2
    assert manhattan.offline.estimate == "cache" and manhattan.heading == HeadingConfig(1e-3)
    assert raycast == replace(manhattan, heading=None)
    paper = presets.get("paper").config
    assert paper == replace(
        manhattan,
        emission=EmissionConfig("mlp", resolution=1 / 31, sigma=0.05, outlier_prob=0.0),
        filter=FilterConfig(proposal="transition"),
        training=TrainingConfig(every=1),
        heading=None,
    )
    visual = presets.get("visual").config
    assert visual.emission == EmissionConfig(
        "image_mlp", resolution=1 / 24, margin=0.0, sigma=0.1, outlier_prob=0.0
    )
    assert visual.emission.observation == "image" and paper.emission.observation == "lidar"
    assert visual.transition == TransitionConfig("kinematic", scale=(0.6, 0.6, 0.15))
    assert visual.filter == FilterConfig(proposal="transition") and visual.heading is None
    assert visual.training == TrainingConfig(particles=8, chunks=16, lr=0.05, every=1)
    assert visual.offline == OfflineConfig(rounds=2, svi_steps=400, estimate="forward")
    ray_camera = EmissionConfig(
        "ray_camera", resolution=1 / 63, margin=0.0, sigma=0.1, outlier_prob=0.0
    )
    assert presets.get("visual-raycast").config == replace(visual, emission=ray_camera)
    assert presets.get("visual-manhattan").config == replace(
        visual, emission=ray_camera, heading=HeadingConfig(1e-3)
    )
    real = presets.get("real").config
    assert real.emission == EmissionConfig(
        "endpoint",
        resolution=0.05,
        margin=0.0,
        sigma=0.075,
        insert=ScanInsertionConfig(kind="fusion", gap=0.5),
        ray_spacing=1.0,
        march_tolerance=1e-6,
    )
    assert real.transition.kind == "kinematic" and real.heading == HeadingConfig()
    assert real.filter.particles == 64 and real.filter.proposal == "transition"
    assert real.training.every == 0 and real.offline == OfflineConfig(0, estimate="forward")


def test_unknown_preset_lists_the_names():
    with pytest.raises(ValueError, match="unknown preset 'nope'") as info:
        presets.get("nope")
    for name in PRESET_NAMES:
        assert name in str(info.value)


def test_real_preset_reads_beam_stride_range_clip_and_odometry_noise_from_the_log():
    tr = real_log()
    real = presets.get("real")
    assert real.for_traversal(None) is real.config
    cfg = real.for_traversal(tr)
    assert cfg.beam_stride == 8  # 361 beams -> every 8th: 46 left
    assert tr.subsample_beams(cfg.beam_stride).num_beams == 46
    valid = tr.observations[tr.obs_mask]
    assert cfg.range_clip == round(float(np.percentile(valid, 99)), 2) and cfg.range_clip < 8
    assert cfg.transition.sigma == pytest.approx(odometry_sigma(tr.controls, *NOISE))
    assert all(isinstance(s, float) for s in cfg.transition.sigma)
    # the rest is the preset's
    assert replace(cfg, beam_stride=1, range_clip=None, transition=real.config.transition) == (
        real.config
    )
    noisy = presets.adapt_real_log(tr, real.config, target_beams=100, odometry_noise=0.2)
    assert noisy.beam_stride == 4
    assert noisy.transition.sigma == pytest.approx(odometry_sigma(tr.controls, 0.2, NOISE[1]))
    assert presets.adapt_real_log(tr, real.config, range_quantile=50).range_clip < cfg.range_clip


def test_default_for_picks_the_real_preset_for_real_logs_only(maze_traversal):
    log = real_log()
    assert presets.is_real_log(log) and not presets.is_real_log(maze_traversal)
    assert presets.default_for(log) == presets.get("real").for_traversal(log)
    default = presets.get(presets.DEFAULT).config
    assert presets.default_for(maze_traversal) == default
    assert presets.default_for(None) == default
    # a log with walls, or without robot-frame odometry, is not a real log
    walled = replace(log, walls=np.array([[0.0, 0.0, 1.0, 0.0]]))
    assert not presets.is_real_log(walled) and presets.default_for(walled) == default
    meta = {**log.metadata, "control_model": "rotate_forward"}
    rotate = replace(log, controls=log.controls[:, :2], metadata=meta)
    assert not presets.is_real_log(rotate) and presets.default_for(rotate) == default
    # SLAM without a configuration uses the default for its traversal
    assert SLAM(maze_traversal).cfg == default


@pytest.mark.parametrize("name", PRESET_NAMES)
def test_every_preset_builds_a_slam_run_for_its_sensor(name, maze_traversal):
    cfg = presets.get(name).config
    if name == "real":
        tr = real_log()
        cfg = presets.get(name).for_traversal(tr)
    elif cfg.emission.observation == "image":
        tr = simulate_traversal("simple-small", steps=4, seed=0, images=True)
    else:
        tr = maze_traversal
    slam = SLAM(tr, cfg)
    e = cfg.emission
    assert isinstance(slam.model.emission, EMISSIONS[e.kind])
    assert slam.model.sigma_emission == e.sigma and slam.cache.num_particles == 50
    grid = slam.model.grid
    assert grid.size[0] / (grid.cells[0] - 1) == pytest.approx(e.resolution, rel=0.05)
    assert (slam.inserter is not None) == (e.insert is not None)
    assert (slam.heading is not None) == (cfg.heading is not None)
    kind = {"learned": LearnedTransition, "kinematic": KinematicTransition}[cfg.transition.kind]
    assert isinstance(slam.model.transition, kind)
    assert slam.model.outlier_prob == e.outlier_prob
    proposal = type(slam.pf.proposal).__name__
    if cfg.filter.proposal == "scan-match":
        assert proposal == "ScanMatchProposal"
    else:  # the transition, conditioned on the heading factor where the model has one
        assert proposal == ("HeadingProposal" if cfg.heading else "TransitionProposal")
    assert slam.pf.proposal is slam.elbo.pf.proposal  # training proposes as filtering does
    assert slam.elbo.K == cfg.training.particles


def test_raycast_preset_writes_scans_and_matches_them(maze_traversal):
    slam = SLAM(maze_traversal, presets.get("raycast").config)
    assert type(slam.pf.proposal).__name__ == "ScanMatchProposal"
    assert isinstance(slam.inserter, ScanInserter) and not slam.inserter.inserted.any()
    assert slam.heading is None and not slam.model.learn_emission
    res = slam.run("online", progress=False)
    assert np.isfinite(res["mean"]).all() and slam.inserter.inserted.any()
    assert SLAM(maze_traversal, presets.get("manhattan").config).heading is not None


def test_paper_preset_loads_the_shipped_emission_frozen_and_the_learned_transition(
    maze_traversal,
):
    tr = maze_traversal
    slam = SLAM(tr, presets.get("paper").config)
    assert not slam.model.learn_emission and slam.inserter is None
    assert type(slam.pf.proposal).__name__ == "TransitionProposal"
    shipped = load_emission(PRETRAINED / EMISSION_FILE, tr).state_dict()
    weights = slam.model.emission.net.state_dict()
    assert weights.keys() == shipped.keys()
    for k in shipped:
        torch.testing.assert_close(weights[k], shipped[k], rtol=0, atol=0)
    transition = slam.model.transition
    assert isinstance(transition, LearnedTransition)
    sigma = load_transition(PRETRAINED / TRANSITION_FILE).sigma
    torch.testing.assert_close(transition.sigma, sigma * torch.tensor([3.0, 3.0, 1.0]))
    # SVI learns the map only: the emission stays as shipped
    slam.run("online", progress=False)
    with slam.scope():
        assert not any(n.startswith("emission") for n in pyro.get_param_store().keys())
    for k, v in slam.model.emission.net.state_dict().items():
        torch.testing.assert_close(v, shipped[k], rtol=0, atol=0)
    # asked to, SLAM learns the shipped emission too
    assert SLAM(tr, presets.get("paper").config, learn_emission=True).model.learn_emission
