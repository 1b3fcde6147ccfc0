"""Pyro's :class:`pyro.infer.SMCFilter` on the same model, with the interface of
:class:`~.filter.ParticleFilter` (``init``, ``step``): a drop-in, slower filter for the SLAM loop
(``SLAM(..., smc=True)``). The model step is :class:`~pyro_slam.model.FilterModel` (the
transition, the scan under the map belief through the model's stated marginalisation, the
heading factor) and the guide step samples the same :class:`~.proposals.Proposal` as ours
(:class:`ProposalGuide`), so SMCFilter's own ``p / q`` weights are ours. It keeps no autograd
graph, so the training ELBO keeps our filter."""

from __future__ import annotations

import pyro
import pyro.distributions as dist
import torch
from pyro.infer import SMCFilter

from ..model import FilterModel
from .particles import Particles
from .proposals import Proposal, TransitionProposal


class ProposalGuide:
    """A :class:`~.proposals.Proposal` as the guide object of :class:`pyro.infer.SMCFilter`:
    ``init`` draws the initial poses from the model's prior, ``step`` samples the site ``"z"``
    from the proposal at the state's particles (``M``: the map or map belief the proposal may
    read, set by the caller before each step)."""

    def __init__(self, model, proposal: Proposal, M=None):
        self.m, self.proposal, self.M = model, proposal, M

    def init(self, state, init_pose, x=None, mask=None, heading=None):
        pyro.sample("z", dist.Normal(init_pose, self.m.init_scale).to_event(1))

    def step(self, state, x, u, mask=None, heading=None):
        q = self.proposal.dist(
            self.m, state["z"], state["scan"], u, x=x, mask=mask, M=self.M, heading=heading
        )
        pyro.sample("z", q)


class PyroSMCFilter:
    """:class:`pyro.infer.SMCFilter` behind the :class:`~.filter.ParticleFilter` interface.

    Args:
        model: the :class:`~pyro_slam.model.DVBFLM`.
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
        self.smc: SMCFilter | None = None
        self._fm: FilterModel | None = None
        self._guide: ProposalGuide | None = None

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

    def _set_map(self, M) -> None:
        self._fm.M = self._guide.M = M

    @torch.no_grad()
    def init(self, z0, M, x, mask=None, step=0, heading=None):
        """Start from the initial pose prior around the mean of ``z0 [K, 3]`` and weigh ``x``.
        Returns ``(particles, nan)`` (SMCFilter tracks no evidence)."""
        self._fm = FilterModel(self.model, M)
        self._guide = ProposalGuide(self.model, self.proposal, M)
        self.smc = SMCFilter(
            self._fm,
            self._guide,
            z0.shape[-2],
            max_plate_nesting=0,
            ess_threshold=self.ess_threshold,
        )
        self.smc.init(init_pose=z0.mean(-2), x=x, mask=mask, heading=heading)
        return self._particles(), torch.tensor(float("nan"))

    @torch.no_grad()
    def step(self, p, M, x, u, mask=None, step=None, heading=None):
        """One SMCFilter step (``p`` is its own state, returned by the last call)."""
        self._set_map(M)
        self.smc.step(x, u, mask=mask, heading=heading)
        return self._particles(), torch.tensor(float("nan"))
