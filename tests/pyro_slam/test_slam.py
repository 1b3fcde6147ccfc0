"""SLAM driver: a tiny online/offline run, determinism, resume-from-checkpoint, atomic saves."""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

import pyro_slam.data
import pyro_slam.filtering
from pyro_slam import resampling
from pyro_slam.metrics import localisation_error
from pyro_slam.slam import SLAM, SLAMConfig, path_integration
from pyro_slam.transitions import KinematicTransition
from simulators import simulate_traversal

REPO = Path(__file__).resolve().parents[2]
STEPS = 24
CFG = dict(
    map_resolution=0.25 / 6,
    map_dim=4,
    emission_hidden=16,
    emission_layers=2,
    filter_particles=32,
    train_particles=8,
    cache_particles=8,
    chunk_length=4,
    chunks_per_batch=4,
    checkpoint_every=7,
    offline_rounds=2,
    offline_svi_steps=5,
)


@pytest.fixture(scope="module")
def traversal():
    return simulate_traversal("simple-small", steps=STEPS, seed=0)


def config(**kw):
    return SLAMConfig(**{**CFG, **kw})


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
    slam = SLAM(tr, config())
    res = slam.run("online", progress=False)
    T = tr.num_steps
    assert res["mean"].shape == (T, 3) and res["std"].shape == (T, 3)
    assert res["map_loc"].shape == res["map_scale"].shape == slam.model.grid.shape
    # one SVI step per step from t = chunk_length - 1 on
    assert len(res["losses"]) == T - CFG["chunk_length"] + 1
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


def test_offline_run(traversal):
    slam = SLAM(traversal, config())
    res = slam.run("offline", progress=False)
    T = traversal.num_steps
    assert res["mean"].shape == (T, 3) and np.isfinite(res["mean"]).all()
    # online sweep, then 2 rounds of 5 SVI steps
    assert len(res["losses"]) == T - CFG["chunk_length"] + 1 + 2 * 5
    assert np.isfinite(res["losses"]).all()
    assert localisation_error(res["mean"], traversal.poses).max() < 0.03
    assert slam.state.phase == "done" and slam.state.round == 2
    # the online sweep it started from is kept apart: its own estimates, not the final pass's
    sweep = res["sweep_mean"]
    assert sweep.shape == (T, 3) and not np.array_equal(sweep, res["mean"])
    assert localisation_error(sweep, traversal.poses).max() < 0.03
    assert SLAM(traversal, config()).run("online", False)["sweep_mean"].shape == (0, 3)


def test_offline_estimate_cache_filters_chunks_from_the_cached_particles(traversal):
    """``offline_estimate="cache"`` (paper B-I): each chunk restarts from the cache, so a pose
    the cache holds far from the truth shows up at that chunk's steps and nowhere else."""
    L = CFG["chunk_length"]
    slam = SLAM(traversal, config(offline_rounds=0, offline_estimate="cache"))
    run_ = slam._cache_pass
    shift = torch.tensor([0.03, 0.0, 0.0])

    def shifted_cache_pass(progress, desc):  # the cache at step 2L moved by 0.03 in x
        slam.cache.z[2 * L] += shift
        before.append(slam.cache.z.clone())
        return run_(progress, desc)

    before = []

    slam._cache_pass = shifted_cache_pass
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
    slam = SLAM(traversal, config(offline_estimate="cache"))
    slam._filter_pass = None  # would raise if called
    res = slam.run("offline", progress=False)
    assert slam.state.round == 2 and localisation_error(res["mean"], traversal.poses).max() < 0.03
    with pytest.raises(ValueError, match="offline_estimate must be 'forward' or 'cache'"):
        SLAM(traversal, config(offline_estimate="smooth"))


def test_heading_jump_gives_a_fraction_of_the_particles_a_wide_heading_noise(traversal):
    slam = SLAM(traversal, config(heading_jump=(0.25, 0.3), filter_particles=4000))
    assert slam._heading_jumps(None, 0) is not None
    sigma = slam._heading_jumps(None, 0)  # [K, 3]
    base = slam.model.transition.sigma
    jumped = sigma[:, 2] == 0.3
    assert sigma.shape == (4000, 3) and abs(float(jumped.float().mean()) - 0.25) < 0.03
    torch.testing.assert_close(sigma[~jumped], base.expand(int((~jumped).sum()), 3))
    assert (sigma[jumped, :2] == base[:2]).all()
    assert SLAM(traversal, config())._heading_jumps(None, 0) is None  # off by default
    for bad in ((1.5, 0.3), (0.1, 0.0), (0.1,)):
        with pytest.raises(ValueError, match="heading_jump must be"):
            SLAM(traversal, config(heading_jump=bad))


