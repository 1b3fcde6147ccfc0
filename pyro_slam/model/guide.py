"""Guides (variational posteriors) of DVBF-LM.

* :class:`MapGuide` -- mean-field Gaussian ``q(M) = prod_ij N(mu_ij, sigma_ij^2)`` with
  ``pyro.param`` mean and scale (paper III-C). Any Pyro guide over the site ``"map"`` can
  replace it (:func:`autoguide` builds Pyro's autoguides over the map site alone); the particle
  filter reads a guide's marginal mean and std through :func:`map_marginals`.
* :class:`BootstrapGuide` -- the pose proposal of a bootstrap particle filter, as a guide object
  with ``init``/``step`` for :class:`pyro.infer.SMCFilter`.
* The custom SMC guide over poses used for *training* is the differentiable particle filter of
  :mod:`pyro_slam.inference`; it is bootstrap, so its weights are the emission likelihoods under
  the sampled map.
"""

from __future__ import annotations

import pyro
import pyro.distributions as dist
import torch
from pyro import poutine
from pyro.distributions import constraints

from .model import DVBFLM


class MapGuide:
    """Mean-field Gaussian ``q(M)``; initialised at the prior (mean 0, scale 1).

    Args:
        shape: ``(w, h, D_m)``.
        init_scale: initial std (paper: 1).
        prefix: name prefix of the two ``pyro.param`` sites (``{prefix}_loc``, ``{prefix}_scale``).
    """

    def __init__(self, shape, init_scale: float | torch.Tensor = 1.0, prefix: str = "map"):
        self.shape, self.init_scale, self.prefix = tuple(shape), init_scale, prefix

    def params(self):
        """``(loc, scale)``, each ``[w, h, D_m]``."""
        loc = pyro.param(f"{self.prefix}_loc", lambda: torch.zeros(self.shape))
        scale = pyro.param(
            f"{self.prefix}_scale",
            lambda: torch.as_tensor(self.init_scale, dtype=loc.dtype).expand(self.shape).clone(),
            constraint=constraints.positive,
        )
        return loc, scale

    def distribution(self):
        loc, scale = self.params()
        return dist.Normal(loc, scale).to_event(1)

    def __call__(self, *args, **kwargs) -> torch.Tensor:
        w, h, _ = self.shape
        with pyro.plate("map_x", w, dim=-2), pyro.plate("map_y", h, dim=-1):
            return pyro.sample("map", self.distribution())

    def mean(self) -> torch.Tensor:
        return self.params()[0].detach()


def autoguide(cls, **kwargs):
    """A guide factory for :class:`~pyro_slam.slam.SLAM`'s ``guide`` argument: Pyro's autoguide
    ``cls`` (e.g. ``AutoNormal``, ``AutoLowRankMultivariateNormal``) over the model's map site
    alone, built with ``kwargs`` (e.g. ``init_scale=1.0``)."""

    def make(model: DVBFLM):
        return cls(poutine.block(model.sample_map, expose=["map"]), **kwargs)

    return make


# the standard normal's quantile at one std above the median
ONE_SIGMA = 0.8413447460685429


def map_marginals(guide) -> tuple[torch.Tensor, torch.Tensor]:
    """The marginal mean and std ``[w, h, D_m]`` of a map guide's ``q(M)``: from its
    ``params()`` (:class:`MapGuide` and any guide with that method), or from Pyro's public
    ``quantiles`` (autoguides: median and the one-sigma quantile, exact for Gaussian
    marginals)."""
    if hasattr(guide, "params"):
        return guide.params()
    if hasattr(guide, "quantiles"):
        q = guide.quantiles([0.5, ONE_SIGMA])["map"]  # [2, w, h, D_m]
        return q[0], q[1] - q[0]
    raise TypeError(
        f"a map guide needs params() -> (loc, scale) or Pyro's quantiles(); got "
        f"{type(guide).__name__}"
    )


class BootstrapGuide:
    """Proposal ``q(z_t | z_{t-1}) = p(z_t | z_{t-1}, u, m_{t-1})`` for :class:`SMCFilter`."""

    def __init__(self, dvbflm: DVBFLM):
        self.m = dvbflm

    def init(self, state, init_pose, x=None, mask=None):
        pyro.sample("z", dist.Normal(init_pose, self.m.init_scale).to_event(1))

    def step(self, state, x, u, mask=None, sigma=None):
        pyro.sample("z", self.m.transition_dist(state["z"], u, state["scan"], sigma))
