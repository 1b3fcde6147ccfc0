"""Smoothing over the particle filter's history (:class:`~pyro_slam.inference.ParticleHistory`)
against the exact Rauch-Tung-Striebel smoother of a linear-Gaussian model, and its lineage
bookkeeping on hand-made histories."""

from __future__ import annotations

import math

import torch
from linear_gaussian import S0, LinearGaussian, Q, kalman, simulate

from pyro_slam.inference import ParticleFilter, ParticleHistory, Particles


def rts(h, x, u, z0):
    """Exact smoothed means ``[T, 3]`` of the random walk of ``test_filtering`` (float64)."""
    h, x, u, m = (a.to(torch.float64) for a in (h, x, u, z0))
    P = torch.diag(torch.tensor(S0, dtype=torch.float64) ** 2)
    Qm = torch.diag(torch.tensor(Q, dtype=torch.float64) ** 2)
    Rm = 0.5**2 * torch.eye(h.shape[0], dtype=torch.float64)
    ms, Ps, preds = [], [], []
    for t in range(x.shape[0]):
        if t:
            m, P = m + u[t - 1], P + Qm
        preds.append(P.clone())
        K = P @ h.T @ torch.linalg.inv(h @ P @ h.T + Rm)
        m, P = m + K @ (x[t] - h @ m), (torch.eye(3, dtype=torch.float64) - K @ h) @ P
        ms.append(m)
        Ps.append(P)
    out = [ms[-1]]
    for t in range(x.shape[0] - 2, -1, -1):
        C = Ps[t] @ torch.linalg.inv(preds[t + 1])
        out.insert(0, ms[t] + C @ (out[0] - ms[t] - u[t]))
    return torch.stack(out)


def filter_history(K: int, seed: int):
    """One particle filter over the simulated sequence, recorded step by step."""
    h, x, u, z0 = simulate(torch.float64)
    model = LinearGaussian(torch.float64)
    g = torch.Generator().manual_seed(seed)
    pf = ParticleFilter(model, generator=g)
    T = x.shape[0]
    hist = ParticleHistory(T, K)
    p, _ = pf.init(
        z0 + model.init_scale * torch.randn(K, 3, generator=g, dtype=torch.float64), h, x[0]
    )
    hist.record(0, p, fresh=True)
    for t in range(1, T):
        p, _ = pf.step(p, h, x[t], u[t - 1], step=t)
        hist.record(t, p)
    return hist, (h, x, u, z0)


def test_smoothing_moves_the_estimates_towards_the_exact_smoother():
    """With a lag as long as the run, the estimates are the smoother's (Rauch-Tung-Striebel),
    far closer to it than the filtered means are; with a lag of 0 they are the filtered means
    (the Kalman filter's)."""
    errs = {"smoothed": [], "filtered": []}
    for seed in range(4):
        hist, data = filter_history(2000, seed)
        exact, kf = rts(*data), kalman(*data)[0]
        smoothed, _ = hist.smoothed(lag=100)
        filtered, _ = hist.smoothed(lag=0)
        assert (filtered - kf).abs().max() < 0.05  # the filter's own means
        errs["smoothed"].append(float((smoothed.double() - exact).abs().mean()))
        errs["filtered"].append(float((filtered.double() - exact).abs().mean()))
    assert sum(errs["smoothed"]) < 0.5 * sum(errs["filtered"]), errs


def test_lineages_are_traced_through_resampling_and_stop_at_a_fresh_cloud():
    """Hand-made ancestors: each step's estimate is the weighted mean of the ancestors (at that
    step) of the particles ``lag`` steps later, never across a fresh start."""
    K, T = 3, 4
    hist = ParticleHistory(T, K)
    uniform = torch.full((K,), -math.log(K))
    positions = [torch.tensor([0.0, 1.0, 2.0]), torch.tensor([10.0, 11.0, 12.0])]
    positions += [torch.tensor([20.0, 21.0, 22.0]), torch.tensor([30.0, 31.0, 32.0])]
    ancestors = [None, torch.tensor([2, 2, 0]), torch.tensor([1, 1, 1]), None]
    for t in range(T):
        z = torch.zeros(K, 3)
        z[:, 0] = positions[t]
        logw = uniform if t < 2 else torch.log(torch.tensor([0.5, 0.25, 0.25]))
        hist.record(t, Particles(z, logw, None, ancestors[t]), fresh=t in (0, 3))
    mean, _ = hist.smoothed(lag=1)
    # step 0 from step 1's particles: ancestors 2, 2, 0 at uniform weights
    assert math.isclose(float(mean[0, 0]), (2 + 2 + 0) / 3, rel_tol=1e-6)
    # step 1 from step 2's: all descend from particle 1 (position 11)
    assert math.isclose(float(mean[1, 0]), 11.0, rel_tol=1e-6)
    # step 2: its lineage ends there (step 3 starts fresh): its own weighted mean
    assert math.isclose(float(mean[2, 0]), 0.5 * 20 + 0.25 * 21 + 0.25 * 22, rel_tol=1e-6)
    full, _ = hist.smoothed(lag=10)  # the ancestral path of step 2's particles
    assert math.isclose(float(full[0, 0]), 0.5 * 2 + 0.25 * 2 + 0.25 * 2, rel_tol=1e-6)
