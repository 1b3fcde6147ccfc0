"""Smoothing over the particle filter's history: each step's particles and weights
(:class:`ParticleHistory`), from which a step's pose is estimated with the weights of a later
step carried back to it by forward filtering, backward smoothing (FFBSm; Doucet, Godsill and
Andrieu 2000): fixed-lag smoothing with a lag of ``L`` steps online, the whole run offline
(``L`` as long as the run). With a lag of 0 the estimate is the filtered mean."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from .particles import Particles, pose_moments

# log f(z_{u+1}^j | z_u^i) [K_next, K_prev] between the recorded particles of steps u and u + 1
LogTransition = Callable[[int], torch.Tensor]


class ParticleHistory:
    """Each recorded step's particles ``z [T, K, 3]`` and normalised weights ``logw [T, K]``; a
    step recorded with ``fresh=True``, or from particles without ancestors (a cloud not
    descended from the previous step's, e.g. a chunk started from the cache), starts a new
    lineage, which smoothing does not cross. With ``keep_scans`` set, also each particle's
    predicted scan ``scan [T, K, B]`` (what a transition that reads the scan needs to be
    evaluated between steps)."""

    def __init__(self, num_steps: int, num_particles: int):
        T, K = num_steps, num_particles
        self.z = torch.zeros(T, K, 3)
        self.logw = torch.full((T, K), -math.log(K))
        self.fresh = torch.ones(T, dtype=torch.bool)  # [T] a lineage starts here
        self.filled = torch.zeros(T, dtype=torch.bool)
        self.keep_scans = False
        self.scan: torch.Tensor | None = None  # [T, K, B] once the first scan is kept

    def record(self, t: int, p: Particles, fresh: bool = False) -> None:
        """Step ``t``'s particles (batch-free: ``z [K, 3]``, ``logw [K]``, ``scan [K, B]``)."""
        self.z[t] = p.z.detach().to(self.z.dtype)
        self.logw[t] = p.logw.detach().to(self.logw.dtype)
        self.fresh[t] = fresh or p.ancestors is None
        self.filled[t] = True
        if self.keep_scans:
            if self.scan is None:
                self.scan = self.z.new_zeros(*self.z.shape[:2], p.scan.shape[-1])
            self.scan[t] = p.scan.detach().to(self.scan.dtype)

    @torch.no_grad()
    def smoothed(self, lag: int, log_transition: LogTransition):
        """Each recorded step's pose mean and std ``[T, 3]`` (headings circular,
        :func:`pose_moments`) under its marginal smoothing weights: the filter weights of step
        ``t = min(s + lag, the lineage's last step)`` carried back to step ``s`` through the
        backward kernels ``B_u[j, i] = w_u^i f(z_{u+1}^j | z_u^i) / sum_l w_u^l f(z_{u+1}^j |
        z_u^l)``, so that every particle of step ``s`` keeps its share of the later evidence
        (the ancestry of step ``t``'s particles collapses to a few lineages).
        ``log_transition(u)``: the model's ``log f`` between the particles of steps ``u`` and
        ``u + 1``, ``[K_next, K_prev]`` (:func:`transition_log_density`)."""
        T = int(self.filled.sum())
        ends = self._lineage_ends(T)  # [T] the last step of each step's lineage
        kernels: dict[int, torch.Tensor] = {}

        def kernel(u: int) -> torch.Tensor:  # B_u [K_next, K_prev], float64
            if u not in kernels:
                lf = log_transition(u).to(torch.float64) + self.logw[u].to(torch.float64)
                kernels[u] = torch.softmax(lf, -1)
            return kernels[u]

        weights = torch.empty(T, self.z.shape[1], dtype=torch.float64)  # [T, K]
        for s in range(T - 1, -1, -1) if lag >= T else range(T):
            t = min(s + lag, int(ends[s]))
            if lag >= T and t > s:  # the whole lineage: one backward pass
                weights[s] = weights[s + 1] @ kernel(s)
                continue
            w = self.logw[t].to(torch.float64).exp()  # [K]
            for u in range(t - 1, s - 1, -1):
                w = w @ kernel(u)  # [K_prev]
            weights[s] = w
            for u in [u for u in kernels if u < s]:  # (the window moves on)
                del kernels[u]
        logw = weights.clamp_min(1e-300).log().to(self.z.dtype)
        return pose_moments(self.z[:T], logw)

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
        keys = ("z", "logw", "fresh", "filled") + (() if self.scan is None else ("scan",))
        return {k: getattr(self, k).clone() for k in keys}

    def load_state_dict(self, d: dict) -> None:
        for k in ("z", "logw", "fresh", "filled"):
            getattr(self, k).copy_(d[k])
        self.scan = d["scan"].clone() if "scan" in d else None


def transition_log_density(model, history: ParticleHistory, controls) -> LogTransition:
    """The model's transition density between the recorded particles of consecutive steps:
    ``u -> log p(z_{u+1}^j | z_u^i, u_u, mu_E(m_u^i))`` ``[K_next, K_prev]`` (controls ``[T-1,
    D_u]``; the predicted scans from the history where the transition reads them)."""

    def log_f(u: int) -> torch.Tensor:
        z = history.z[u]  # [K, 3]
        scan = None if history.scan is None else history.scan[u]
        ctl = torch.as_tensor(controls[u], dtype=z.dtype).unsqueeze(-2)  # [1, D_u]
        d = model.transition_dist(z, ctl, scan, validate=False)
        return d.log_prob(history.z[u + 1].unsqueeze(-2))

    return log_f
