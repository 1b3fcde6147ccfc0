"""Weighted pose particles and their moments."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..geometry import wrap_angle
from . import resampling


@dataclass
class Particles:
    """A weighted particle set. ``z [..., K, 3]``, ``logw [..., K]`` (normalised),
    ``scan [..., K, B]`` the predicted scan at ``z`` (the transition's input), detached;
    ``ancestors [..., K]`` each particle's index in the set it descends from (None: unknown),
    for smoothing over the particles' history (:class:`~.smoothing.ParticleHistory`)."""

    z: torch.Tensor
    logw: torch.Tensor
    scan: torch.Tensor | None = None
    ancestors: torch.Tensor | None = None

    @property
    def num_particles(self) -> int:
        return self.z.shape[-2]

    def mean(self) -> torch.Tensor:
        """Weighted mean pose ``[..., 3]`` (circular mean of the heading, wrapped)."""
        return weighted_pose_mean(self.z, self.logw)

    def std(self) -> torch.Tensor:
        """Weighted std ``[..., 3]`` (the heading's about its circular mean, see
        :func:`pose_moments`)."""
        return pose_moments(self.z, self.logw)[1]

    def posterior_std(self) -> torch.Tensor:
        """The posterior's std ``[3]`` the cloud reports: per axis the larger of the weighted
        std (:meth:`std`) and the Gaussian fit's (:func:`fitted_variance`), which still
        measures the posterior's width when the weights fall on one particle."""
        std = self.std()
        fitted = fitted_variance(self.z, self.logw)
        return std if fitted is None else torch.maximum(std**2, fitted).sqrt()

    def resample(self, generator=None, scheme="systematic") -> Particles:
        """Equally weighted particles drawn by ``scheme`` (:data:`resampling.SCHEMES`); their
        ``ancestors`` are the drawn indices."""
        idx = resampling.SCHEMES[scheme](self.logw, generator)
        scan = None if self.scan is None else resampling.gather_particles(self.scan, idx)
        return Particles(
            resampling.gather_particles(self.z, idx),
            torch.full_like(self.logw, -math.log(self.num_particles)),
            scan,
            idx,
        )

    def where(self, mask: torch.Tensor, other: Particles) -> Particles:
        """These particles where ``mask [...]`` holds, ``other``'s elsewhere (both with
        ``ancestors``)."""
        m = mask.unsqueeze(-1)
        return Particles(
            torch.where(m.unsqueeze(-1), self.z, other.z),
            torch.where(m, self.logw, other.logw),
            None if self.scan is None else torch.where(m.unsqueeze(-1), self.scan, other.scan),
            torch.where(m, self.ancestors, other.ancestors),
        )

    def identity(self) -> torch.Tensor:
        """``[..., K]`` each particle its own ancestor (no resampling)."""
        return torch.arange(self.num_particles).expand(self.logw.shape)

    def detach(self) -> Particles:
        return Particles(
            self.z.detach(),
            self.logw.detach(),
            None if self.scan is None else self.scan.detach(),
            self.ancestors,
        )

    def batched(self) -> Particles:
        """The same particles with a leading batch dimension of 1."""
        scan = None if self.scan is None else self.scan.unsqueeze(0)
        return Particles(self.z.unsqueeze(0), self.logw.unsqueeze(0), scan)


def weighted_pose_mean(z: torch.Tensor, logw: torch.Tensor) -> torch.Tensor:
    """``z [..., K, 3]`` weighted by ``exp(logw) [..., K]`` -> ``[..., 3]`` (circular mean of
    the heading, wrapped)."""
    w = logw.exp().unsqueeze(-1)
    xy = (w * z[..., :2]).sum(-2)
    h = z[..., 2:3]
    c, s = (w * torch.cos(h)).sum(-2), (w * torch.sin(h)).sum(-2)
    return torch.cat([xy, torch.atan2(s, c)], -1)


def pose_moments(z: torch.Tensor, logw: torch.Tensor | None = None):
    """Weighted mean and std ``[..., 3]`` of poses ``z [..., N, 3]`` (weights ``exp(logw)
    [..., N]``, normalised; None: uniform). The heading's mean is the circular mean and its
    std that of the wrapped deviations from it, so a cloud that straddles +-pi (heading ~pi)
    has the mean ~pi and a small std, not 0 and ~pi."""
    if logw is None:
        logw = torch.full(z.shape[:-1], -math.log(z.shape[-2]), dtype=z.dtype)
    mean = weighted_pose_mean(z, logw)  # [..., 3]
    d = torch.cat(
        [z[..., :2] - mean[..., None, :2], wrap_angle(z[..., 2:] - mean[..., None, 2:])], -1
    )
    w = logw.exp().unsqueeze(-1)  # [..., N, 1]
    dm = (w * d).sum(-2, keepdim=True)
    return mean, (w * (d - dm) ** 2).sum(-2).sqrt()


# the particles :func:`fitted_variance` fits: those within FIT_DEPTH nats of the largest
# log-weight (the beam mixture flattens the log-likelihood of poses far from the scan's, which
# a quadratic cannot follow), at least FIT_PARTICLES of them (twice the quadratic's parameters)
FIT_DEPTH, FIT_PARTICLES = 30.0, 20


def fitted_variance(z: torch.Tensor, logw: torch.Tensor) -> torch.Tensor | None:
    """The posterior's variance ``[3]`` from a Gaussian fit to the weighted cloud ``z [K, 3]``,
    ``logw [K]`` (one cloud, no batch): the particles are draws from the proposal, whose
    covariance ``S`` their unweighted moments give, and the log-weights of those within
    :data:`FIT_DEPTH` of the largest (at least :data:`FIT_PARTICLES`) are fitted by least
    squares with a quadratic ``c + b'd - d'Hd / 2`` in the deviations ``d`` from the unweighted
    mean (the heading's wrapped), ``H`` projected onto the positive semi-definite matrices. The
    posterior, proposal times weight, is then Gaussian with precision ``S^-1 + H``: the diagonal
    of its inverse. None where there is nothing to fit: fewer than :data:`FIT_PARTICLES`
    particles of non-zero weight, or a proposal with no spread on an axis (or none at all)."""
    K = z.shape[-2]
    zd, lw = z.double(), logw.double()
    mean = pose_moments(zd)[0]
    d = torch.cat([zd[:, :2] - mean[:2], wrap_angle(zd[:, 2:] - mean[2:])], -1)  # [K, 3]
    scale = d.std(0)  # [3]
    if K < FIT_PARTICLES or bool((scale <= 1e-12).any()):
        return None
    fit = lw >= torch.minimum(lw.max() - FIT_DEPTH, lw.topk(FIT_PARTICLES).values[-1])  # [K]
    fit &= torch.isfinite(lw)
    if int(fit.sum()) < FIT_PARTICLES:  # (particles of zero weight)
        return None
    u = d / scale
    iu = torch.triu_indices(3, 3)  # the 6 products u_a u_b, a <= b
    X = torch.cat([torch.ones_like(u[:, :1]), u, u[:, iu[0]] * u[:, iu[1]]], -1)  # [K, 10]
    q = torch.linalg.lstsq(X[fit], lw[fit].unsqueeze(-1)).solution[4:, 0]  # [6] quadratic
    H = torch.zeros(3, 3, dtype=zd.dtype)
    H[iu[0], iu[1]] = q
    H = -(H + H.T)  # u_a^2 carries -H_aa / 2, u_a u_b (a < b) -H_ab
    ev, V = torch.linalg.eigh(H)
    H = (V * ev.clamp_min(0)) @ V.T / scale[:, None] / scale[None, :]
    proposal_precision, info = torch.linalg.inv_ex(d.T @ d / K)
    var = torch.linalg.inv(proposal_precision + H).diagonal()
    if int(info) or not bool(torch.isfinite(var).all()):  # particles on a plane
        return None
    return var.to(z.dtype)