def test_heading_jump_age_allows_jumps_only_on_cells_mapped_long_enough_ago(traversal):
    slam = SLAM(traversal, config(heading_jump=(1.0, 0.3), heading_jump_age=100))
    with torch.no_grad():
        slam._filter_step(0, slam.map_mean(0))
    cell = slam._mean_cell()
    assert slam._heading_jumps(None, 10**6) is None  # an unmapped cell: no revisit
    slam.first_seen[cell] = 50.0
    assert slam._heading_jumps(None, 149) is None  # mapped 99 steps ago: still the frontier
    sigma = slam._heading_jumps(None, 150)  # [K, 3], a revisit: every particle jumps (p = 1)
    assert sigma.shape == (slam.cfg.filter_particles, 3) and (sigma[:, 2] == 0.3).all()
    slam.first_seen.fill_(float("inf"))
    slam.first_seen[cell[0] + 2 :, :] = 0.0  # old cells elsewhere do not count
    assert slam._heading_jumps(None, 10**6) is None
    with pytest.raises(ValueError, match="heading_jump_age must be >= 0"):
        SLAM(traversal, config(heading_jump_age=-1))


def test_same_seed_same_result_other_seed_differs(traversal):
    # (runs share Pyro's global param store: a SLAM is built when the previous one is done)
    a = SLAM(traversal, config())
    ra = a.run("online", False)
    b = SLAM(traversal, config())
    assert_same_run(a, ra, b, b.run("online", False))
    c = SLAM(traversal, config(seed=1)).run("online", False)
    assert not np.array_equal(c["mean"], ra["mean"])


def test_pin_cache_learns_the_map_at_the_given_poses(traversal):
    slam = SLAM(traversal, config())
    shifted = traversal.poses + np.array([0.05, 0.0, 0.0])
    slam.pin_cache(shifted, noise=1e-3)
    res = slam.run("offline", progress=False)
    # every store (online sweep, chunk refreshes, offline passes) kept the pinned poses
    dev = slam.cache.z.numpy() - shifted[:, None].astype(np.float32)
    assert slam.cache.filled.all() and np.abs(dev).max() < 6e-3 and dev.std() > 5e-4
    # the filter still ran on its own: its estimates are not the pinned poses
    assert np.abs(res["mean"][:, 0] - shifted[:, 0]).mean() > 1e-3
    T = traversal.num_steps
    msg = re.escape(f"pin_cache needs poses of shape ({T}, 3), got ({T - 1}, 3)")
    with pytest.raises(ValueError, match=msg):
        slam.pin_cache(shifted[:-1])


@pytest.mark.parametrize("weighting", ["marginal", "tempered", "predictive"])
def test_revisit_gating_before_any_revisit_is_path_integration(traversal, weighting):
    # every cell is younger than the gap: the map may not weigh particles, so the filter is a
    # transition-driven cloud (finite, near-flat weights -- no -inf from a zero trust)
    slam = SLAM(traversal, config(revisit_gap=10_000, weighting=weighting))
    res = slam.run("online", progress=False)
    assert np.isfinite(res["mean"]).all() and np.isfinite(res["losses"]).all()
    K = slam.particles.num_particles
    if weighting != "predictive":  # "predictive" scores unusable charts by the prior predictive
        assert resampling.ess(slam.particles.logw) > 0.9 * K


def test_revisit_radius_trusts_the_map_by_distance_to_old_positions(traversal):
    slam = SLAM(traversal, config(revisit_gap=5, revisit_radius=0.02))
    res = slam.run("online", progress=False)
    assert np.isfinite(res["mean"]).all()
    np.testing.assert_allclose(slam.track.numpy(), res["mean"][:, :2], atol=1e-6)
    here = slam.particles.mean()[:2]
    # the cloud sits on a position estimated >= 5 steps before t: full trust
    slam.track[:] = here + torch.tensor([3.0, 0.0])
    slam.track[10] = here
    assert slam.map_mean(16).trust == pytest.approx(1.0)
    assert slam.map_mean(15).trust == pytest.approx(0.01)  # step 10 is too recent (gap 5)
    slam.track[10] = here + torch.tensor([0.0, 0.02])  # one radius away
    assert slam.map_mean(16).trust == pytest.approx(math.exp(-0.5), rel=1e-4)
    assert slam.map_mean(2).trust == 0.01  # nothing old enough yet: path integration
    assert slam.map_mean().trust == 1.0  # offline passes: the whole map
    with pytest.raises(ValueError, match="revisit_radius must be > 0, got 0.0"):
        SLAM(traversal, config(revisit_radius=0.0))


