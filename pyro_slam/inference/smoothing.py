"""Smoothing over the particle filter's history: each step's particles, weights and ancestors
(:class:`ParticleHistory`), from which a step's pose is estimated with the particles of a later
step traced back along their ancestral lines (Kitagawa 1996): fixed-lag smoothing with a lag of
``L`` steps online, the ancestral path of the last particles offline (``L`` as long as the
run). With a lag of 0 the estimate is the filtered mean."""

from __future__ import annotations

import math

import torch

from .particles import Particles, pose_moments


class ParticleHistory:
    """Each recorded step's particles ``z [T, K, 3]``, normalised weights ``logw [T, K]`` and
    ancestors ``anc [T, K]`` (``anc[t, k]``: the index at step ``t - 1`` of particle ``k``'s
    parent); a step recorded with ``fresh=True`` (a cloud not descended from the previous step's,
    e.g. a chunk started from the cache) starts a new lineage."""

    def __init__(self, num_steps: int, num_particles: int):
        T, K = num_steps, num_particles
        self.z = torch.zeros(T, K, 3)
        self.logw = torch.full((T, K), -math.log(K))
        self.anc = torch.arange(K).repeat(T, 1)
        self.fresh = torch.ones(T, dtype=torch.bool)  # [T] a lineage starts here
        self.filled = torch.zeros(T, dtype=torch.bool)

    def record(self, t: int, p: Particles, fresh: bool = False) -> None:
        """Step ``t``'s particles (batch-free: ``z [K, 3]``, ``logw [K]``)."""
        self.z[t] = p.z.detach().to(self.z.dtype)
        self.logw[t] = p.logw.detach().to(self.logw.dtype)
        known = p.ancestors is not None and not fresh
        self.anc[t] = p.ancestors if known else torch.arange(self.z.shape[1])
        self.fresh[t] = not known
        self.filled[t] = True

    def smoothed(self, lag: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Each recorded step's pose mean and std ``[T, 3]`` from the particles ``lag`` steps
        later (or the lineage's last step, whichever comes first), traced back to it and
        weighted by their weights there (headings circular, :func:`pose_moments`)."""
        T = int(self.filled.sum())
        ends = self._lineage_ends(T)  # [T] the last step of each step's lineage
        if lag >= T:  # the ancestral path: one backward pass per lineage
            return self._ancestral(T, ends)
        means, stds = [], []
        for s in range(T):
            t = min(s + lag, int(ends[s]))
            idx = torch.arange(self.z.shape[1])
            for u in range(t, s, -1):
                idx = self.anc[u, idx]
            mean, std = pose_moments(self.z[s, idx], self.logw[t])
            means.append(mean)
            stds.append(std)
        return torch.stack(means), torch.stack(stds)

    def _ancestral(self, T: int, ends: torch.Tensor):
        """The poses ``[T, 3]`` (mean, std) along the ancestral lines of each lineage's last
        particles, weighted by their weights."""
        mean, std = torch.empty(T, 3), torch.empty(T, 3)
        idx, t_end = None, None
        for s in range(T - 1, -1, -1):
            if idx is None or int(ends[s]) != t_end:
                t_end, idx = int(ends[s]), torch.arange(self.z.shape[1])
            mean[s], std[s] = pose_moments(self.z[s, idx], self.logw[t_end])
            idx = self.anc[s, idx]
        return mean, std

    def _lineage_ends(self, T: int) -> torch.Tensor:
        """``[T]`` for each step, the last step before the next fresh lineage starts."""
        ends = torch.empty(T, dtype=torch.long)
        end = T - 1
        for s in range(T - 1, -1, -1):
            ends[s] = end
            if self.fresh[s]:
                end = s - 1
        return ends

    def state_dict(self) -> dict:
        return {k: getattr(self, k).clone() for k in ("z", "logw", "anc", "fresh", "filled")}

    def load_state_dict(self, d: dict) -> None:
        for k in ("z", "logw", "anc", "fresh", "filled"):
            getattr(self, k).copy_(d[k])
