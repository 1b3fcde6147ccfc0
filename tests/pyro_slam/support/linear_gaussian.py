"""A linear-Gaussian stand-in for :class:`~pyro_slam.model.DVBFLM` and its exact Kalman filter,
for the particle filter's and the smoother's tests.

The filter only needs four things of its ``model``: ``emission_mean(M, z)``,
``sigma_emission``, ``transition`` (``mean(z, u, scan)`` and ``sigma``) and ``init_scale``.
:class:`LinearGaussian` provides them for a 3-D random walk with drift observed through a linear
map ``x = H z + noise`` (``H`` is passed where DVBF-LM passes the map ``M``), reusing DVBF-LM's
:class:`Transition` base; DVBF-LM's own emission log-density gives the expected weights.
"""

from __future__ import annotations

import pyro
import torch

from pyro_slam.model import DVBFLM, Transition
from pyro_slam.model.factors import _Memo

Q = (0.2, 0.15, 0.1)  # transition std per pose dimension
R = 0.5  # observation std
S0 = (0.3, 0.3, 0.2)  # initial-pose std
H = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, -0.5, 1.0], [0.0, 0.3, -0.6]]  # [B=4, 3]
T = 12


class RandomWalk(Transition):
    """``z_{t+1} = z_t + u_t + N(0, diag(sigma^2))``."""

    def mean(self, z, u, scan=None):
        return z + u


class LinearGaussian:
    """Duck-typed stand-in for :class:`DVBFLM`: linear-Gaussian emission ``x ~ N(M z, R^2)``."""

    # DVBF-LM's own factors (emission noise and log-density, transition distribution, the
    # heading factor) and its Pyro model, whose one-step windows the filter traces
    noise_dist = DVBFLM.noise_dist
    emission_dist = DVBFLM.emission_dist
    emission_log_prob = DVBFLM.emission_log_prob
    transition_dist = DVBFLM.transition_dist
    heading_dist = DVBFLM.heading_dist
    heading_log_prob = DVBFLM.heading_log_prob
    model, step, handled = DVBFLM.model, DVBFLM.step, DVBFLM.handled
    _read, _observe_heading = DVBFLM._read, DVBFLM._observe_heading
    outlier_prob, outlier_range = 0.0, 1.0
    heading_scale = DVBFLM.heading_scale
    handler = None

    def __init__(self, dtype, heading=None):
        self.noise = pyro.distributions.Normal
        self.sigma_emission = R
        self.transition = RandomWalk(torch.tensor(Q, dtype=dtype))
        self.init_scale = torch.tensor(S0, dtype=dtype)
        self.heading = heading
        self._memo = _Memo()

    def _register_networks(self):  # (no networks)
        pass

    def emission_mean(self, M, z, x=None):
        return z @ M.T


def simulate(dtype, seed=0, steps=T):
    g = torch.Generator().manual_seed(seed)
    h = torch.tensor(H, dtype=torch.float64)
    z = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    z0 = z.clone()
    u = 0.1 * torch.randn(steps - 1, 3, generator=g, dtype=torch.float64)
    xs = []
    for t in range(steps):
        if t:
            z = z + u[t - 1] + torch.tensor(Q, dtype=torch.float64) * torch.randn(3, generator=g)
        xs.append(h @ z + R * torch.randn(4, generator=g, dtype=torch.float64))
    return h.to(dtype), torch.stack(xs).to(dtype), u.to(dtype), z0.to(dtype)


def kalman(h, x, u, z0):
    """Exact filtering means, stds ``[T, 3]`` and log-evidence ``log p(x_{0:T-1})`` (float64)."""
    h, x, u, m = (a.to(torch.float64) for a in (h, x, u, z0))
    P = torch.diag(torch.tensor(S0, dtype=torch.float64) ** 2)
    Qm = torch.diag(torch.tensor(Q, dtype=torch.float64) ** 2)
    Rm = R**2 * torch.eye(h.shape[0], dtype=torch.float64)
    means, stds, logz = [], [], 0.0
    for t in range(x.shape[0]):
        if t:
            m, P = m + u[t - 1], P + Qm
        S = h @ P @ h.T + Rm
        logz += torch.distributions.MultivariateNormal(h @ m, S).log_prob(x[t]).item()
        K = P @ h.T @ torch.linalg.inv(S)
        m = m + K @ (x[t] - h @ m)
        P = (torch.eye(3, dtype=torch.float64) - K @ h) @ P
        means.append(m)
        stds.append(P.diagonal().sqrt())
    return torch.stack(means), torch.stack(stds), logz
