"""Guides (variational posteriors) of DVBF-LM.

* :class:`MapGuide` -- mean-field Gaussian ``q(M) = prod_ij N(mu_ij, sigma_ij^2)`` with
  ``pyro.param`` mean and scale (paper III-C). Any Pyro guide over the site ``"map"`` can
  replace it (:func:`autoguide` builds Pyro's autoguides over the map site alone); the particle
  filter reads a guide's marginal mean and std through :func:`map_marginals`.
* :class:`FrameGuide` -- ``q(phi) = N(mean, var)`` of the walls' frame of the heading factor,
  fitted by Kalman updates from the data (:mod:`pyro_slam.slam.heading`) rather than by SVI.
* :class:`GlobalGuide` -- a map guide and (with a heading factor) the frame guide: the guide of
  the model's global sites ``"map"`` and ``"frame"``.
* The SMC guides over poses are the proposals of :mod:`pyro_slam.inference.proposals`.
"""

from __future__ import annotations

import contextlib
import math

import pyro
import pyro.distributions as dist
import torch
from pyro import poutine
from pyro.distributions import constraints
from pyro.infer.autoguide import AutoDelta
from torch.distributions import biject_to, kl_divergence

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


class FrameGuide:
    """``q(phi) = N(mean, var)``, the walls' frame of the model's heading factor (site
    ``"frame"``). Its mean and variance are set by an estimator outside SVI (Kalman updates
    from the scans' wall directions, :class:`~pyro_slam.slam.heading.ManhattanHeading`); nan:
    no frame known yet (the heading evidence is then not used)."""

    def __init__(self, mean: float = math.nan, var: float = math.inf):
        self.mean, self.var = float(mean), float(var)

    def __call__(self, *args, **kwargs):
        if math.isnan(self.mean):
            return None
        return pyro.sample("frame", dist.Normal(torch.tensor(self.mean), math.sqrt(self.var)))

    def state_dict(self) -> dict:
        return {"mean": self.mean, "var": self.var}

    def load_state_dict(self, d: dict) -> None:
        self.mean, self.var = float(d["mean"]), float(d["var"])


class GlobalGuide:
    """The guide of the model's global sites: a map guide (any guide over the site ``"map"``,
    called with the model's arguments) and, where given, a :class:`FrameGuide` (the site
    ``"frame"``). Returns ``(M, phi)``."""

    def __init__(self, map_guide, frame: FrameGuide | None = None):
        self.map, self.frame = map_guide, frame

    def __call__(self, *args, **kwargs):
        M = self.map(*args, **kwargs)
        if isinstance(M, dict):  # an autoguide returns its sample by site
            M = M["map"]
        return M, None if self.frame is None else self.frame()


def autoguide(cls, **kwargs):
    """A guide factory for :class:`~pyro_slam.slam.SLAM`'s ``guide`` argument: Pyro's autoguide
    ``cls`` (e.g. ``AutoNormal``, ``AutoLowRankMultivariateNormal``) over the model's map site
    alone, built with ``kwargs`` (e.g. ``init_scale=1.0``)."""

    def make(model: DVBFLM):
        def map_site(*args, **kw):  # whatever the inference passes the guide
            return model.sample_map()

        return cls(poutine.block(map_site, expose=["map"]), **kwargs)

    return make


# the standard normal's quantile at one std above the median
ONE_SIGMA = 0.8413447460685429


def map_marginals(guide, args=()) -> tuple[torch.Tensor, torch.Tensor]:
    """The marginal mean and std ``[w, h, D_m]`` of a map guide's ``q(M)``: from its
    ``params()`` (:class:`MapGuide` and any guide with that method), from Pyro's public
    ``quantiles`` (autoguides: median and the one-sigma quantile, exact for Gaussian
    marginals), from ``median`` with a zero std for a point estimate (``AutoDelta``), or else
    from 64 draws of the site (``args``: the model's arguments, which the guide is called
    with)."""
    if hasattr(guide, "params"):
        return guide.params()
    if isinstance(guide, AutoDelta):
        loc = guide.median(*args)["map"]
        return loc, torch.zeros_like(loc)
    try:
        q = guide.quantiles([0.5, ONE_SIGMA], *args)["map"]  # [2, w, h, D_m]
        return q[0], q[1] - q[0]
    except (AttributeError, NotImplementedError):
        draws = sample_maps(guide, 64, args)  # [64, w, h, D_m]
        return draws.mean(0), draws.std(0)


