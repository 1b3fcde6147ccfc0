"""Smoothing over the particle filter's history (:class:`~pyro_slam.inference.ParticleHistory`)
against the exact Rauch-Tung-Striebel smoother of a linear-Gaussian model, and its lineage
bookkeeping on hand-made histories."""

from __future__ import annotations

import math

import torch
from linear_gaussian import S0, LinearGaussian, Q, T, kalman, simulate

from pyro_slam.inference import ParticleFilter, ParticleHistory, Particles, transition_log_density


def rts(h, x, u, z0):
    """Exact smoothed means and stds ``[T, 3]`` of the random walk of ``test_filtering``
    (float64)."""
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
    out, cov = [ms[-1]], [Ps[-1]]
    for t in range(x.shape[0] - 2, -1, -1):
        C = Ps[t] @ torch.linalg.inv(preds[t + 1])
        out.insert(0, ms[t] + C @ (out[0] - ms[t] - u[t]))
        cov.insert(0, Ps[t] + C @ (cov[0] - preds[t + 1]) @ C.T)
    return torch.stack(out), torch.stack([c.diagonal().sqrt() for c in cov])


def filter_history(K: int, seed: int, steps: int = T):
    """One particle filter over the simulated sequence, recorded step by step."""
    h, x, u, z0 = simulate(torch.float64, steps=steps)
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
    return hist, (h, x, u, z0), transition_log_density(model, hist, u)


def test_smoothing_moves_the_estimates_towards_the_exact_smoother():
    """With a lag as long as the run, the estimates are the smoother's (Rauch-Tung-Striebel),
    far closer to it than the filtered means are; with a lag of 0 they are the filtered means
    (the Kalman filter's)."""
    errs = {"smoothed": [], "filtered": []}
    for seed in range(4):
        hist, data, log_f = filter_history(2000, seed)
        exact, kf = rts(*data)[0], kalman(*data)[0]
        smoothed, _ = hist.smoothed(100, log_f)
        filtered, _ = hist.smoothed(0, log_f)
        assert (filtered - kf).abs().max() < 0.05  # the filter's own means
        errs["smoothed"].append(float((smoothed.double() - exact).abs().mean()))
        errs["filtered"].append(float((filtered.double() - exact).abs().mean()))
    assert sum(errs["smoothed"]) < 0.5 * sum(errs["filtered"]), errs


def test_smoothed_std_is_the_exact_smoothers():
    """Over a long run the smoothed std is the Rauch-Tung-Striebel smoother's at every step
    (within sampling error): each step keeps all its particles, weighted by the later evidence.
    The ancestors of the last step's particles collapse to a few lineages far back, whose
    spread is far narrower."""
    ratios = []
    for seed in range(3):
        hist, data, log_f = filter_history(300, seed, steps=150)
        _, exact_std = rts(*data)
        _, std = hist.smoothed(100, log_f)
        ratios.append(std.double() / exact_std)
    ratios = torch.stack(ratios)  # [seeds, T, 3]
    assert 0.9 < float(ratios.mean()) < 1.1, ratios.mean()
    assert float(ratios.quantile(0.1)) > 0.75, ratios.quantile(0.1)


def test_backward_kernels_weigh_each_particle_by_the_filter_and_the_transition():
    """Hand-made history: step 0's smoothed weights are ``w_0^i sum_j w_1^j f_ji / sum_l w_0^l
    f_jl``; a lineage that ends (step 2 starts fresh) keeps its own weights, and the transition
    is never evaluated across the fresh start."""
    K, T = 2, 3
    hist = ParticleHistory(T, K)
    w0, w1, w2 = torch.tensor([0.6, 0.4]), torch.tensor([0.8, 0.2]), torch.tensor([0.3, 0.7])
    f = torch.tensor([[0.9, 0.1], [0.2, 0.8]])  # f(z_1^j | z_0^i) [j, i]
    for t, (w, x) in enumerate([(w0, [0.0, 1.0]), (w1, [10.0, 11.0]), (w2, [20.0, 21.0])]):
        z = torch.zeros(K, 3)
        z[:, 0] = torch.tensor(x)
        ancestors = None if t == 2 else torch.arange(K)
        hist.record(t, Particles(z, w.log(), None, ancestors), fresh=t == 0)

    def log_f(u):
        assert u == 0, "the transition is evaluated across a fresh start"
        return f.log()

    expected = w0 * ((w1[:, None] * f) / (f * w0).sum(-1, keepdim=True)).sum(0)  # [K]
    for lag in (1, 10):
        mean, _ = hist.smoothed(lag, log_f)
        assert math.isclose(float(mean[0, 0]), float(expected[1]), rel_tol=1e-6)
        assert math.isclose(float(mean[1, 0]), 0.8 * 10 + 0.2 * 11, rel_tol=1e-6)
        assert math.isclose(float(mean[2, 0]), 0.3 * 20 + 0.7 * 21, rel_tol=1e-6)
    filtered, _ = hist.smoothed(0, log_f)
    assert math.isclose(float(filtered[0, 0]), 0.4, rel_tol=1e-6)


def test_the_transition_reads_the_kept_scans():
    """A transition that reads the predicted scan is evaluated between steps with the scans
    that the history kept for the earlier step."""
    K = 3
    hist = ParticleHistory(2, K)
    hist.keep_scans = True
    scans = [torch.full((K, 5), 1.0), torch.full((K, 5), 2.0)]
    for t in range(2):
        hist.record(t, Particles(torch.zeros(K, 3), torch.zeros(K), scans[t], torch.arange(K)))
    seen = []

    class Stub:
        def transition_dist(self, z, u, scan, validate=None):
            seen.append(scan)
            return LinearGaussian(torch.float32).transition_dist(z, u, None, validate=False)

    out = transition_log_density(Stub(), hist, torch.zeros(1, 3))(0)
    assert out.shape == (K, K) and torch.equal(seen[0], scans[0])
