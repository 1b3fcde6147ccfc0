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
