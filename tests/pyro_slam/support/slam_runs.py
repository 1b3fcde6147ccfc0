"""A tiny SLAM run the tests of the runner, the loop, checkpoints, the model builder and the
training objective share: the emission MLP learned from scratch with Gaussian noise, a kinematic
transition, the bootstrap filter and SVI at every step, on a 24-step traversal."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pyro_slam.model import EmissionMLP
from pyro_slam.slam import (
    SLAM,
    EmissionConfig,
    FilterConfig,
    OfflineConfig,
    SLAMConfig,
    TrainingConfig,
    TransitionConfig,
    with_overrides,
)

REPO = Path(__file__).resolve().parents[3]
STEPS = 24
CHUNK_LENGTH = 4
CHECKPOINT_EVERY = 7
# the small emission network the tests learn (the shipped one is 10 -> 4 x 256 -> 20)
MAP_DIM, HIDDEN, LAYERS = 4, 16, 2
# the emission MLP with Gaussian noise, a kinematic transition and the bootstrap filter, SVI at
# every step: the plainest SLAM the tests build on
CONFIG = SLAMConfig(
    emission=EmissionConfig("mlp", resolution=0.25 / 6, sigma=0.1, outlier_prob=0.0),
    transition=TransitionConfig("kinematic", scale=(1.0, 1.0, 1.0)),
    filter=FilterConfig(particles=32, proposal="transition"),
    training=TrainingConfig(particles=8, chunk_length=CHUNK_LENGTH, chunks=4, every=1),
    offline=OfflineConfig(rounds=2, svi_steps=5, estimate="forward"),
    heading=None,
)


def config(changes: dict | None = None) -> SLAMConfig:
    """The test configuration with nested ``changes`` (:func:`with_overrides`)."""
    return with_overrides(CONFIG, changes or {})


def small_emission(tr, seed: int = 0, n_world: int | None = None) -> EmissionMLP:
    """A small emission MLP for ``tr``'s LiDAR, its initial weights drawn from ``seed``."""
    torch.manual_seed(seed)
    n_world = max(tr.num_beams, 20) if n_world is None else n_world
    return EmissionMLP(MAP_DIM, n_world, hidden=HIDDEN, layers=LAYERS, scale=tr.max_range)


def make_slam(tr, changes: dict | None = None, *, seed: int = 0, **kw) -> SLAM:
    """A SLAM run of the test configuration that learns a small emission MLP (the ray-cast
    emission has nothing to learn and is built by SLAM)."""
    cfg = config(changes)
    kw.setdefault("checkpoint_every", CHECKPOINT_EVERY)
    if cfg.emission.kind == "mlp" and "emission" not in kw:
        kw["emission"] = small_emission(tr, seed)
        kw["learn_emission"] = True
    return SLAM(tr, cfg, seed=seed, **kw)


def emission_params(slam):
    return {k: v.detach().clone() for k, v in slam.model.emission.state_dict().items()}


def assert_same_run(a: SLAM, ra: dict, b: SLAM, rb: dict):
    for key in ("mean", "std", "losses", "map_loc", "map_scale", "sweep_mean"):
        np.testing.assert_array_equal(ra[key], rb[key], err_msg=key)
    pa, pb = emission_params(a), emission_params(b)
    for k in pa:
        torch.testing.assert_close(pa[k], pb[k], rtol=0, atol=0, msg=k)
    torch.testing.assert_close(a.particles.z, b.particles.z, rtol=0, atol=0)


class Crash(Exception):
    pass


def crash_after_save(slam: SLAM, n: int):
    """Make ``slam`` die right after its ``n``-th checkpoint (a kill between two steps)."""
    save, count = slam.save, [0]

    def hooked(path):
        save(path)
        count[0] += 1
        if count[0] == n:
            raise Crash

    slam.save = hooked


RAYCAST = {"emission": {"kind": "raycast", "insert": {}, "outlier_prob": 0.1}}