class MapLeaves:
    """Where a map guide keeps ``q(M)``'s marginal mean and std in Pyro's parameter store, for
    reading and writing them per grid point (scan insertion): views ``loc [w, h, D]`` and
    ``raw [w, h, D]`` (the unconstrained scale) of the store's leaf tensors, and, for a low-rank
    guide, its ``cov_factor [w, h, D, r]``, whose rows' norm ``sqrt(1 + |row|^2)`` is the factor
    by which the marginal std exceeds the diagonal ``scale``. Build with :meth:`of`."""

    def __init__(self, loc, raw, constraint, cov_factor=None):
        self.loc, self.raw, self.cov_factor = loc, raw, cov_factor
        self.transform = biject_to(constraint)
        self._std, self._var = None, None  # the kept std and variance [w, h, D]
        self._seen = -1  # the raw scale's version they are of

    def marginals(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """``q(M)``'s marginal mean, std and variance ``[w, h, D]`` (detached; all change in
        place with the guide), the std and variance kept between calls: :meth:`write` updates
        the grid points it writes, any other change of the raw scale (an SVI step) recomputes
        them. None for a low-rank guide."""
        if self.cov_factor is not None:
            return None
        if self._std is None or self._seen != self.raw._version:
            with torch.no_grad():
                self._std = self.transform(self.raw)
                self._var = self._std**2
            self._seen = self.raw._version
        return self.loc.detach(), self._std, self._var

    def _factor(self, i, j):
        """``[P]``: the marginal std over the diagonal scale at ``(i, j)`` (1 without a
        low-rank part)."""
        if self.cov_factor is None:
            return 1.0
        return (1 + self.cov_factor[i, j, 0].detach().pow(2).sum(-1)).sqrt()

    @classmethod
    def of(cls, guide, shape) -> MapLeaves | None:
        """The leaves of ``guide`` for a map of ``shape`` ``(w, h, D)``; None where the guide
        keeps no such parameters. The protocol, met by :class:`MapGuide` and by Pyro's
        :class:`~pyro.infer.autoguide.AutoNormal`, :class:`~pyro.infer.autoguide.
        AutoDiagonalNormal` and :class:`~pyro.infer.autoguide.AutoLowRankMultivariateNormal`
        over the map site alone: parameters named ``{prefix}_loc``/``{prefix}_scale``
        (``guide.prefix``), ``{name}.locs.map``/``{name}.scales.map``, or ``{name}.loc``/
        ``{name}.scale`` (a flat vector of the map's entries, with ``{name}.cov_factor`` for the
        low-rank guide, whose marginal std is ``scale * sqrt(1 + |cov_factor row|^2)``)."""
        store = pyro.get_param_store()
        if isinstance(guide, MapGuide):
            names = (f"{guide.prefix}_loc", f"{guide.prefix}_scale")
        else:
            name = getattr(guide, "_pyro_name", None)
            names = next(
                (
                    (f"{name}.{a}", f"{name}.{b}")
                    for a, b in (("locs.map", "scales.map"), ("loc", "scale"))
                    if f"{name}.{a}" in store and f"{name}.{b}" in store
                ),
                None,
            )
        if names is None or any(n not in store for n in names):
            return None
        raw = dict(store.named_parameters())
        loc, scale = raw[names[0]], raw[names[1]]
        if loc.numel() != math.prod(shape) or scale.numel() != loc.numel():
            return None
        cov = names[0][: -len("loc")] + "cov_factor"
        low_rank = not isinstance(guide, MapGuide) and cov in store
        cov = raw[cov].view(*shape, -1) if low_rank else None
        return cls(loc.view(shape), scale.view(shape), store._constraints[names[1]], cov)

    def read(self, i, j) -> tuple[torch.Tensor, torch.Tensor]:
        """``q(M)``'s marginal mean and std of the first feature at grid points ``(i [P], j
        [P])``: ``([P], [P])``."""
        with torch.no_grad():
            std = self.transform(self.raw[i, j, 0]) * self._factor(i, j)
            return self.loc[i, j, 0].clone(), std

    def write(self, i, j, loc, std) -> None:
        """Set the marginal mean ``loc`` and std ``std`` (``[P]`` or numbers) of the first
        feature at grid points ``(i [P], j [P])``."""
        kept = self._std is not None and self._seen == self.raw._version
        with torch.no_grad():
            std = torch.as_tensor(std, dtype=self.raw.dtype) / self._factor(i, j)
            self.loc[i, j, 0] = torch.as_tensor(loc, dtype=self.loc.dtype)
            self.raw[i, j, 0] = self.transform.inv(std)
            if kept:
                self._std[i, j, 0] = self.transform(self.raw[i, j, 0])
                self._var[i, j, 0] = self._std[i, j, 0] ** 2
                self._seen = self.raw._version


class ParamScope:
    """A parameter store of one's own (:meth:`pyro.params.param_store.ParamStoreDict.scope`):
    ``with scope():`` runs the enclosed code with these parameters in Pyro's store and restores
    the caller's afterwards; re-entrant. Objects that train (a SLAM run, exploration's mapper)
    keep one each, so two of them never share or clear each other's parameters."""

    def __init__(self):
        self.state = {"params": {}, "constraints": {}}
        self._depth = 0

    @contextlib.contextmanager
    def __call__(self):
        if self._depth:
            yield
            return
        self._depth += 1
        try:
            with pyro.get_param_store().scope(self.state):
                yield
        finally:
            self._depth -= 1


def sample_maps(guide, n: int, args=()) -> torch.Tensor:
    """``n`` draws of the site ``"map"`` from a map guide (called with ``args``):
    ``[n, w, h, D_m]``."""
    with torch.no_grad():
        draws = [poutine.trace(guide).get_trace(*args).nodes["map"]["value"] for _ in range(n)]
    return torch.stack(draws)


def map_kl(loc: torch.Tensor, scale: torch.Tensor, prior, samples: int = 64) -> torch.Tensor:
    """``KL(q(M) || p(M))`` (nats, summed over cells and features) of a mean-field Gaussian
    belief ``N(loc, scale^2)`` ``[w, h, D]`` against the map prior (event ``[D]``): analytic
    where torch has it, else a Monte Carlo estimate from ``samples`` draws."""
    q = dist.Normal(loc, scale).to_event(1)
    try:
        return kl_divergence(q, prior).sum()
    except NotImplementedError:
        m = q.sample((samples,))
        return (q.log_prob(m) - prior.log_prob(m)).sum(-1).sum(-1).mean()
