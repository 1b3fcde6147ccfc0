"""The differentiable, batched particle filter over DVBF-LM poses.

:class:`ParticleFilter` is the custom SMC guide over poses of DVBF-LM (paper III-C): particles
are proposed by a :class:`~.proposals.Proposal` (the transition, or a guide with its importance
correction) and weighted by the model's likelihood of the step's observations -- the emission
under a map (or, under a map belief ``q(M)``, the model's stated marginalisation over it,
:meth:`~pyro_slam.model.DVBFLM.marginal_emission`) and the heading factor where the model has
one -- in log space, with ESS-triggered resampling. Unlike :class:`pyro.infer.SMCFilter` it keeps
the autograd graph from the map and emission parameters to the log-evidence estimate

    log p^(x_{1:T} | M) = sum_t log sum_k w_{t-1,k} p(x_t | z_t^k, M) p(z_t^k | .) / q(z_t^k | .)

(resampling indices and particle positions are treated as samples, i.e. no gradient flows
through them), so the same step serves training (:class:`~.elbo.ParticleChunkELBO`) and
filtering. Particles may carry any batch shape: ``[..., K, 3]``.
"""

from __future__ import annotations

import math

import torch

from ..model.model import HeadingEvidence, MapBelief
from . import resampling
from .particles import Particles
from .proposals import Proposal, TransitionProposal


