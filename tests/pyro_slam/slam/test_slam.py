"""SLAM driver: a tiny online/offline run, determinism, resume-from-checkpoint, atomic saves."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pyro.distributions as dist
import pytest
import torch

import pyro_slam.data
from pyro_slam.inference import ChunkBatch, ParticleFilter, Particles
from pyro_slam.metrics import localisation_error
from pyro_slam.model import EmissionMLP, KinematicTransition, MapBelief
from pyro_slam.pretrained import EMISSION_FILE, PRETRAINED, load_emission
from pyro_slam.slam import (
    SLAM,
    ConfigError,
    EmissionConfig,
    FilterConfig,
    OfflineConfig,
    SLAMConfig,
    TrainingConfig,
    TransitionConfig,
    checkpoint,
    loop,
    path_integration,
    with_overrides,
)
from simulators import simulate_traversal
from simulators.world import LidarConfig

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


@pytest.fixture(scope="module")
def traversal():
    return simulate_traversal("simple-small", steps=STEPS, seed=0)


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


def test_offline_estimate_cache_filters_chunks_from_the_cached_particles(traversal, monkeypatch):
    """``offline.estimate="cache"`` (paper B-I): each chunk restarts from the cache, so a pose
    the cache holds far from the truth shows up at that chunk's steps and nowhere else."""
    L = CHUNK_LENGTH
    slam = make_slam(traversal, {"offline": {"rounds": 0, "estimate": "cache"}})
    run_ = loop.cache_pass
    shift = torch.tensor([0.03, 0.0, 0.0])

    def shifted_cache_pass(run, progress, desc):  # the cache at step 2L moved by 0.03 in x
        run.cache.z[2 * L] += shift
        before.append(run.cache.z.clone())
        return run_(run, progress, desc)

    before = []

    monkeypatch.setattr(loop, "cache_pass", shifted_cache_pass)
    res = slam.run("offline", progress=False)
    T = traversal.num_steps
    assert res["mean"].shape == res["std"].shape == (T, 3)
    err = localisation_error(res["mean"], traversal.poses)
    chunk = slice(2 * L, 3 * L)
    assert err[chunk].min() > 0.015 and np.delete(err, np.arange(2 * L, 3 * L)).max() < 0.01
    # chunk starts sit on the cache's means, which the pass leaves as they were
    starts = slam.cache.z[::L].mean(1).numpy()
    np.testing.assert_allclose(res["mean"][::L, :2], starts[:, :2], atol=5e-3)
    assert torch.equal(slam.cache.z, before[0])
    # with SVI rounds, only their chunks refresh the cache: no whole-traversal filter pass
    slam = make_slam(traversal, {"offline": {"estimate": "cache"}})
    monkeypatch.setattr(loop, "cache_pass", run_)
    monkeypatch.setattr(loop, "filter_pass", None)  # would raise if called
    res = slam.run("offline", progress=False)
    assert slam.state.round == 2 and localisation_error(res["mean"], traversal.poses).max() < 0.03
    msg = r"offline.estimate must be one of \['forward', 'cache'\], got 'smooth'"
    with pytest.raises(ConfigError, match=msg):
        config({"offline": {"estimate": "smooth"}})


def test_same_seed_same_result_other_seed_differs(traversal):
    # (runs share Pyro's global param store: a SLAM is built when the previous one is done)
    a = make_slam(traversal)
    ra = a.run("online", False)
    b = make_slam(traversal)
    assert_same_run(a, ra, b, b.run("online", False))
    c = make_slam(traversal, seed=1).run("online", False)
    assert not np.array_equal(c["mean"], ra["mean"])


