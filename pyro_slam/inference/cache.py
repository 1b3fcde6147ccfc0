"""The asynchronous particle cache of DVBF-LM (paper III-D2, eq. 3)."""

from __future__ import annotations

import torch

from ..geometry import wrap_angle
from . import resampling
from .particles import Particles, pose_moments


class ParticleCache:
    """``N`` cached pose particles for each of ``T`` steps (paper III-D2).

    ``propose`` draws the start particles of a chunk from the moment-matched Gaussian
    ``q^(z_t) = N(mean(xi_t), var(xi_t))`` (paper eq. 3) or, with ``kind="categorical"``, from
    the cached particles plus a little noise (paper Appendix B-I).
    """

    def __init__(self, num_steps: int, num_particles: int = 50, dtype=torch.float32):
        self.z = torch.zeros(num_steps, num_particles, 3, dtype=dtype)  # [T, N, 3]
        self.filled = torch.zeros(num_steps, dtype=torch.bool)  # [T]

    @property
    def num_particles(self) -> int:
        return self.z.shape[1]

    def store(self, t: torch.Tensor, p: Particles, generator=None) -> None:
        """Store particles ``p`` (batch ``[C]``) at steps ``t [C]``, resampled to N by weight."""
        N = self.num_particles
        K = p.num_particles
        logw = p.logw.detach()
        if K != N:
            # systematic resampling to N from K particles: replicate the log weights' grid
            w = logw.exp()
            cdf = torch.cumsum(w, -1)
            cdf[..., -1] = 1.0
            u0 = torch.rand(logw.shape[:-1] + (1,), generator=generator, dtype=w.dtype)
            u = (u0 + torch.arange(N, dtype=w.dtype)) / N
            idx = torch.searchsorted(cdf, u.contiguous()).clamp_(max=K - 1)
        else:
            idx = resampling.systematic(logw, generator)
        self.z[t] = resampling.gather_particles(p.z.detach(), idx).to(self.z.dtype)
        self.filled[t] = True

    def moments(self, t: torch.Tensor):
        """Mean and std ``[C, 3]`` of the cached particles at steps ``t [C]`` (the heading's
        circular, :func:`~pyro_slam.inference.pose_moments`)."""
        return pose_moments(self.z[t])

    def propose(
        self, t: torch.Tensor, K: int, kind="gaussian", noise=1e-3, min_std=1e-4, generator=None
    ):
        """``K`` start particles ``[C, K, 3]`` for chunks starting at ``t [C]``."""
        if not bool(self.filled[t].all()):
            missing = t[~self.filled[t]].tolist()
            raise ValueError(f"particle cache has no particles at steps {missing[:5]}")
        if kind == "gaussian":
            loc, scale = self.moments(t)
            eps = torch.randn(len(t), K, 3, generator=generator, dtype=loc.dtype)
            z = loc.unsqueeze(1) + eps * scale.clamp_min(min_std).unsqueeze(1)
            return torch.cat([z[..., :2], wrap_angle(z[..., 2:])], -1)
        if kind == "categorical":
            N = self.num_particles
            idx = torch.randint(N, (len(t), K), generator=generator)
            z = torch.gather(self.z[t], 1, idx.unsqueeze(-1).expand(-1, -1, 3))
            return z + noise * torch.randn(z.shape, generator=generator, dtype=z.dtype)
        raise ValueError(f"unknown proposal kind {kind!r}")

    def state_dict(self):
        return {"z": self.z.clone(), "filled": self.filled.clone()}

    def load_state_dict(self, d):
        self.z.copy_(d["z"])
        self.filled.copy_(d["filled"])
