"""How the particle filter weighs a pose by a scan under a map belief.

The filter weighs each particle ``z`` by the emission likelihood ``p(x | z, M)``. Under a
mean-field map belief ``q(M)`` (a :class:`MapBelief`) the map is not known, and a
:class:`Weighting` says how its uncertainty enters: the chart's variance under ``q(M)``
relative to the prior's gives a *trust* in ``[0.01, 1]`` per particle (or per beam), and

* ``"marginal"``: the map mean with the emission std inflated to ``sigma / trust`` (an
  approximate marginalisation of ``q(M)``: flat weights where the map is still at its prior);
* ``"shared"``: the same with one trust for the whole cloud (the weighted mean), so the
  normaliser ``-B log sigma`` cancels and cannot favour particles in cells written more often;
* ``"tempered"``: the likelihood raised to ``trust^2`` without the normaliser, so unmapped
  charts are neutral.

``outlier_prob = eps > 0``: tempered weights get a floor ``log eps`` per beam; the others the
classic beam mixture ``(1 - eps) N(x; mu, sigma) + eps / outlier_range`` (Thrun et al.,
*Probabilistic Robotics* 6.3), so a few beams the map cannot explain cannot dominate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

WEIGHTINGS = ("marginal", "shared", "tempered")


@dataclass
class MapBelief:
    """A Gaussian map belief, ``loc`` and ``scale`` ``[w, h, D]`` (e.g. a mean-field ``q(M)``)."""

    loc: torch.Tensor
    scale: torch.Tensor


class Weighting:
    """The filter's particle weights (module doc).

    Args:
        kind: ``"marginal"``, ``"shared"`` or ``"tempered"``.
        sigma: emission std of the weights (None: the model's ``sigma_E``; the paper filters
            with a smaller one, Appendix B-I).
        outlier_prob: per-beam outlier probability ``eps`` in ``[0, 1)``.
        outlier_range: width of the uniform outlier density (the sensor's range).
        per_beam: with an emission that has ``beam_variance``
            (:class:`~pyro_slam.model.RayEmission`), one trust per beam from the map's variance
            where that beam stops, instead of one per particle from its own chart.
    """

    def __init__(
        self,
        kind: str = "marginal",
        sigma: float | None = None,
        outlier_prob: float = 0.0,
        outlier_range: float = 1.0,
        per_beam: bool = False,
    ):
        if kind not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {kind!r}")
        if sigma is not None and not sigma > 0:
            raise ValueError(f"the weights' sigma must be positive, got {sigma!r}")
        if not 0.0 <= outlier_prob < 1.0:
            raise ValueError(f"outlier_prob must be in [0, 1), got {outlier_prob!r}")
        if not outlier_range > 0:
            raise ValueError(f"outlier_range must be positive, got {outlier_range!r}")
        self.kind, self.sigma = kind, sigma
        self.outlier_prob, self.outlier_range = outlier_prob, outlier_range
        self.per_beam = bool(per_beam)

    def check(self, model) -> None:
        """Raise if this weighting cannot be used with ``model``'s emission."""
        if self.per_beam and not hasattr(model.emission, "beam_variance"):
            raise ValueError(
                "per-beam trust needs an emission with beam_variance (RayEmission), "
                f"got {type(model.emission).__name__}"
            )

    def trust(self, model, z: torch.Tensor, M: MapBelief) -> torch.Tensor:
        """How far the weights trust ``M`` at poses ``z [..., K, 3]``: ``[..., K, 1]`` (per
        beam ``[..., K, B]``) in ``[0.01, 1]``: one minus the chart's variance under ``M``
        relative to the map prior's (``model.prior_std()``; of the first
        ``emission.trust_features`` features where the emission says so). Charts of cells
        still at the prior (relative variance 1) give flat weights."""
        return self._read(model, z, M, scan=False)[1]

    def _read(self, model, z, M: MapBelief, scan: bool = True):
        """The predicted scans at the map mean (if ``scan``) and the trust, sharing one march
        along the beams where the trust is per beam."""
        g = model.grid
        scale = M.scale / model.prior_std()  # [w, h, D] relative to the prior
        if self.per_beam:
            pred, var = model.emission.range_and_variance(g, M.loc, scale, z)  # [..., K, B]
        else:
            n = getattr(model.emission, "trust_features", None)  # None: every feature
            scale = scale if n is None else scale[..., :n]
            var = g.relative_variance(scale, z[..., :2])  # [..., K, 1]
            pred = model.emission_mean(M.loc, z) if scan else None
        return pred, (1.0 - var).clamp_min(1e-2)

    def log_likelihood(self, model, z, M, x, mask=None, logw=None, autocast_dtype=None):
        """Log weights of poses ``z [..., K, 3]`` for the scan ``x [..., B]`` (``mask [..., B]``)
        under ``M``, a map ``[w, h, D]`` or a :class:`MapBelief`; ``logw [..., K]`` the prior
        weights (``"shared"`` averages the trust with them). The per-beam density is the
        model's emission noise (``model.noise_dist``) with this weighting's scale. Returns
        ``(loglik [..., K], scan [..., K, B], trust)``: the predicted scans at the map mean and
        the trust (None for a plain map)."""
        sigma = self.sigma if self.sigma is not None else model.sigma_emission
        s0, beta, trust = sigma, None, None
        if isinstance(M, MapBelief):
            scan, trust = self._read(model, z, M)  # [..., K, B], [..., K, 1 | B]
            shared = trust
            if self.kind == "shared":
                shared = (logw.exp().unsqueeze(-1) * trust).sum(-2, keepdim=True)  # [..., 1, 1]
            if self.kind == "tempered":
                beta = shared**2  # p(x | z, E[M])^beta, without the normaliser
            else:
                sigma = s0 / shared
        elif autocast_dtype is not None and not torch.is_grad_enabled():
            # reduced-precision emission for filtering only (training keeps full precision)
            with torch.autocast(z.device.type, dtype=autocast_dtype):
                scan = model.emission_mean(M, z).to(z.dtype)  # [..., K, B]
        else:
            scan = model.emission_mean(M, z)  # [..., K, B]
        return self._log_density(model, scan, x, mask, sigma, s0, beta), scan, trust

    def _log_density(self, model, scan, x, mask, sigma, s0, beta) -> torch.Tensor:
        """``[..., K]``: the per-beam log-density of ``x`` around ``scan`` summed over the
        unmasked beams (tempered: relative to a perfect match, times ``beta``)."""
        m = None if mask is None else mask.unsqueeze(-2)
        xs = x.unsqueeze(-2)  # [..., 1, B]
        eps = self.outlier_prob
        if beta is not None:
            # relative to a perfect match (no normaliser): an unmapped chart (beta = 0) scores
            # like a perfectly predicted scan, so no pull towards mapped cells at the frontier
            noise = model.noise_dist(scan, s0)
            lb = noise.log_prob(xs) - noise.log_prob(scan)  # [..., K, B]
            if eps > 0:
                lb = torch.logaddexp(lb + math.log1p(-eps), lb.new_tensor(math.log(eps)))
            return (beta * (lb if m is None else lb * m)).sum(-1)
        lb = model.noise_dist(scan, sigma).log_prob(xs)  # [..., K, B] the model's noise
        if eps > 0:  # the beam mixture
            floor = lb.new_tensor(math.log(eps / self.outlier_range))
            lb = torch.logaddexp(lb + math.log1p(-eps), floor)
        return (lb if m is None else lb * m).sum(-1)
