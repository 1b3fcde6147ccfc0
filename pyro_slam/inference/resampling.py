"""Particle resampling: one implementation of each scheme, shared by every filter.

All functions take **log** weights of shape ``[..., K]`` (any batch shape, unnormalised) and
return ancestor indices ``[..., K]`` (and, for soft resampling, the new log weights). They are
used by the DVBF-LM particle guide (:mod:`pyro_slam.inference`) and by PF-net
(:mod:`pyro_slam.pfnet`).
"""

from __future__ import annotations

import math

import torch


class ParticleFilterFailed(RuntimeError):
    """All particle weights are -inf or NaN at some step (cf. ``pyro.infer.smcfilter.SMCFailed``).

    Attributes:
        step: the time step index at which the weights collapsed (``None`` if unknown).
    """

    def __init__(self, message: str, step: int | None = None):
        super().__init__(message if step is None else f"step {step}: {message}")
        self.step = step


def normalize(log_weights: torch.Tensor) -> torch.Tensor:
    """Normalised log weights ``[..., K]`` (log-sum-exp, so each row sums to one in exp space)."""
    return log_weights - torch.logsumexp(log_weights, dim=-1, keepdim=True)


def check_weights(log_weights: torch.Tensor, step: int | None = None) -> None:
    """Raise :class:`ParticleFilterFailed` if any row has no finite weight or contains NaN."""
    if torch.isnan(log_weights).any():
        raise ParticleFilterFailed("particle log weights contain NaN", step)
    if not torch.isfinite(log_weights.max(dim=-1).values).all():
        raise ParticleFilterFailed("all particle weights are zero (-inf log weight)", step)


def ess(log_weights: torch.Tensor) -> torch.Tensor:
    """Effective sample size ``1 / sum w_k^2`` of normalised weights, shape ``[...]``."""
    logw = normalize(log_weights)
    return torch.exp(-torch.logsumexp(2 * logw, dim=-1))


def multinomial(log_weights: torch.Tensor, generator: torch.Generator | None = None):
    """Ancestors drawn i.i.d. from the categorical over particles: ``[..., K]`` long."""
    K = log_weights.shape[-1]
    probs = torch.exp(normalize(log_weights.detach())).reshape(-1, K)
    idx = torch.multinomial(probs, K, replacement=True, generator=generator)
    return idx.reshape(log_weights.shape)


def systematic(log_weights: torch.Tensor, generator: torch.Generator | None = None):
    """Systematic resampling (one uniform offset per row): ``[..., K]`` long, sorted."""
    K = log_weights.shape[-1]
    w = torch.exp(normalize(log_weights.detach()))
    cdf = torch.cumsum(w, dim=-1)
    cdf[..., -1] = 1.0  # guard against round-off
    u0 = torch.rand(
        log_weights.shape[:-1] + (1,),
        generator=generator,
        dtype=w.dtype,
        device=w.device,
    )
    u = (u0 + torch.arange(K, dtype=w.dtype, device=w.device)) / K
    return torch.searchsorted(cdf, u.contiguous()).clamp_(max=K - 1)


def soft(
    log_weights: torch.Tensor,
    alpha: float,
    generator: torch.Generator | None = None,
):
    """Soft resampling of PF-net (Karkus et al. 2018, eqs. 8-9).

    Ancestors are drawn from ``q(k) = alpha * w_k + (1 - alpha) / K`` and the new weights are
    ``w_k / q(k)`` (normalised), which keeps a gradient path through the weights for
    ``alpha < 1``. With ``alpha = 1`` this is ordinary multinomial resampling with uniform new
    weights.

    Returns:
        ``(ancestors [..., K] long, new_log_weights [..., K])``.
    """
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"soft resampling alpha must lie in [0, 1], got {alpha}")
    K = log_weights.shape[-1]
    logw = normalize(log_weights)
    if alpha >= 1.0:
        log_q = logw
    else:
        log_q = torch.logaddexp(
            logw + math.log(alpha) if alpha > 0 else torch.full_like(logw, -math.inf),
            torch.full_like(logw, math.log((1 - alpha) / K)),
        )
    idx = multinomial(log_q, generator)
    new = torch.gather(logw - log_q, -1, idx)
    return idx, normalize(new)


SCHEMES = {"multinomial": multinomial, "systematic": systematic}


def gather_particles(x: torch.Tensor, ancestors: torch.Tensor) -> torch.Tensor:
    """Select particles ``x [..., K, D]`` by ancestors ``[..., K]`` -> ``[..., K, D]``."""
    return torch.gather(x, -2, ancestors.unsqueeze(-1).expand(*ancestors.shape, x.shape[-1]))
