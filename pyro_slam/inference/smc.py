"""Pyro's :class:`pyro.infer.SMCFilter` on the same model, with the interface of
:class:`~.filter.ParticleFilter` (``init``, ``step``, ``cloud_trust``): a drop-in, slower filter
for the SLAM loop (``SLAM(..., smc=True)``). The proposal is the model's transition
(:class:`~pyro_slam.model.BootstrapGuide`) and the weights are the SLAM filter's
(:class:`~.weighting.Weighting`, from the model's emission noise) through
:class:`~pyro_slam.model.FilterModel`. It keeps no autograd graph, so the training ELBO keeps
our filter; per-cloud weights (``"shared"``) and the heading observation need the cloud's
weights inside the model step and are refused."""

from __future__ import annotations

import torch
from pyro.infer import SMCFilter

from ..model import BootstrapGuide, FilterModel
from .particles import Particles
from .weighting import MapBelief, Weighting


class PyroSMCFilter:
    """:class:`pyro.infer.SMCFilter` behind the :class:`~.filter.ParticleFilter` interface.

    Args:
        model: the :class:`~pyro_slam.model.DVBFLM`.
        weighting: the particle weights (``"marginal"`` or ``"tempered"``).
        ess_threshold: resample when ``ESS < ess_threshold * K``.
    """

    def __init__(self, model, weighting: Weighting | None = None, ess_threshold: float = 0.5):
        self.model = model
        self.weighting = Weighting() if weighting is None else weighting
        if self.weighting.kind == "shared":
            raise ValueError("Pyro's SMCFilter weighs each particle alone: 'shared' is refused")
        self.ess_threshold = ess_threshold
        self.smc: SMCFilter | None = None
        self._belief: MapBelief | torch.Tensor | None = None
        self.last_cloud_trust: torch.Tensor | None = None  # (not tracked: computed on demand)

    def _weights(self, z, x, mask):
        log_lik, scan, _ = self.weighting.log_likelihood(self.model, z, self._belief, x, mask)
        return log_lik, scan

    def state_dict(self) -> dict:
        """Nothing beyond the particles (the interface of :class:`~.filter.ParticleFilter`)."""
        return {}

    def load_state_dict(self, d: dict) -> None:
        if d:
            raise KeyError(f"unexpected filter state {sorted(d)}")

    def trust(self, z, M: MapBelief) -> torch.Tensor:
        return self.weighting.trust(self.model, z, M)

    def cloud_trust(self, p: Particles, M: MapBelief) -> torch.Tensor:
        return (p.logw.exp() * self.trust(p.z, M).mean(-1)).sum(-1)

    def _particles(self) -> Particles:
        logw = self.smc.get_empirical()["z"].log_weights.clone()  # (updated in place)
        logw = logw - torch.logsumexp(logw, -1)
        return Particles(self.smc.state["z"].clone(), logw, self.smc.state["scan"].clone())

    @torch.no_grad()
    def init(self, z0, M, x, mask=None, step=0):
        """Start from the initial pose prior around the mean of ``z0 [K, 3]`` and weigh ``x``.
        Returns ``(particles, nan)`` (SMCFilter tracks no evidence)."""
        self._belief = M
        fm = FilterModel(self.model, None, self._weights)
        self.smc = SMCFilter(fm, BootstrapGuide(self.model), z0.shape[-2], max_plate_nesting=0,
                             ess_threshold=self.ess_threshold)  # fmt: skip
        self.smc.init(init_pose=z0.mean(-2), x=x, mask=mask)
        return self._particles(), torch.tensor(float("nan"))

    @torch.no_grad()
    def step(self, p, M, x, u, mask=None, step=None, sigma=None, heading=None):
        """One SMCFilter step (``p`` is its own state, returned by the last call)."""
        if heading is not None:
            raise ValueError("Pyro's SMCFilter drop-in does not take the heading observation")
        self._belief = M
        self.smc.step(x, u, mask=mask, sigma=sigma)
        return self._particles(), torch.tensor(float("nan"))