class ParticleFilter:
    """Particle filter over DVBF-LM poses (module doc).

    Args:
        model: the :class:`~pyro_slam.model.DVBFLM`.
        proposal: the pose proposal (:class:`~.proposals.Proposal`; default the transition).
        generator: ``torch.Generator`` for reproducible noise and resampling.
        ess_threshold: resample when ``ESS < ess_threshold * K``.
        scheme: ``"systematic"`` or ``"multinomial"`` (:mod:`.resampling`).
        autocast_dtype: e.g. ``torch.bfloat16``: run the emission in reduced precision when no
            gradient is needed (filtering under a fixed map); ~2-3x faster on CPU.
    """

    def __init__(
        self,
        model,
        proposal: Proposal | None = None,
        generator: torch.Generator | None = None,
        ess_threshold: float = 0.5,
        scheme: str = "systematic",
        autocast_dtype: torch.dtype | None = None,
    ):
        if scheme not in resampling.SCHEMES:
            raise ValueError(f"unknown resampling scheme {scheme!r}")
        self.model = model
        self.proposal = TransitionProposal() if proposal is None else proposal
        self.generator = generator
        self.ess_threshold, self.scheme = ess_threshold, scheme
        self.autocast_dtype = autocast_dtype

    def log_likelihood(self, z, M, x, mask=None, heading=None):
        """The model's log-likelihood of the step's observations at poses ``z [..., K, 3]``:
        the scan ``x [..., B]`` (``mask [..., B]``) under the map ``M [w, h, D]`` or marginalised
        over a :class:`~pyro_slam.model.MapBelief`, plus the heading factor's log-density of
        ``heading`` (:class:`~pyro_slam.model.HeadingEvidence`, batch ``[...]``). Returns
        ``(loglik [..., K], scan [..., K, B])``, the scans predicted at the map (mean)."""
        m = self.model
        eps = None
        obs = x.unsqueeze(-2)  # [..., 1, B]
        if isinstance(M, MapBelief):
            scan, eps = m.marginal_emission(M, z, obs)
        elif self.autocast_dtype is not None and not torch.is_grad_enabled():
            with torch.autocast(z.device.type, dtype=self.autocast_dtype):
                scan = m.emission_mean(M, z, obs).to(z.dtype)  # [..., K, B]
        else:
            scan = m.emission_mean(M, z, obs)  # [..., K, B]
        mask = None if mask is None else mask.unsqueeze(-2)
        ll = m.emission_log_prob(obs, scan, mask, outlier_prob=eps)
        if heading is not None and m.heading is not None:
            ll = ll + m.heading_log_prob(z[..., 2], heading.per_particle())
        return ll, scan

    def state_dict(self) -> dict:
        """What the next step reads besides the particles and the run's generator: nothing (the
        weights are the model's, the proposal keeps no state); kept so that a checkpoint stores
        any filter alike."""
        return {}

    def load_state_dict(self, d: dict) -> None:
        """Restore :meth:`state_dict`; ``TypeError`` for anything but a dict."""
        if not isinstance(d, dict):
            raise TypeError(f"a filter state must be a dict, got {type(d).__name__}")

    def _weigh(self, z, M, x, mask, logw, step, correction=None, heading=None):
        """Weigh poses ``z [..., K, 3]`` (plus ``correction [..., K]``, the proposal's log
        transition-over-proposal density ratio). Returns new particles and the log-evidence
        increment ``[...]``."""
        loglik, scan = self.log_likelihood(z, M, x, mask, heading)
        if correction is not None:
            loglik = loglik + correction
        joint = logw + loglik
        resampling.check_weights(joint.detach(), step)
        inc = torch.logsumexp(joint, -1)  # [...]
        # normalised weights keep their graph: without resampling, the next step's evidence
        # depends on the map through them too (resampling resets them to constants)
        return Particles(z, joint - inc.unsqueeze(-1), scan.detach()), inc

    def init(self, z0, M, x, mask=None, step=0, heading: HeadingEvidence | None = None):
        """Weigh initial particles ``z0 [..., K, 3]`` by ``x [..., B]`` (and ``heading``).

        Returns ``(particles, log_evidence [...])`` with ``log p^(x_0) = log mean_k p(x_0|z^k)``.
        """
        K = z0.shape[-2]
        logw = z0.new_full(z0.shape[:-1], -math.log(K))
        return self._weigh(z0.detach(), M, x, mask, logw, step, heading=heading)

    def propagate(self, p: Particles, u: torch.Tensor) -> torch.Tensor:
        """Sample ``z_{t+1} ~ p(. | z_t, u_t, mu_E(m_t))``: ``[..., K, 3]`` (no gradient)."""
        return TransitionProposal().propose(self.model, p, u, self.generator)[0]

    def resample_if_needed(self, p: Particles) -> Particles:
        """Resample the batch elements whose ESS is below ``ess_threshold * K``; the result's
        ``ancestors`` index ``p``'s particles."""
        need = resampling.ess(p.logw) < self.ess_threshold * p.num_particles  # [...]
        if not bool(need.any()):
            return Particles(p.z, p.logw, p.scan, p.identity())
        r = p.resample(self.generator, self.scheme)
        if bool(need.all()):
            return r
        return r.where(need, Particles(p.z, p.logw, p.scan, p.identity()))

    def step(self, p: Particles, M, x, u, mask=None, step=None, heading=None):
        """One filtering step: resample if needed, propose with ``u [..., D_u]`` (the proposal
        may read the scan ``x [..., B]``, the map and the step's ``heading`` evidence), weigh.

        Returns ``(particles, log_evidence_increment [...])``.
        """
        p = self.resample_if_needed(p)
        z, correction = self.proposal.propose(
            self.model, p, u, self.generator, x=x, mask=mask, M=M, heading=heading
        )
        new, inc = self._weigh(z, M, x, mask, p.logw, step, correction, heading)
        new.ancestors = p.ancestors
        return new, inc

    @torch.no_grad()
    def run(self, M, observations, controls, init_pose, num_particles, mask=None, init_scale=None):
        """Filter a whole sequence with a fixed map (no gradients).

        Args:
            M: map ``[w, h, D]``; observations ``[T, B]``; controls ``[T-1, D_u]``;
            init_pose ``[3]``; mask ``[T, B]`` or None.
        Returns:
            dict with ``mean [T, 3]`` (heading wrapped), ``std [T, 3]``, ``log_evidence`` (float)
            and the final :class:`Particles`.
        """
        scale = self.model.init_scale if init_scale is None else torch.as_tensor(init_scale)
        z0 = init_pose + scale * torch.randn(
            num_particles, 3, generator=self.generator, dtype=init_pose.dtype
        )
        p, ev = self.init(z0, M, observations[0], None if mask is None else mask[0], step=0)
        means, stds = [p.mean()], [p.std()]
        for t in range(1, observations.shape[0]):
            m = None if mask is None else mask[t]
            p, inc = self.step(p, M, observations[t], controls[t - 1], m, step=t)
            ev = ev + inc
            means.append(p.mean())
            stds.append(p.std())
        return {
            "mean": torch.stack(means),
            "std": torch.stack(stds),
            "log_evidence": float(ev),
            "particles": p,
        }
