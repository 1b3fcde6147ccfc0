"""Fast tests of PF-net (pyro_slam.pfnet) and its baselines, on a numpy stand-in world (plus
one check of the adapter to the pymunk simulator)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from pfnet_standin import StandInWorld, make_maze
from scipy import stats

from pyro_slam import pfnet
from pyro_slam.geometry import odometry_delta, wrap_angle
from pyro_slam.inference import resampling
from pyro_slam.pfnet import baselines as bl
from pyro_slam.pfnet import data as pfnet_data


@pytest.fixture(autouse=True)
def _threads():
    torch.set_num_threads(1)


@pytest.fixture(scope="module")
def data():
    mazes = [make_maze(s) for s in range(3)]
    return pfnet_data.generate(mazes, lambda m, s: StandInWorld(m), 2, seed=0, T=6)


# ---------------------------------------------------------------------------- soft resampling


@pytest.mark.parametrize("alpha", [1.0, 0.5])
def test_soft_resampling_ancestor_distribution(alpha):
    """Ancestors follow q = alpha w + (1 - alpha)/K; alpha = 1 is standard resampling."""
    w = torch.tensor([0.5, 0.25, 0.15, 0.07, 0.03])
    K = len(w)
    logw = torch.log(w).expand(4000, K)
    g = torch.Generator().manual_seed(0)
    idx, new = resampling.soft(logw, alpha, g)
    counts = torch.bincount(idx.flatten(), minlength=K).double()
    q = alpha * w + (1 - alpha) / K
    assert stats.chisquare(counts.numpy(), (q * counts.sum()).double().numpy()).pvalue > 1e-3
    if alpha == 1.0:  # same frequencies as plain multinomial resampling, uniform new weights
        ref = torch.bincount(resampling.multinomial(logw, g).flatten(), minlength=K).double()
        table = torch.stack([counts, ref]).numpy()
        assert stats.chi2_contingency(table).pvalue > 1e-3
        torch.testing.assert_close(new, torch.full_like(new, -math.log(K)))
    else:  # importance weights w / q of the drawn ancestors
        expect = resampling.normalize(torch.gather(torch.log(w / q).expand(4000, K), 1, idx))
        torch.testing.assert_close(new, expect)


def test_soft_resampling_gradient_path():
    """alpha < 1: non-zero gradient of the new weights wrt the old; alpha = 1: exactly zero."""
    for alpha, nonzero in ((0.5, True), (1.0, False)):
        logw = torch.randn(3, 8, generator=torch.Generator().manual_seed(1)).requires_grad_()
        x = torch.linspace(0, 1, 8).expand(3, 8)
        idx, new = resampling.soft(logw, alpha, torch.Generator().manual_seed(2))
        est = (torch.exp(new) * torch.gather(x, 1, idx)).sum()
        (grad,) = torch.autograd.grad(est, logw)
        assert (grad.abs().sum() > 1e-6) == nonzero


def test_pfnet_gradient_reaches_observation_model_through_resampling(data):
    net = pfnet.PFNet(pfnet.ObservationModel(data.obs_model_config("lidar")), resample="always")
    b = data.with_sensor("lidar").batch(range(4))
    out = net(b, K=10, generator=torch.Generator().manual_seed(0))
    pfnet.pose_loss(out["estimates"], b["poses"]).backward()
    g = net.obs_model.head[-1].weight.grad
    assert g is not None and g.abs().sum() > 0
    assert net.transition.raw_sigma.grad.abs().sum() > 0


# ---------------------------------------------------------------------------- filter


class OraclePF(pfnet.PFNet):
    """PF-net with a perfect observation model: Gaussian in the distance to the true pose."""

    def log_likelihood(self, batch, obs_feat, particles, t):
        d = particles - batch["poses"][:, t, None]
        d = torch.cat([d[..., :2] / 0.01, wrap_angle(d[..., 2:]) / 0.1], -1)
        return -0.5 * (d**2).sum(-1)


def test_filter_with_perfect_observation_model_converges(data):
    ds = data.with_sensor("lidar")
    oracle = OraclePF(bl._Identity(), pfnet.GaussianTransition(learn=False), resample="ess")
    err = pfnet.evaluate(oracle, ds, K=300)
    prop = pfnet.evaluate(bl.propagated_uncertainty(), ds, K=300)
    out = oracle(ds.batch(range(len(ds))), K=300, generator=torch.Generator().manual_seed(0))
    final = pfnet.rmse_cm(out["estimates"][:, -1:], torch.as_tensor(ds.poses[:, -1:]))
    assert prop > 20.0
    assert err < prop / 3
    assert final < 5.0


@pytest.mark.parametrize("sensor", ["lidar", "depth"])
@pytest.mark.parametrize("resample", ["never", "always", "ess"])
def test_pfnet_shapes(data, sensor, resample):
    net = pfnet.PFNet(pfnet.ObservationModel(data.obs_model_config(sensor)), resample=resample)
    b = data.with_sensor(sensor).batch(range(5))
    out = net(b, K=7, generator=torch.Generator().manual_seed(0))
    assert out["estimates"].shape == (5, 6, 3)
    assert out["particles"].shape == (5, 7, 3)
    assert out["log_weights"].shape == (5, 7)
    torch.testing.assert_close(torch.logsumexp(out["log_weights"], -1), torch.zeros(5))


def test_ess_mode_resamples_only_degenerate_rows():
    net = pfnet.PFNet(None, resample="ess", alpha=1.0, ess_threshold=0.5)
    p = torch.randn(2, 6, 3)
    lw = torch.stack([torch.zeros(6), torch.tensor([0.0, -50, -50, -50, -50, -50])])
    new_p, new_lw = net.resample_step(p, resampling.normalize(lw), torch.Generator())
    torch.testing.assert_close(new_p[0], p[0])  # uniform weights: ESS = K, untouched
    torch.testing.assert_close(new_p[1], p[1, :1].expand(6, 3))  # all mass on particle 0
    torch.testing.assert_close(new_lw[1], torch.full((6,), -math.log(6)))


def test_transition_mean_and_circular_estimate():
    tr = pfnet.GaussianTransition(sigma_t=1e-8, sigma_r=1e-8, learn=False)
    p = torch.tensor([[[0.5, 0.5, 3.1], [0.2, 0.3, -1.0]]])
    u = torch.tensor([[0.1, 0.0, 0.2]])
    torch.testing.assert_close(tr(p, u), odometry_delta(p, u.expand(1, 2, 3)), atol=1e-6, rtol=0)
    parts = torch.tensor([[[0.0, 0.0, math.pi - 0.1], [1.0, 2.0, -math.pi + 0.1]]])
    est = pfnet.weighted_pose_mean(parts, torch.zeros(1, 2))
    torch.testing.assert_close(est[0, :2], torch.tensor([0.5, 1.0]))
    assert abs(abs(float(est[0, 2])) - math.pi) < 1e-5  # not 0


# ---------------------------------------------------------------------------- observation model


def test_rasterize_floor_map():
    grid = pfnet.rasterize_floor_map(np.array([[0.0, 0.5, 1.0, 0.5]]), 1.0, 10, thickness=1.0)
    rows = grid.sum(1)
    assert set(np.flatnonzero(rows > 0)) <= {4, 5}  # wall at y = 0.5 between rows 4 and 5
    assert grid[:, 0].sum() > 0 and grid[0].sum() == 0


@pytest.mark.parametrize("heading", [0.0, math.pi / 2, -2.3])
def test_map_crop_of_single_marked_cell(heading):
    """A cell 0.1 ahead and 0.05 to the left of the pose lands at the right crop pixel."""
    R = 100
    pose = torch.tensor([0.5, 0.5, heading])
    c, s = math.cos(heading), math.sin(heading)
    fwd, left = 0.1, 0.05
    wx, wy = 0.5 + c * fwd - s * left, 0.5 + s * fwd + c * left
    maps = torch.zeros(1, 1, R, R)
    maps[0, 0, int(wy * R), int(wx * R)] = 1.0
    size, half, off = 40, 0.2, 0.0
    crop = pfnet.local_map_crops(maps, pose[None, None], 1.0, size, half, off)[0, 0]
    assert crop.shape == (size, size)
    i, j = divmod(int(crop.argmax()), size)
    # column = forward, row = left: pixel centre (2j+1)/size - 1 = forward / half
    assert abs(((2 * j + 1) / size - 1) * half - fwd) <= 1.5 * 2 * half / size
    assert abs(((2 * i + 1) / size - 1) * half - left) <= 1.5 * 2 * half / size
    assert crop.sum() > 0.5  # the cell's mass (0.01^2 at 0.01 crop pixels) is preserved


def test_scan_topdown_projects_a_return_ahead():
    angles = 2 * np.pi * np.arange(20) / 20
    proj = pfnet.ScanTopDown(angles, 0.53, 32, 0.3, 0.1)
    scan = torch.full((1, 20), 0.53)
    scan[0, 0] = 0.2  # wall 0.2 straight ahead
    img = proj(scan)[0]  # [3, S, S]
    i, j = divmod(int(img[0].argmax()), 32)
    fwd = 0.1 + 0.3 * ((2 * j + 1) / 32 - 1)
    left = 0.3 * ((2 * i + 1) / 32 - 1)
    assert abs(fwd - 0.2) < 0.02 and abs(left) < 0.03
    assert img[0].sum() > 0 and img[0][:, j].sum() == img[0][:, j].sum()  # only one beam hits
    assert float(img[1].max()) > 0.9  # free space before the return


def test_observation_features_computed_once_per_step(data, monkeypatch):
    om = pfnet.ObservationModel(data.obs_model_config("lidar"))
    calls = []
    orig = om.encode_obs
    monkeypatch.setattr(om, "encode_obs", lambda o: calls.append(o.shape) or orig(o))
    pfnet.PFNet(om)(data.with_sensor("lidar").batch(range(2)), K=50)
    assert calls == [(2, 20)] * 6  # one call per step for all 2 x 50 particles


# ---------------------------------------------------------------------------- training


def test_checkpoint_resume_matches_uninterrupted_run(data, tmp_path):
    ds = data.with_sensor("lidar", fresh_init=True)

    def make():
        torch.manual_seed(0)
        return pfnet.PFNet(pfnet.ObservationModel(data.obs_model_config("lidar")))

    def cfg(epochs):
        return pfnet.TrainConfig(epochs=epochs, batch_size=3, K=5, progress=False, seed=3)

    a = make()
    pfnet.train(a, ds, cfg(2))
    b = make()
    ck = tmp_path / "ck.pt"
    pfnet.train(b, ds, cfg(1), checkpoint=ck)
    assert torch.load(ck, weights_only=True)["epoch"] == 1
    c = make()  # fresh process: model rebuilt, then resumed from the checkpoint
    hist = pfnet.train(c, ds, cfg(2), checkpoint=ck).history
    assert len(hist) == 2
    for (n, pa), pc in zip(a.state_dict().items(), c.state_dict().values()):
        torch.testing.assert_close(pa, pc, msg=n)


def test_pretrain_reduces_loss(data):
    torch.manual_seed(0)
    om = pfnet.ObservationModel(data.obs_model_config("lidar"))
    losses = pfnet.pretrain_observation_model(om, data.with_sensor("lidar"), 40, batch_size=8)
    assert np.mean(losses[-10:]) < np.mean(losses[:10])


def test_simworld_adapter_on_the_real_simulator():
    """pfnet_data.SimWorld (pymunk simulator): odometry = relative motion up to actuation noise,
    sensors in range, floor map = walls only (distractors are seen but not mapped)."""
    pytest.importorskip("pymunk")
    import simulators

    maze = simulators.make_maze("moderate-medium", 0)
    ds = pfnet_data.generate(
        [maze], lambda m, s: pfnet_data.SimWorld(m, distractors=6, seed=s), 2, seed=0, T=6
    )
    assert ds.poses.shape == (2, 6, 3) and ds.depth.shape == (2, 6, 24, 32)
    rel = pfnet_data.relative_pose(ds.poses[:, :-1], ds.poses[:, 1:])
    assert np.abs(rel[..., :2] - ds.odom[..., :2]).max() < 0.01  # 6 cm
    assert np.abs(rel[..., 2] - ds.odom[..., 2]).max() < 0.05  # 3 deg
    assert ds.lidar.max() <= ds.max_range + 1e-6 and 0 <= ds.depth.min() <= ds.depth.max() <= 1
    np.testing.assert_array_equal(ds.maps[0], pfnet.rasterize_floor_map(maze.walls, maze.side))


# ---------------------------------------------------------------------------- baselines


@pytest.mark.parametrize("sensor", ["lidar", "depth"])
def test_baseline_shapes_and_gradients(data, sensor):
    ds = data.with_sensor(sensor)
    b = ds.batch(range(3))
    for model in (bl.HistogramFilterNet(ds.obs_model_config()), bl.LSTMNet(ds.obs_model_config())):
        est = model(b)["estimates"]
        assert est.shape == (3, 6, 3) and torch.isfinite(est).all()
        pfnet.pose_loss(est, b["poses"]).backward()
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())


def test_histogram_filter_transition_moves_mass():
    hf = bl.HistogramFilterNet(pfnet.ObsModelConfig(), grid=16, headings=4)
    mean = torch.tensor([[0.25, 0.5, 0.0]])  # heading 0: mass in the bins at -pi/4 and pi/4
    logb = hf.initial_belief(mean, torch.tensor([0.03, 0.03, 0.3]), 1.0)
    before = hf.estimate(logb, 1.0)
    after = hf.estimate(hf.transition(logb, torch.tensor([[0.25, 0.0, 0.0]]), 1.0), 1.0)
    assert (after[0, 0] - before[0, 0]).item() > 0.1  # moved along +x (heading ~ 0)


def test_histogram_filter_initial_blur_is_narrow():
    """Untrained, a step without motion adds < 0.2 cell^2 of position variance (a uniform 3x3
    blur would add 2/3 cell^2 and out-spread the propagated uncertainty)."""
    G = 16
    hf = bl.HistogramFilterNet(pfnet.ObsModelConfig(), grid=G, headings=8)
    logb = hf.initial_belief(torch.tensor([[0.5, 0.5, 0.0]]), torch.tensor([0.05, 0.05, 0.3]), 1.0)
    c = (torch.arange(G) + 0.5) / G

    def var_x(lb):
        px = torch.exp(lb).sum((1, 2))[0]  # [G] marginal over x
        return float((px * c**2).sum() - (px * c).sum() ** 2) * G**2  # in cells^2

    with torch.no_grad():
        after = hf.transition(logb, torch.zeros(1, 3), 1.0)
    added = var_x(after) - var_x(logb)
    assert 0.0 < added < 0.2


def test_beam_model_prefers_true_pose(data):
    ds = data.with_sensor("lidar")
    b = ds.batch([0])
    pf = bl.BeamModelPF()
    true = b["poses"][:, 0:1]
    off = true + torch.tensor([0.05, 0.0, 0.3])
    ll = pf.log_likelihood(b, b["obs"][:, 0], torch.cat([true, off], 1), 0)
    assert float(ll[0, 0]) > float(ll[0, 1])
    prop = pfnet.evaluate(bl.propagated_uncertainty(), ds, K=300)
    assert pfnet.evaluate(pf, ds, K=300) < prop / 2
