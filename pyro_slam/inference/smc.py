"""Pyro's :class:`pyro.infer.SMCFilter` on the same model, with the interface of
:class:`~.filter.ParticleFilter` (``init``, ``step``): a drop-in, slower filter for the SLAM loop
(``SLAM(..., smc=True)``). The model step is :class:`~pyro_slam.model.FilterModel`, the model's
own one-step :class:`~pyro_slam.model.Window` under its handlers (the transition, the scan under
the map belief through the model's stated marginalisation, the heading factor), and the guide
step samples the same :class:`~.proposals.Proposal` as ours (:class:`ProposalGuide`), so
SMCFilter's own ``p / q`` weights are ours. :class:`EvidenceSMCFilter` adds the log-evidence
estimate, which SMCFilter itself does not keep. It keeps no autograd graph, so the training ELBO
keeps our filter."""

from __future__ import annotations

import math

import pyro
import pyro.distributions as dist
import torch
from pyro.infer import SMCFilter
from pyro.poutine.util import prune_subsample_sites

from ..model import FilterModel
from .filter import resolve_globals
from .particles import Particles
from .proposals import Proposal, TransitionProposal


class ProposalGuide:
    """A :class:`~.proposals.Proposal` as the guide object of :class:`pyro.infer.SMCFilter`:
    ``init`` draws the initial poses ``z_0`` from the model's prior, ``step`` samples the site
    ``z_t`` from the proposal at the state's particles (``M``: the map or map belief the
    proposal may read, set by the caller before each step)."""

    def __init__(self, model, proposal: Proposal, M=None):
        self.m, self.proposal, self.M = model, proposal, M

    def init(self, state, init_pose, x=None, mask=None, heading=None):
        pyro.sample("z_0", dist.Normal(init_pose, self.m.init_scale).to_event(1))

    def step(self, state, t, x, u, mask=None, heading=None):
        if heading is not None:
            heading = heading.per_particle()
        q = self.proposal.dist(
            self.m, state["z"], state["scan"], u, x=x, mask=mask, M=self.M, heading=heading
        )
        pyro.sample(f"z_{t}", q)


class EvidenceSMCFilter(SMCFilter):
    """:class:`pyro.infer.SMCFilter` that also estimates the log-evidence: ``log_evidence``
    is the sum over steps of ``log sum_k w_{t-1,k} exp(delta_k)``, with ``w_{t-1}`` the
    normalised weights before the step and ``delta`` each particle's incremental log-weight
    (model minus guide log-densities of the step's sites, observed sites included), taken
    before any resampling. (Reading ``state`` after a step is not enough: SMCFilter resamples
    the state, and resets the weights, inside ``step``.)"""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.log_evidence = 0.0
        self.last_increment = math.nan

    @torch.no_grad()
    def _update_weights(self, model_trace, guide_trace):
        model_trace = prune_subsample_sites(model_trace)
        guide_trace = prune_subsample_sites(guide_trace)
        model_trace.compute_log_prob()
        guide_trace.compute_log_prob()
        delta = torch.zeros(self.num_particles)
        for name, site in guide_trace.nodes.items():
            if site["type"] == "sample":
                lp = model_trace.nodes[name]["log_prob"] - site["log_prob"]
                delta = delta + lp.reshape(self.num_particles, -1).sum(-1)
        for site in model_trace.nodes.values():
            if site["type"] == "sample" and site["is_observed"]:
                delta = delta + site["log_prob"].reshape(self.num_particles, -1).sum(-1)
        prev = self.state._log_weights
        prev = prev - prev.logsumexp(-1)
        self.last_increment = float(torch.logsumexp(prev + delta, -1))
        self.log_evidence += self.last_increment
        super()._update_weights(model_trace, guide_trace)


class PyroSMCFilter:
    """:class:`EvidenceSMCFilter` behind the :class:`~.filter.ParticleFilter` interface.

    Args:
        model: the :class:`~pyro_slam.model.DVBFLM` (its handlers included).
        proposal: the pose proposal (default: the transition).
        ess_threshold: resample when ``ESS < ess_threshold * K``.
    """

    def __init__(
        self,
        model,
        proposal: Proposal | None = None,
        ess_threshold: float = 0.5,
    ):
        self.model = model
        self.proposal = TransitionProposal() if proposal is None else proposal
        self.ess_threshold = ess_threshold
        self.smc: EvidenceSMCFilter | None = None
        self._fm: FilterModel | None = None
        self._guide: ProposalGuide | None = None
        self._t = 0  # the last step

    def _logw(self) -> torch.Tensor:
        """The cloud's normalised log weights ``[K]`` (a copy: SMCFilter updates in place)."""
        logw = self.smc.get_empirical()["z"].log_weights.clone()
        return logw - torch.logsumexp(logw, -1)

    def state_dict(self) -> dict:
        """Nothing beyond the particles (the interface of :class:`~.filter.ParticleFilter`)."""
        return {}

    def load_state_dict(self, d: dict) -> None:
        if d:
            raise KeyError(f"unexpected filter state {sorted(d)}")

    def _particles(self) -> Particles:
        return Particles(self.smc.state["z"].clone(), self._logw(), self.smc.state["scan"].clone())

    def _set_map(self, M, heading) -> None:
        """The step's global values (under the model's handlers, :func:`~.filter.
        resolve_globals`) for the model and the guide."""
        M, frame, _ = resolve_globals(self.model, M, heading)
        self._fm.M = self._guide.M = M
        self._fm.frame = frame

    @torch.no_grad()
    def init(self, z0, M, x, mask=None, step=0, heading=None):
        """Start from the initial pose prior around the mean of ``z0 [K, 3]`` and weigh ``x``.
        Returns ``(particles, log-evidence increment)``."""
        self._fm = FilterModel(self.model, M)
        self._guide = ProposalGuide(self.model, self.proposal, M)
        self._set_map(M, heading)
        self.smc = EvidenceSMCFilter(
            self._fm,
            self._guide,
            z0.shape[-2],
            max_plate_nesting=0,
            ess_threshold=self.ess_threshold,
        )
        self._t = int(step)
        with pyro.validation_enabled(False):
            self.smc.init(init_pose=z0.mean(-2), x=x, mask=mask, heading=heading)
        return self._particles(), torch.tensor(self.smc.last_increment)

    @torch.no_grad()
    def step(self, p, M, x, u, mask=None, step=None, heading=None):
        """One SMCFilter step (``p`` is its own state, returned by the last call)."""
        self._set_map(M, heading)
        self._t = self._t + 1 if step is None else int(step)  # (the sites' names)
        with pyro.validation_enabled(False):
            self.smc.step(self._t, x, u, mask=mask, heading=heading)
        return self._particles(), torch.tensor(self.smc.last_increment)
