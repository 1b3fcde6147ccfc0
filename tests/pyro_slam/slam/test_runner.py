"""The SLAM run (:mod:`pyro_slam.slam.runner`): a tiny online/offline run, determinism, the
emission it reads, its arguments."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from slam_runs import (
    CHUNK_LENGTH,
    STEPS,
    assert_same_run,
    make_slam,
    small_emission,
)

import pyro_slam.data
from pyro_slam.inference import ParticleFilter
from pyro_slam.metrics import localisation_error
from pyro_slam.model import MapBelief
from pyro_slam.pretrained import EMISSION_FILE, PRETRAINED, load_emission
from simulators import simulate_traversal
from simulators.world import LidarConfig


@pytest.fixture(scope="module")
def traversal():
    return simulate_traversal("simple-small", steps=STEPS, seed=0)


# ------------------------------------------------------------------------------ runs
def test_online_run_is_finite_and_tracks_the_path(traversal):
    tr = traversal
    slam = make_slam(tr)
    res = slam.run("online", progress=False)
    T = tr.num_steps
    assert res["mean"].shape == (T, 3) and res["std"].shape == (T, 3)
    assert res["map_loc"].shape == res["map_scale"].shape == slam.model.grid.shape
    # one SVI step per step from t = chunk_length - 1 on
    assert len(res["losses"]) == T - CHUNK_LENGTH + 1
    for key in ("mean", "std", "losses", "map_loc", "map_scale"):
        assert np.isfinite(res[key]).all(), key
    assert (res["std"] > 0).all() and (res["std"][:, :2] < 0.02).all()
    # starts at the known pose and stays well inside the corridor (width 1/12)
    err = localisation_error(res["mean"], tr.poses)
    assert err[0] < 5e-3 and err.max() < 0.04
    assert np.abs(np.angle(np.exp(1j * (res["mean"][:, 2] - tr.poses[:, 2])))).max() < 0.1
    # q(M) moved where the agent has been (scale sharpened somewhere) and nowhere else:
    # grid nodes more than 2 cells from every pose keep the prior exactly
    grid = slam.model.grid
    spacing = np.asarray(grid.size) / (np.asarray(grid.cells) - 1)
    nodes = np.stack(np.meshgrid(*(np.arange(c) for c in grid.cells), indexing="ij"), -1)
    pos = (tr.poses[:, :2] - np.asarray(grid.origin)) / spacing
    far = np.abs(nodes[:, :, None] - pos).max(-1).min(-1) > 2
    assert far.mean() > 0.5
    assert (res["map_scale"][far] == 1).all() and (res["map_loc"][far] == 0).all()
    assert res["map_scale"][~far].min() < 0.9 and np.abs(res["map_loc"][~far]).max() > 0.1


def test_offline_run_refines_the_online_sweep(traversal):
    slam = make_slam(traversal)
    res = slam.run("offline", progress=False)
    T = traversal.num_steps
    assert res["mean"].shape == (T, 3) and np.isfinite(res["mean"]).all()
    # online sweep, then 2 rounds of 5 SVI steps
    assert len(res["losses"]) == T - CHUNK_LENGTH + 1 + 2 * 5
    assert np.isfinite(res["losses"]).all()
    assert localisation_error(res["mean"], traversal.poses).max() < 0.03
    assert slam.state.phase == "done" and slam.state.round == 2
    # the online sweep it started from is kept apart: its own estimates, not the final pass's
    sweep = res["sweep_mean"]
    assert sweep.shape == (T, 3) and not np.array_equal(sweep, res["mean"])
    assert localisation_error(sweep, traversal.poses).max() < 0.03
    assert make_slam(traversal).run("online", False)["sweep_mean"].shape == (0, 3)


def test_same_seed_same_result_other_seed_differs(traversal):
    # (runs share Pyro's global param store: a SLAM is built when the previous one is done)
    a = make_slam(traversal)
    ra = a.run("online", False)
    b = make_slam(traversal)
    assert_same_run(a, ra, b, b.run("online", False))
    c = make_slam(traversal, seed=1).run("online", False)
    assert not np.array_equal(c["mean"], ra["mean"])


def test_the_marginal_emission_prefers_particles_whose_readings_the_map_knows(traversal):
    # a map whose mean is the same everywhere (every particle predicts the same scan, and the
    # observation is that scan) but whose scale falls from 1 (unmapped) to 0.2 (written often)
    # along x: the marginal emission prefers the particles in the often-written cells, where
    # the perfect match is a known reading's and not an unknown (uniform) one's
    slam = make_slam(traversal)
    w, h, D = slam.model.grid.shape
    scale = torch.linspace(1.0, 0.2, w).view(w, 1, 1).expand(w, h, D).contiguous()
    belief = MapBelief(torch.full((w, h, D), 0.3), scale)
    x0, x1, y0, y1 = slam.model.grid.extent()
    z = torch.zeros(64, 3)
    z[:, 0] = torch.linspace(x0 + 0.05, x1 - 0.05, 64)
    z[:, 1] = 0.5 * (y0 + y1)
    pf = ParticleFilter(slam.model)
    x = slam.model.emission_mean(belief.loc, z[0]).detach()  # [B] a perfect match everywhere
    p, _ = pf.init(z, belief, x, step=0)  # (uniform prior weights)
    logw = p.logw.detach()
    assert logw[-1] - logw[0] > 1.0 and (logw.diff() >= -1e-6).all()


def test_an_emission_with_a_finer_world_profile_reads_the_traversals_beams(traversal):
    emission = small_emission(traversal, n_world=40)
    slam = make_slam(traversal, emission=emission, learn_emission=True)
    assert slam.model.emission.n_world == 40
    assert slam.model.emission_mean(slam.map_belief().loc, torch.zeros(3)).shape == (
        traversal.num_beams,
    )
    # the shipped 20-direction emission does not fit a 40-beam LiDAR
    wide = simulate_traversal("simple-small", steps=4, seed=0, lidar=LidarConfig(n_beams=40))
    with pytest.raises(pyro_slam.data.DatasetError, match="40"):
        load_emission(PRETRAINED / EMISSION_FILE, wide)


def test_unknown_run_mode_is_rejected(traversal):
    with pytest.raises(ValueError, match="mode must be"):
        make_slam(traversal).run("sideways", progress=False)


# ---------------------------------------------------------------------------- resume


# ------------------------------------------------------------------------ atomic saves
def test_checkpoint_every_must_be_a_positive_integer(traversal):
    for bad in (0, -3, 2.5):
        with pytest.raises(ValueError, match="checkpoint_every must be a positive integer"):
            make_slam(traversal, checkpoint_every=bad)
