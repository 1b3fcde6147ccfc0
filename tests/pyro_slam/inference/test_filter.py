"""The particle filter of :mod:`pyro_slam.inference` against an exact Kalman filter, its failure
mode, resampling, weight normalisation and dtypes.

The model is the linear-Gaussian stand-in of ``support/linear_gaussian.py``, whose exact
posterior the Kalman filter gives.
"""

from __future__ import annotations

import math

import pytest
import torch
from linear_gaussian import S0, H, LinearGaussian, Q, R, RandomWalk, T, kalman, simulate

from pyro_slam.inference import (
    HeadingProposal,
    ParticleFilter,
    ParticleFilterFailed,
    Particles,
    resampling,
)
from pyro_slam.model import DVBFLM, HeadingEvidence, WallHeading


def run_replicates(dtype, reps, K, seed=0, ess_threshold=0.5, **pf_args):
    """``reps`` independent filters as one batch ``[reps, K, 3]``: log-evidence ``[reps]``,
    weighted means ``[T, reps, 3]``; asserts normalised weights at every step."""
    h, x, u, z0 = simulate(dtype)
    model = LinearGaussian(dtype)
    g = torch.Generator().manual_seed(seed)
    pf = ParticleFilter(model, ess_threshold=ess_threshold, generator=g, **pf_args)
    z = z0 + model.init_scale * torch.randn(reps, K, 3, generator=g, dtype=dtype)
    p, ev = pf.init(z, h, x[0])
    means = [p.mean()]
    for t in range(1, T):
        assert torch.allclose(torch.logsumexp(p.logw, -1), torch.zeros((), dtype=dtype), atol=1e-5)
        p, inc = pf.step(p, h, x[t], u[t - 1], step=t)
        ev = ev + inc
        means.append(p.mean())
    assert p.z.shape == (reps, K, 3) and p.logw.shape == (reps, K) and ev.shape == (reps,)
    assert p.z.dtype == dtype and ev.dtype == dtype
    return ev.double(), torch.stack(means).double(), (h, x, u, z0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_log_evidence_and_means_match_kalman(dtype):
    reps, K = 64, 400
    ev, means, (h, x, u, z0) = run_replicates(dtype, reps, K)
    kf_mean, kf_std, kf_logz = kalman(h, x, u, z0)
    assert torch.isfinite(ev).all()
    # exp(log p^) is unbiased for p(x): the mean ratio is 1 up to its own Monte-Carlo error
    ratio = torch.exp(ev - kf_logz)
    se = ratio.std() / math.sqrt(reps)
    assert abs(ratio.mean().item() - 1.0) < 4 * se.item() + 1e-3, (ratio.mean(), se)
    assert 0 < ratio.std() < 0.5  # the estimator is informative (K = 400 on T = 12 steps)
    # each replicate's log-evidence is close; their spread is the MC error
    assert (ev - kf_logz).abs().max() < 1.5
    # filtering means: the replicate average matches Kalman within its standard error
    avg, spread = means.mean(1), means.std(1)  # [T, 3]
    z = (avg - kf_mean).abs() / (spread / math.sqrt(reps) + 0.02 * kf_std)
    assert z.max() < 4.5, z.max()
    # and single replicates within a few posterior stds / sqrt(K)-ish MC error
    assert ((means - kf_mean.unsqueeze(1)).abs() < 6 * spread.unsqueeze(1) + 1e-4).all()
    assert (spread < 0.25 * kf_std).all()  # MC error << posterior spread


def test_heading_factor_matches_kalman_with_an_extra_heading_row():
    """The model's heading factor (:class:`WallHeading` of period 2 pi, frame 0) observes the
    wall direction ``-y_t`` (std ``sigma_o``, far from the wrap), a linear observation of the
    heading ``y_t``, so the filter that samples it by the exact heading proposal must match the
    Kalman filter with the extra row ``[0, 0, 1]``: log-evidence and means within Monte-Carlo
    error, though ``sigma_o`` is 10x below the transition's heading noise."""
    h, x, u, z0 = simulate(torch.float64)
    so = 0.01
    gy = torch.Generator().manual_seed(7)
    y = kalman(h, x, u, z0)[0][:, 2] + 0.03 * torch.randn(T, generator=gy, dtype=torch.float64)
    # the augmented Kalman filter (the heading row from t = 1, as the filter's step applies it)
    P = torch.diag(torch.tensor(S0, dtype=torch.float64) ** 2)
    Qm = torch.diag(torch.tensor(Q, dtype=torch.float64) ** 2)
    m, logz, means = z0.clone(), 0.0, []
    for t in range(T):
        hh, xx, rr = h, x[t], [R**2] * h.shape[0]
        if t:
            m, P = m + u[t - 1], P + Qm
            hh = torch.cat([h, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)])
            xx, rr = torch.cat([x[t], y[t : t + 1]]), rr + [so**2]
        S = hh @ P @ hh.T + torch.diag(torch.tensor(rr, dtype=torch.float64))
        logz += torch.distributions.MultivariateNormal(hh @ m, S).log_prob(xx).item()
        Kg = P @ hh.T @ torch.linalg.inv(S)
        m, P = m + Kg @ (xx - hh @ m), (torch.eye(3, dtype=torch.float64) - Kg @ hh) @ P
        means.append(m)
    reps, K = 64, 200
    model = LinearGaussian(torch.float64, WallHeading(period=2 * math.pi))
    g = torch.Generator().manual_seed(0)
    pf = ParticleFilter(model, HeadingProposal(), generator=g)
    z = z0 + model.init_scale * torch.randn(reps, K, 3, generator=g, dtype=torch.float64)
    p, ev = pf.init(z, h, x[0])
    for t in range(1, T):
        obs = HeadingEvidence(torch.remainder(-y[t], 2 * math.pi).expand(reps), so, frame=0.0)
        p, inc = pf.step(p, h, x[t], u[t - 1], step=t, heading=obs)
        ev = ev + inc
        # the emission's own weights (measured ESS 0.49 K); a heading weight on the transition's
        # samples alone, at 10x their std, would leave a handful
        assert float(resampling.ess(p.logw).mean()) > 0.12 * K
    assert abs(float(ev.mean()) - logz) < 0.3  # measured -0.07 nats (replicates' std 0.27)
    assert (p.mean().mean(0) - means[-1]).abs().max() < 0.015  # measured 0.0065
    assert (p.mean()[:, 2] - means[-1][2]).abs().max() < 0.01  # measured 0.003
    # the cloud's heading spread is the posterior's, about sigma_o (the transition's is 0.1)
    assert float(p.z[..., 2].std(-1).mean()) < 0.012  # measured 0.0098
    # nan: no observation there, the step is the bootstrap one (same draws, same weights)
    outs = []
    for heading in (None, HeadingEvidence(torch.full((reps,), math.nan), so, frame=0.0)):
        pf.generator.manual_seed(3)
        outs.append(pf.step(p, h, x[1], u[0], step=1, heading=heading))
    torch.testing.assert_close(outs[0][0].z, outs[1][0].z)
    torch.testing.assert_close(outs[0][1], outs[1][1])