def test_transition_scale_scales_a_copy_of_sigma_t(traversal):
    tran = KinematicTransition((5e-4, 5e-4, 8e-3))
    slam = SLAM(traversal, config(transition_scale=(3.0, 3.0, 0.2)), transition=tran)
    torch.testing.assert_close(slam.model.transition.sigma, torch.tensor([1.5e-3, 1.5e-3, 1.6e-3]))
    torch.testing.assert_close(tran.sigma, torch.tensor([5e-4, 5e-4, 8e-3]))  # not changed
    # the filter's particles spread by the scaled sigma: heading spread shrinks 5x
    z = torch.zeros(4000, 3)
    p = slam.pf.propagate(pyro_slam.filtering.Particles(z, torch.zeros(4000)), torch.zeros(2))
    spread = p - slam.model.transition.mean(z, torch.zeros(1, 2))
    np.testing.assert_allclose(spread.std(0).numpy(), [1.5e-3, 1.5e-3, 1.6e-3], rtol=0.06)
    same = SLAM(traversal, config(), transition=tran)
    assert same.model.transition is tran  # factors of 1: the transition as given
    for bad in [(1.0, 1.0), (1.0, 0.0, 1.0)]:
        with pytest.raises(ValueError, match="transition_scale must be 3 positive factors"):
            SLAM(traversal, config(transition_scale=bad))


def test_newest_svi_steps_train_on_the_newest_chunk_only(traversal):
    T, L = traversal.num_steps, CFG["chunk_length"]
    slam = SLAM(traversal, config(newest_svi_steps=2))
    batches = []
    step = slam.svi.step
    slam.svi.step = lambda batch: batches.append(batch.starts.tolist()) or step(batch)
    res = slam.run("online", progress=False)
    assert len(res["losses"]) == T - L + 1  # the regular steps are unchanged
    assert len(batches) == 3 * (T - L + 1)
    # each time step t: one regular batch (newest chunk first), then two of the newest alone
    assert batches[1] == batches[2] == [0] and batches[-1] == [T - L]
    assert len(batches[-3]) == CFG["chunks_per_batch"] and batches[-3][0] == T - L
    with pytest.raises(ValueError, match="newest_svi_steps must be >= 0, got -1"):
        SLAM(traversal, config(newest_svi_steps=-1))


def test_write_lag_learns_the_map_only_from_old_enough_steps(traversal):
    T, L = traversal.num_steps, CFG["chunk_length"]
    slam = SLAM(traversal, config(write_lag=5))
    seen = []
    step = slam._svi_step
    slam._svi_step = lambda lo, hi, newest: seen.append((hi, newest)) or step(lo, hi, newest)
    res = slam.run("online", progress=False)
    # one SVI step per time step t >= write_lag + L - 1, on chunks ending <= t - write_lag
    assert len(res["losses"]) == T - 5 - L + 1
    assert seen[0] == (0, 0) and seen[-1] == (T - 1 - 5 - L + 1,) * 2
    prior = SLAM(traversal, config(write_lag=T)).run("online", progress=False)
    assert len(prior["losses"]) == 0 and (prior["map_loc"] == 0).all()
    with pytest.raises(ValueError, match="write_lag must be >= 0, got -1"):
        SLAM(traversal, config(write_lag=-1))


def test_cloud_wide_trust_flattens_the_weights_of_every_particle(traversal):
    from pyro_slam.filtering import MapBelief

    slam = SLAM(traversal, config())
    slam.run("online", progress=False)
    b, p = slam.map_mean(), slam.particles
    flat = torch.zeros_like(p.logw)
    spread = {}
    for trust in (1.0, 0.01):
        belief = MapBelief(b.loc, b.scale, None, trust)
        w, _ = slam.pf._weigh(p.z, belief, slam.obs[-1], None, flat, step=0)
        spread[trust] = float(w.logw.detach().max() - w.logw.detach().min())
    assert spread[1.0] > 0.5 and spread[0.01] < 0.1 * spread[1.0]