def test_transition_scale_scales_a_copy_of_sigma_t(traversal):
    tran = KinematicTransition((5e-4, 5e-4, 8e-3))
    slam = make_slam(traversal, {"transition": {"scale": [3.0, 3.0, 0.2]}}, transition=tran)
    torch.testing.assert_close(slam.model.transition.sigma, torch.tensor([1.5e-3, 1.5e-3, 1.6e-3]))
    torch.testing.assert_close(tran.sigma, torch.tensor([5e-4, 5e-4, 8e-3]))  # not changed
    # the filter's particles spread by the scaled sigma: heading spread shrinks 5x
    z = torch.zeros(4000, 3)
    p = slam.pf.propagate(Particles(z, torch.zeros(4000)), torch.zeros(2))
    spread = p - slam.model.transition.mean(z, torch.zeros(1, 2))
    np.testing.assert_allclose(spread.std(0).numpy(), [1.5e-3, 1.5e-3, 1.6e-3], rtol=0.06)
    same = make_slam(traversal, transition=tran)
    assert same.model.transition is tran  # factors of 1: the transition as given
    for bad in [(1.0, 1.0), (1.0, 0.0, 1.0)]:
        with pytest.raises(ConfigError, match="transition.scale must be 3 positive numbers"):
            TransitionConfig(scale=bad)


