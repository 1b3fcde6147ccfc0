"""Particle proposals: the transition itself (bootstrap) and the transition conditioned exactly
on a direct observation of the heading (:class:`HeadingObservation`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pyro.distributions as dist
import torch

from ..geometry import wrap_angle


@dataclass
class HeadingObservation:
    """A direct observation of the heading modulo ``period``: ``heading = value (mod period)``
    up to Gaussian noise of std ``sigma`` (rad), or, with probability ``outlier_prob``, an
    outlier uniform over the period (a wall mistaken for straight, a spurious agreement). E.g.
    the Manhattan-world one: a scan's walls run along the world's two axes, so the heading is
    the walls' frame minus the scan's wall direction (:mod:`pyro_slam.slam.heading`)."""

    value: torch.Tensor  # [...] (one per batch element; nan: no observation there)
    sigma: float | torch.Tensor  # a number, or one per batch element [...]
    period: float = math.pi / 2
    outlier_prob: float = 0.0

    def at(self, t) -> HeadingObservation:
        """The observation of step(s) ``t`` from one that holds a sequence ``value [T]``."""
        sigma = self.sigma[t] if torch.is_tensor(self.sigma) else self.sigma
        return HeadingObservation(self.value[t], sigma, self.period, self.outlier_prob)


def _gaussian(model, p, u, sigma):
    """The model's transition at particles ``p`` as its ``(loc, scale)`` ``[..., K, 3]``; a
    transition that is not Gaussian is refused where the proposal needs one."""
    d = model.transition_dist(p.z, u.unsqueeze(-2), p.scan, sigma, validate=False)
    base = getattr(d, "base_dist", d)
    if not isinstance(base, dist.Normal):
        return None, d
    return (base.loc, base.scale), d


@torch.no_grad()
def bootstrap(model, p, u: torch.Tensor, sigma=None, generator=None) -> torch.Tensor:
    """Sample ``z_{t+1} ~ p(. | z_t, u_t, mu_E(m_t))`` (``model.transition_dist``) for particles
    ``p``: ``[..., K, 3]``. A Gaussian transition is sampled with ``generator``; any other
    distribution with its own ``sample()``.

    ``sigma``: the transition std to use instead of the model's ``sigma_T`` (``[3]`` or
    ``[..., 1, 3]``)."""
    params, d = _gaussian(model, p, u, sigma)
    if params is None:
        return d.sample()
    loc, scale = params
    eps = torch.randn(loc.shape, generator=generator, dtype=loc.dtype)
    return loc + eps * scale


@torch.no_grad()
def heading_conditioned(model, p, u, obs: HeadingObservation, sigma=None, generator=None):
    """Sample ``z [..., K, 3]`` from the transition conditioned on a heading observation.

    The transition's heading is Gaussian about its mean ``m`` (std ``s`` from ``sigma`` or
    the model's) and independent of its position noise, and the observation is Gaussian in
    the wrapped residual (std ``sigma_o``), so the optimal proposal is exact: with
    ``r = wrap_angle(m - value, period)`` and ``v = s^2 + sigma_o^2``, the heading is drawn from
    ``N(m - r s^2 / v, s^2 sigma_o^2 / v)`` and the weight gains the predictive
    ``log N(r; 0, sqrt(v))``. With a sharp observation (``sigma_o << s``) every particle
    lands on a heading the observation allows, however narrow the cloud. With
    ``outlier_prob = eps`` the observation is the mixture ``(1 - eps) N + eps / period``, still
    exact: each particle takes the conditioned heading with probability ``(1 - eps) N(r) /
    ((1 - eps) N(r) + eps / period)`` (else the transition's) and the weight gains the log of
    that denominator, so an observation far from a particle barely moves it. Where the value is
    nan the heading is the transition's sample and the weight unchanged. Returns
    ``(z, log_weight [..., K])``."""
    params, _ = _gaussian(model, p, u, sigma)
    if params is None:
        raise ValueError("the heading observation's exact proposal needs a Gaussian transition")
    mean, std = params  # [..., K, 3]
    eps = torch.randn(mean.shape, generator=generator, dtype=mean.dtype)
    z = mean + eps * std
    s = std[..., 2]
    value = torch.as_tensor(obs.value, dtype=mean.dtype).unsqueeze(-1)  # [..., 1]
    so = torch.as_tensor(obs.sigma, dtype=mean.dtype)
    so = so.unsqueeze(-1) if so.dim() else so  # [..., 1]
    seen = ~torch.isnan(value)  # [..., 1]
    r = wrap_angle(mean[..., 2] - value.nan_to_num(), obs.period)
    v = s**2 + so**2  # r: [..., K]
    h = mean[..., 2] - r * s**2 / v + eps[..., 2] * (s * so / v.sqrt())
    log_in = -0.5 * r**2 / v - 0.5 * torch.log(2 * math.pi * v)  # [..., K]
    logw, inlier = log_in, torch.ones_like(log_in, dtype=torch.bool)
    if obs.outlier_prob > 0:
        log_in = log_in + math.log1p(-obs.outlier_prob)
        log_out = math.log(obs.outlier_prob / obs.period)
        logw = torch.logaddexp(log_in, log_in.new_tensor(log_out))
        u01 = torch.rand(log_in.shape, generator=generator, dtype=mean.dtype)
        inlier = u01 < torch.exp(log_in - logw)
    h = torch.where(seen & inlier, wrap_angle(h), z[..., 2])
    logw = torch.where(seen, logw, 0.0)
    return torch.cat([z[..., :2], h.unsqueeze(-1)], -1), logw