@pytest.mark.parametrize("train_sigma", [None, 0.1])
def test_elbo_chunk_filter_sigma(traversal, train_sigma):
    # the ELBO's chunk filter weighs with filter_sigma unless train_sigma overrides it (e.g.
    # with the model's own sigma_E = 0.1)
    from pyro_slam.filtering import ChunkBatch

    slam = SLAM(traversal, config(filter_sigma=0.02, train_sigma=train_sigma))
    t = 5
    true = torch.as_tensor(traversal.poses, dtype=slam.cache.z.dtype)
    slam.cache.z[:] = true.unsqueeze(1)  # every cached particle at the true pose
    slam.cache.filled[:] = True
    M = 0.5 * torch.randn(slam.model.grid.shape, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        ev = slam.elbo.chunk_log_evidence(M, ChunkBatch(torch.tensor([t]), 1))
        scan = slam.model.emission_mean(M, true[t])
        sigma = 0.02 if train_sigma is None else train_sigma
        expected = slam.model.emission_log_prob(slam.obs[t], scan, sigma=sigma)
    assert slam.pf.sigma_emission == 0.02
    torch.testing.assert_close(ev[0], expected, rtol=1e-3, atol=1e-2)


def test_reprojection_writes_the_map_around_the_chunk_poses(traversal):
    # reproject_radius > 0: the loss also scores the scans reprojected within the radius, so
    # map cells the chunk filter never reads get gradients; the chunk evidence is unchanged
    from pyro_slam.filtering import ChunkBatch

    true = torch.as_tensor(traversal.poses)
    grads, evidence = {}, {}
    for radius in (0.0, 0.1):
        slam = SLAM(traversal, config(reproject_radius=radius, reproject_samples=16))
        slam.cache.z[:] = true.to(slam.cache.z.dtype).unsqueeze(1)  # cached particles at truth
        slam.cache.filled[:] = True
        slam.model.transition.sigma = torch.full((3,), 1e-6)  # the chunk stays on the truth
        loc, _ = slam.guide.params()
        loss = slam.elbo.differentiable_loss(
            slam.model.map_model, slam.guide, ChunkBatch(torch.tensor([0, 10]), 4)
        )
        (g,) = torch.autograd.grad(loss, loc)
        kl_only = loc.detach()  # the KL's gradient is d/dloc KL / T = loc / T
        grads[radius] = (g - kl_only / slam.elbo.num_steps_seen).abs().sum(-1)  # [w, h]
        evidence[radius] = slam.elbo.last_log_evidence
    torch.testing.assert_close(evidence[0.0], evidence[0.1])
    read = grads[0.0] > 0
    assert read.sum() >= 4  # the cells around the chunk poses
    assert (grads[0.1][read] > 0).all()
    assert ((grads[0.1] > 0) & ~read).sum() >= 4  # cells only the reprojection writes
    with pytest.raises(ValueError, match="reproject_samples >= 1"):
        SLAM(traversal, config(reproject_radius=0.1, reproject_samples=0))


@pytest.mark.parametrize("weighting", ["marginal", "shared"])
def test_shared_trust_removes_the_pull_towards_often_written_cells(traversal, weighting):
    # a map whose mean is the same everywhere (every particle predicts the same scan, and the
    # observation is that scan) but whose scale falls from 1 (unmapped) to 0.2 (written often)
    # along x: per-particle trust ("marginal") prefers the particles in the often-written cells
    # through the normaliser -B log sigma alone; one trust for the cloud ("shared") does not
    from pyro_slam.filtering import MapBelief, ParticleFilter

    slam = SLAM(traversal, config())
    w, h, D = slam.model.grid.shape
    scale = torch.linspace(1.0, 0.2, w).view(w, 1, 1).expand(w, h, D).contiguous()
    belief = MapBelief(torch.full((w, h, D), 0.3), scale)
    x0, x1, y0, y1 = slam.model.grid.extent()
    z = torch.zeros(64, 3)
    z[:, 0] = torch.linspace(x0 + 0.05, x1 - 0.05, 64)
    z[:, 1] = 0.5 * (y0 + y1)
    pf = ParticleFilter(slam.model, sigma_emission=0.05, weighting=weighting)
    flat = torch.full((64,), -math.log(64))
    x = slam.model.emission_mean(belief.loc, z[0]).detach()  # [B] a perfect match everywhere
    p, _ = pf._weigh(z, belief, x, None, flat, step=0)
    logw = p.logw.detach()
    if weighting == "shared":
        torch.testing.assert_close(logw, flat)
    else:
        assert logw[-1] - logw[0] > 1.0 and (logw.diff() >= -1e-6).all()


def test_n_world_sets_the_emission_profile_resolution(traversal):
    from pyro_slam.cli import load_emission

    slam = SLAM(traversal, config(n_world=40))
    assert slam.model.emission.n_world == 40
    assert slam.model.emission_mean(slam.guide.params()[0].detach(), torch.zeros(3)).shape == (
        traversal.num_beams,
    )
    # a shipped 20-direction emission does not fit a 40-direction config
    with pytest.raises(pyro_slam.data.DatasetError, match="40"):
        shipped = REPO / "pyro_slam/pretrained/emission_lidar20.pt"
        load_emission(shipped, traversal, config(n_world=40))


def test_bad_mode(traversal):
    with pytest.raises(ValueError, match="mode must be"):
        SLAM(traversal, config()).run("sideways", progress=False)


def test_path_integration_reproduces_noiseless_motion():
    tr = simulate_traversal("simple-small", steps=40, seed=3, noise=0)
    assert tr.metadata["collisions"] == 0
    poses = path_integration(tr, KinematicTransition((1e-3, 1e-3, 1e-3)))
    assert poses.shape == (40, 3) and poses.dtype == np.float64
    np.testing.assert_allclose(poses[:, :2], tr.poses[:, :2], atol=1e-5)
    np.testing.assert_allclose(np.angle(np.exp(1j * (poses[:, 2] - tr.poses[:, 2]))), 0, atol=1e-5)
    assert (poses[:, 2] >= -np.pi).all() and (poses[:, 2] < np.pi).all()


# ---------------------------------------------------------------------------- resume
@pytest.mark.parametrize(
    "mode, crash_at, over",
    [
        ("online", 2, {}),  # online, after step 14
        ("offline", 2, {}),  # inside the online sweep that starts offline SLAM
        ("offline", 5, {}),  # between the two offline rounds
        ("offline", 7, {}),  # after the final checkpoint: nothing is redone
        ("online", 2, {"revisit_gap": 3, "revisit_radius": 0.01}),  # the track is restored
        ("offline", 5, {"transition_scale": (3.0, 3.0, 0.2)}),  # scaled once, not on resume
        ("offline", 5, {"offline_estimate": "cache"}),  # between rounds without filter passes
    ],
)
def test_resume_reproduces_uninterrupted_run(traversal, tmp_path, mode, crash_at, over):
    ref = SLAM(traversal, config(**over))
    r_ref = ref.run(mode, progress=False)

    ckpt = tmp_path / "ckpt.pt"
    first = SLAM(traversal, config(**over), checkpoint=ckpt)
    crash_after_save(first, crash_at)
    with pytest.raises(Crash):
        first.run(mode, progress=False)
    del first

    resumed = SLAM(traversal, config(**over), checkpoint=ckpt).resume(ckpt)
    assert 0 < resumed.state.t or resumed.state.round > 0 or resumed.state.phase != "online"
    r_res = resumed.run(mode, progress=False)
    assert_same_run(ref, r_ref, resumed, r_res)


def test_resume_after_sigkill(traversal, tmp_path):
    """A process killed with SIGKILL right after a checkpoint resumes to the same result."""
    ckpt = tmp_path / "ckpt.pt"
    script = textwrap.dedent(
        f"""
        import os, signal, torch
        torch.set_num_threads(1)
        from simulators import simulate_traversal
        from pyro_slam.slam import SLAM, SLAMConfig
        tr = simulate_traversal("simple-small", steps={STEPS}, seed=0)
        slam = SLAM(tr, SLAMConfig(**{CFG!r}), checkpoint={str(ckpt)!r})
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
    ref = SLAM(traversal, config())
    r_ref = ref.run("online", False)
    resumed = SLAM(traversal, config(), checkpoint=ckpt).resume(ckpt)
    assert resumed.state.t == 14 and resumed.state.phase == "online"
    assert_same_run(ref, r_ref, resumed, resumed.run("online", False))


# ------------------------------------------------------------------------ atomic saves
def test_checkpoint_writes_are_atomic(traversal, tmp_path, monkeypatch):
    ckpt = tmp_path / "ckpt.pt"
    slam = SLAM(traversal, config(checkpoint_every=100), checkpoint=ckpt)
    slam.run("online", progress=False)
    good = ckpt.read_bytes()
    assert torch.load(ckpt, weights_only=False)["state"]["t"] == STEPS

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
        m.setattr(pyro_slam.data.os, "fsync", boom)
        with pytest.raises(OSError, match="disk full"):
            slam.save(ckpt)
    # 3) the rename fails
    with monkeypatch.context() as m:
        m.setattr(pyro_slam.data.os, "replace", boom)
        with pytest.raises(OSError, match="disk full"):
            slam.save(ckpt)
    assert ckpt.read_bytes() == good
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pt"]  # no temp files left
    # the surviving checkpoint still resumes
    again = SLAM(traversal, config(), checkpoint=ckpt).resume(ckpt)
    assert again.state.t == STEPS and again.state.phase == "done"
    slam.save(ckpt)  # and a working save replaces it
    assert torch.load(ckpt, weights_only=False)["state"]["t"] == 3


def test_transition_scale_trusted_loosens_sigma_t_with_the_clouds_trust(traversal):
    # sigma_T moves from the transition_scale one (unmapped map: trust 0.01) to the
    # transition_scale_trusted one (map with scale 0: trust 1), and the filter spreads by it
    from pyro_slam.filtering import MapBelief, Particles

    lo_scale, hi_scale = (1.0, 1.0, 0.2), (1.0, 1.0, 1.0)
    slam = SLAM(traversal, config(transition_scale=lo_scale, transition_scale_trusted=hi_scale))
    base = SLAM(traversal, config(transition_scale=lo_scale))
    assert base._transition_sigma(base.map_mean()) is None  # off by default
    lo = slam.model.transition.sigma.clone()
    w, h, D = slam.model.grid.shape
    K = 4000
    z = torch.tensor(traversal.poses[0], dtype=torch.float32).expand(K, 3).clone()
    slam.particles = Particles(z, torch.full((K,), -math.log(K)))
    unmapped = MapBelief(torch.zeros(w, h, D), torch.ones(w, h, D))
    mapped = MapBelief(torch.zeros(w, h, D), torch.zeros(w, h, D))
    hi = lo / torch.tensor(lo_scale) * torch.tensor(hi_scale)
    torch.testing.assert_close(slam._transition_sigma(unmapped), lo + 0.01 * (hi - lo))
    torch.testing.assert_close(slam._transition_sigma(mapped), hi)
    assert hi[2] == pytest.approx(5 * lo[2]) and hi[0] == pytest.approx(lo[0])
    u = slam.ctl[0]
    for M, sigma in ((unmapped, lo), (mapped, hi)):
        spread = slam.pf.propagate(slam.particles, u, slam._transition_sigma(M)).std(0)
        torch.testing.assert_close(spread, sigma, rtol=0.08, atol=0)
    res = slam.run("online", progress=False)  # runs end to end with it
    assert np.isfinite(res["mean"]).all()
    # the offline filter passes (a finished map, no frontier) keep the model's sigma_T
    from pyro_slam.slam import SLAMState

    slam.state = SLAMState("offline", phase="online-init")
    torch.testing.assert_close(slam._transition_sigma(mapped), hi)
    slam.state = SLAMState("offline", phase="offline-filter")
    assert slam._transition_sigma(mapped) is None
    slam.state = SLAMState("offline", phase="offline-final")
    assert slam._transition_sigma(mapped) is None
    # ... unless trusted_passes widens it: "final" to the last pass, "all" to every pass
    for passes, loose in (
        ("final", ("offline-final",)),
        ("all", ("offline-final", "offline-filter")),
    ):
        slam.cfg.trusted_passes = passes
        for phase in ("offline-filter", "offline-final"):
            slam.state = SLAMState("offline", phase=phase)
            sigma = slam._transition_sigma(mapped)
            if phase in loose:
                torch.testing.assert_close(sigma, hi)
            else:
                assert sigma is None
    with pytest.raises(ValueError, match="transition_scale_trusted must be 3 positive"):
        SLAM(traversal, config(transition_scale_trusted=(1.0, 0.0, 1.0)))
    with pytest.raises(ValueError, match="trusted_passes must be"):
        SLAM(traversal, config(trusted_passes="sometimes"))