def test_elbo_chunk_filter_weighs_with_the_models_emission(traversal):
    # the training objective's chunk filter weighs with the model's emission: its sigma_E and
    # its beam mixture, as the filter does
    slam = make_slam(traversal, {"emission": {"sigma": 0.02, "outlier_prob": 0.2}})
    t = 5
    true = torch.as_tensor(traversal.poses, dtype=slam.cache.z.dtype)
    slam.cache.z[:] = true.unsqueeze(1)  # every cached particle at the true pose
    slam.cache.filled[:] = True
    M = 0.5 * torch.randn(slam.model.grid.shape, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        ev = slam.elbo.chunk_log_evidence(M, ChunkBatch(torch.tensor([t]), 1))
        scan = slam.model.emission_mean(M, true[t])
        gauss = dist.Normal(scan, 0.02).log_prob(slam.obs[t]).exp()
        expected = torch.log(0.8 * gauss + 0.2 / slam.model.outlier_range).sum()
    assert slam.model.sigma_emission == 0.02 and slam.model.outlier_prob == 0.2
    torch.testing.assert_close(ev[0], expected, rtol=1e-3, atol=1e-2)


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
    flat = torch.full((64,), -math.log(64))
    x = slam.model.emission_mean(belief.loc, z[0]).detach()  # [B] a perfect match everywhere
    p, _ = pf._weigh(z, belief, x, None, flat, step=0)
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


def test_path_integration_reproduces_noiseless_motion():
    tr = simulate_traversal("simple-small", steps=40, seed=3, noise=0)
    assert tr.metadata["collisions"] == 0
    poses = path_integration(tr, KinematicTransition((1e-3, 1e-3, 1e-3)))
    assert poses.shape == (40, 3) and poses.dtype == np.float64
    np.testing.assert_allclose(poses[:, :2], tr.poses[:, :2], atol=1e-5)
    np.testing.assert_allclose(np.angle(np.exp(1j * (poses[:, 2] - tr.poses[:, 2]))), 0, atol=1e-5)
    assert (poses[:, 2] >= -np.pi).all() and (poses[:, 2] < np.pi).all()


# ---------------------------------------------------------------------------- resume
RAYCAST = {"emission": {"kind": "raycast", "insert": {}, "outlier_prob": 0.1}}


@pytest.mark.parametrize(
    "mode, crash_at, over",
    [
        ("online", 2, {}),  # online, after step 14
        ("offline", 2, {}),  # inside the online sweep that starts offline SLAM
        ("offline", 5, {}),  # between the two offline rounds
        ("offline", 7, {}),  # after the final checkpoint: nothing is redone
        ("offline", 5, {"transition": {"scale": [3.0, 3.0, 0.2]}}),  # scaled once, not on resume
        ("offline", 5, {"offline": {"estimate": "cache"}}),  # between rounds without filter passes
        ("online", 2, RAYCAST),  # the scan inserter's record of written cells is restored
        # the heading factor's frame guide, refined online, and the scan-matching proposal
        ("online", 2, {"heading": {"sigma": 1e-3}, "filter": {"proposal": "scan-match"}}),
    ],
)
def test_resume_reproduces_uninterrupted_run(traversal, tmp_path, mode, crash_at, over):
    ref = make_slam(traversal, over)
    r_ref = ref.run(mode, progress=False)

    ckpt = tmp_path / "ckpt.pt"
    first = make_slam(traversal, over, checkpoint=ckpt)
    crash_after_save(first, crash_at)
    with pytest.raises(Crash):
        first.run(mode, progress=False)
    del first

    resumed = make_slam(traversal, over, checkpoint=ckpt).resume(ckpt)
    assert 0 < resumed.state.t or resumed.state.round > 0 or resumed.state.phase != "online"
    if resumed.inserter is not None:
        assert resumed.inserter.inserted.any()
    r_res = resumed.run(mode, progress=False)
    assert_same_run(ref, r_ref, resumed, r_res)
    if ref.inserter is not None:
        assert torch.equal(ref.inserter.inserted, resumed.inserter.inserted)


def test_resume_after_sigkill(traversal, tmp_path):
    """A process killed with SIGKILL right after a checkpoint resumes to the same result."""
    ckpt = tmp_path / "ckpt.pt"
    script = textwrap.dedent(
        f"""
        import os, signal, torch
        torch.set_num_threads(1)
        from simulators import simulate_traversal
        from pyro_slam.model import EmissionMLP
        from pyro_slam.slam import SLAM, from_dict
        tr = simulate_traversal("simple-small", steps={STEPS}, seed=0)
        torch.manual_seed(0)
        emission = EmissionMLP({MAP_DIM}, max(tr.num_beams, 20), hidden={HIDDEN},
                               layers={LAYERS}, scale=tr.max_range)
        slam = SLAM(tr, from_dict({CONFIG.to_dict()!r}), emission=emission,
                    learn_emission=True, checkpoint={str(ckpt)!r},
                    checkpoint_every={CHECKPOINT_EVERY})
        save = slam.save
        def hooked(path):
            save(path)
            if slam.state.t == 14:
                os.kill(os.getpid(), signal.SIGKILL)
        slam.save = hooked
        slam.run("online", progress=False)
        """
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()[-2000:]
    ref = make_slam(traversal)
    r_ref = ref.run("online", False)
    resumed = make_slam(traversal, checkpoint=ckpt).resume(ckpt)
    assert resumed.state.t == 14 and resumed.state.phase == "online"
    assert_same_run(ref, r_ref, resumed, resumed.run("online", False))


# ------------------------------------------------------------------------ atomic saves
def test_checkpoint_writes_are_atomic(traversal, tmp_path, monkeypatch):
    ckpt = tmp_path / "ckpt.pt"
    slam = make_slam(traversal, checkpoint=ckpt, checkpoint_every=100)
    slam.run("online", progress=False)
    good = ckpt.read_bytes()
    assert checkpoint.read(ckpt)["state"]["t"] == STEPS

    def boom(*args, **kwargs):
        raise OSError("disk full")

    slam.state.t = 3  # something that would change the file
    # 1) serialisation fails before anything is written
    with monkeypatch.context() as m:
        m.setattr(torch, "save", boom)
        with pytest.raises(OSError, match="disk full"):
            slam.save(ckpt)
    # 2) the temporary file is half written when the disk fills up
    with monkeypatch.context() as m:
        m.setattr(os, "fsync", boom)
        with pytest.raises(OSError, match="disk full"):
            slam.save(ckpt)
    # 3) the rename fails
    with monkeypatch.context() as m:
        m.setattr(os, "replace", boom)
        with pytest.raises(OSError, match="disk full"):
            slam.save(ckpt)
    assert ckpt.read_bytes() == good
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pt"]  # no temp files left
    # the surviving checkpoint still resumes
    again = make_slam(traversal, checkpoint=ckpt).resume(ckpt)
    assert again.state.t == STEPS and again.state.phase == "done"
    slam.save(ckpt)  # and a working save replaces it
    assert checkpoint.read(ckpt)["state"]["t"] == 3


def test_checkpoint_every_must_be_a_positive_integer(traversal):
    for bad in (0, -3, 2.5):
        with pytest.raises(ValueError, match="checkpoint_every must be a positive integer"):
            make_slam(traversal, checkpoint_every=bad)