def test_run_matches_kalman_and_reports_posterior_std():
    h, x, u, z0 = simulate(torch.float64)
    kf_mean, kf_std, kf_logz = kalman(h, x, u, z0)
    pf = ParticleFilter(LinearGaussian(torch.float64), generator=torch.Generator().manual_seed(3))
    out = pf.run(h, x, u, z0, num_particles=3000)
    assert out["mean"].shape == (T, 3) and out["std"].shape == (T, 3)
    assert abs(out["log_evidence"] - kf_logz) < 0.25
    err = (out["mean"] - kf_mean).abs() / kf_std
    assert err.max() < 0.25, err.max()  # MC error ~ 1/sqrt(ESS) posterior stds
    torch.testing.assert_close(out["std"], kf_std, rtol=0.15, atol=0)
    # the returned particles carry the last step's normalised weights
    assert torch.logsumexp(out["particles"].logw, -1).abs() < 1e-9


@pytest.mark.parametrize("bad, kind", [(float("nan"), "NaN"), (float("inf"), "-inf")])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_collapsed_weights_raise_with_step_index(bad, kind, dtype):
    h, x, u, z0 = simulate(dtype)
    x[5, 2] = bad
    pf = ParticleFilter(LinearGaussian(dtype), generator=torch.Generator().manual_seed(0))
    with pytest.raises(ParticleFilterFailed) as info:
        pf.run(h, x, u, z0, num_particles=50)
    assert info.value.step == 5
    assert str(info.value).startswith("step 5:") and kind in str(info.value)
    x[5, 2] = 0.0
    x[0] = bad  # at the very first step too
    with pytest.raises(ParticleFilterFailed) as info:
        pf.run(h, x, u, z0, num_particles=50)
    assert info.value.step == 0


def test_check_weights_flags_any_collapsed_row():
    ok = torch.tensor([[0.0, -1.0], [-math.inf, -2.0]])
    resampling.check_weights(ok, 3)  # one -inf particle is fine
    with pytest.raises(ParticleFilterFailed, match="step 7: all particle weights are zero"):
        resampling.check_weights(torch.tensor([[0.0, 0.0], [-math.inf, -math.inf]]), 7)
    with pytest.raises(ParticleFilterFailed, match="NaN") as info:
        resampling.check_weights(torch.tensor([[0.0, math.nan]]))
    assert info.value.step is None and not str(info.value).startswith("step")


def test_ess_resampling_only_in_degenerate_rows():
    """Rows with ESS < threshold are resampled, others keep their particles and weights."""
    model = LinearGaussian(torch.float64)
    model.transition = RandomWalk(torch.zeros(3, dtype=torch.float64))  # deterministic moves
    pf = ParticleFilter(model, ess_threshold=0.5, generator=torch.Generator().manual_seed(0))
    K = 6
    z = torch.arange(2 * K * 3, dtype=torch.float64).reshape(2, K, 3) / 10
    logw = torch.stack([torch.tensor([0.0] + [-50.0] * (K - 1)), torch.zeros(K)]).double()
    p = Particles(z, resampling.normalize(logw), None)
    assert resampling.ess(p.logw)[0] < 1.01 and resampling.ess(p.logw)[1] == pytest.approx(K)
    u = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    h = torch.tensor(H, dtype=torch.float64)
    x = torch.zeros(2, 4, dtype=torch.float64)
    q, inc = pf.step(p, h, x, u, step=1)
    # degenerate row: all particles descend from particle 0; healthy row: moved in place
    torch.testing.assert_close(q.z[0], (z[0, 0] + u).expand(K, 3))
    torch.testing.assert_close(q.z[1], z[1] + u)
    lik = DVBFLM.emission_log_prob(model, x.unsqueeze(-2), q.z @ h.T)  # [2, K]
    torch.testing.assert_close(q.logw[1], resampling.normalize(lik[1]))  # uniform prior weights
    torch.testing.assert_close(q.logw[0], torch.full((K,), -math.log(K), dtype=torch.float64))
    torch.testing.assert_close(inc, torch.logsumexp(lik - math.log(K), -1))
