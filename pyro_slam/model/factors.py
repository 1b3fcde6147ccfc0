"""The DVBF-LM model's factors as plain functions of tensors (:class:`Factors`, the base of
:class:`~pyro_slam.model.DVBFLM`): the chart, the emission and its noise, the emission
marginalised over a map belief, the transition, the heading factor and the map prior. The Pyro
model, the particle filter's proposals and weights, the training objective, map fitting,
planning rollouts and MI all read these, so a swapped prior or noise model reaches all of
them."""

from __future__ import annotations

from typing import TYPE_CHECKING

import pyro
import pyro.distributions as dist
import torch
from torch import nn

from .noise import BeamMixture, WrappedMixture

if TYPE_CHECKING:
    from .model import HeadingEvidence, MapBelief


class _Independent(dist.Independent):
    """An :class:`~pyro.distributions.Independent` whose expansion to its own batch shape is
    itself: a plate leaves the model's transition the object a proposal drew from (whose
    importance correction is then zero by construction, even for a deterministic one)."""

    def expand(self, batch_shape, _instance=None):
        if torch.Size(batch_shape) == self.batch_shape:
            return self
        return super().expand(batch_shape, _instance)


class _Memo:
    """The last distribution built from some tensors, kept with them: a later call on the same
    tensor objects, unchanged since (their version), gets it back. Tensors that need a
    gradient are never kept."""

    def __init__(self):
        self.args, self.versions, self.value = None, None, None

    @staticmethod
    def _versions(args) -> tuple | None:
        if any(torch.is_tensor(a) and a.requires_grad for a in args):
            return None
        return tuple(a._version if torch.is_tensor(a) else None for a in args)

    def get(self, args):
        if self.args is None or len(args) != len(self.args):
            return None
        if all(a is b for a, b in zip(args, self.args)) and self._versions(args) == self.versions:
            return self.value
        return None

    def put(self, args, value) -> None:
        versions = self._versions(args)
        if versions is not None:
            self.args, self.versions, self.value = tuple(args), versions, value


class Factors(nn.Module):
    """The factors of :class:`~pyro_slam.model.DVBFLM` as functions of tensors; the model's
    constructor sets what they read (``grid``, ``emission``, ``transition``, ``sigma_emission``,
    ``noise``, ``outlier_prob``, ``outlier_range``, ``prior``, ``heading``, ``init_scale``)."""

    def chart(self, M: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """``m_t = f_m(z_t, M)``: ``[..., D_m]``."""
        return self.grid.attend(M, z[..., :2])

    @property
    def beam_angles(self):
        """The LiDAR beam directions (None for other emissions)."""
        return getattr(self.emission, "beam_angles", None)

    def emission_mean(self, M: torch.Tensor, z: torch.Tensor, x=None) -> torch.Tensor:
        """Predicted observation ``mu_E(f_m(z_t, M), z_t)`` (LiDAR: body-frame scan), or the
        emission's own read-out of ``M`` (:meth:`~pyro_slam.model.emissions.Emission.read`; a
        :class:`~pyro_slam.model.emissions.RayEmission` casts the beams through ``M``). Given
        the observation ``x [..., N]``, an end-point emission's mean given it
        (:class:`~pyro_slam.model.emissions.EndPointEmission`; other emissions ignore it).

        ``z [..., 3]`` -> ``[..., N]``.
        """
        return self.emission.read(self.grid, M, z, x)

    def _observed_mean(self, M, z, scan, x):
        """The emission's mean for the observed ``x`` where it reads it, else ``scan``."""
        if x is None or not self.emission.reads_observation:
            return scan
        return self.emission_mean(M, z, x)

    def noise_dist(self, mean: torch.Tensor, sigma=None, validate: bool = False, outlier_prob=None):
        """The emission noise around ``mean [..., N]``, one distribution per entry (batch
        ``[..., N]``) with scale ``sigma`` (default ``sigma_E``; a tensor broadcasts), mixed
        with the outlier component of probability ``outlier_prob`` (default the model's; a
        tensor broadcasts). Argument validation is off unless ``validate``: the particle filter
        checks its weights itself and evaluates this on every particle of every step."""
        s = torch.as_tensor(self.sigma_emission if sigma is None else sigma, dtype=mean.dtype)
        with pyro.validation_enabled(validate):
            d = self.noise(mean, s)
        d._validate_args = validate  # (read again by log_prob, after the context)
        eps = self.outlier_prob if outlier_prob is None else outlier_prob
        if torch.is_tensor(eps) or eps > 0:
            d = BeamMixture(d, eps, self.outlier_range, validate_args=False)
        return d

    def marginal_emission(self, belief: MapBelief, z: torch.Tensor, x=None):
        """The emission marginalised over a Gaussian map belief ``q(M)``, a stated
        approximation: along each reading ``q(M)`` is either known, at its mean, or unknown,
        with the probability ``v`` in ``[0, 1]`` that the map's variance relative to the
        prior's gives where the reading comes from
        (:meth:`~pyro_slam.model.emissions.Emission.read_moments`); an unknown map makes the
        reading uniform over the sensor's range, as the model's outlier component does. So

            p(x_t | z_t, q) ~ (1 - v) p(x_t | z_t, E_q[M]) + v U(0, R),

        the model's own emission at the map mean with the outlier probability ``1 - (1 - eps)
        (1 - v)``. Returns the predicted reading ``mean [..., N]`` (given the observation ``x``
        where the emission reads it, :meth:`emission_mean`) and that outlier probability
        ``[..., N]`` (or broadcastable)."""
        if self.prior is None:  # (the prior's std is 1)
            rel, rel_var = belief.scale, belief.variance
        else:
            rel, rel_var = belief.scale / self.prior_std(), None
        mean, v = self.emission.read_moments(self.grid, belief.loc, rel, z, rel_var, x)
        return mean, 1 - (1 - self.outlier_prob) * (1 - v.clamp(0, 1))

    def emission_dist(self, mean: torch.Tensor, mask=None, sigma=None, outlier_prob=None):
        """``p(x_t | m_t)`` as a Pyro distribution with event shape ``[N]``."""
        d = self.noise_dist(mean, sigma, dist.is_validation_enabled(), outlier_prob)
        if mask is not None:
            d = d.mask(mask)
        return d.to_event(1)

    def emission_log_prob(self, x, mean, mask=None, sigma=None, outlier_prob=None):
        """``log p(x_t | m_t)`` summed over (unmasked) entries: ``[...]``; the same value as
        ``emission_dist(mean, mask, sigma, outlier_prob).log_prob(x)``, on the particle batch."""
        lp = self.noise_dist(mean, sigma, outlier_prob=outlier_prob).log_prob(x)  # [..., N]
        return (lp if mask is None else lp * mask).sum(-1)

    def transition_dist(self, z, u, scan=None, sigma=None, validate: bool | None = None):
        """``p(z_{t+1} | z_t, u_t, m_t)`` with event shape ``[3]`` (std ``sigma`` instead of the
        transition's ``sigma_T`` if given, ``[3]`` or broadcastable to ``z``). ``validate``:
        check the arguments (default: Pyro's setting; the particle filter turns it off, so a
        deterministic transition, ``sigma_T = 0``, can be filtered)."""
        s = self.transition.sigma if sigma is None else sigma
        validate = dist.is_validation_enabled() if validate is None else validate
        args = (z, u, scan, s, validate)
        keep = not any(p.requires_grad for p in self.transition.parameters())
        if keep and (d := self._memo.get(args)) is not None:
            return d
        mean = self.transition.mean(z, u, scan)
        d = _Independent(dist.Normal(mean, s, validate_args=validate), 1)
        if keep:
            self._memo.put(args, d)
        return d

    def heading_dist(self, theta: torch.Tensor, frame, scale):
        """``p(h_t | theta_t, phi)``: the wall direction seen at headings ``theta [...]`` (event
        shape ``[]``) in the frame ``phi`` (a number or a tensor broadcasting with ``theta``),
        with std ``scale`` (the scan's)."""
        if self.heading is None:
            raise ValueError("this model has no heading factor (heading=WallHeading(...))")
        frame = torch.as_tensor(frame, dtype=theta.dtype)
        h = self.heading
        return WrappedMixture(frame - theta, scale, h.period, h.outlier_prob)

    def heading_log_prob(self, theta: torch.Tensor, evidence: HeadingEvidence) -> torch.Tensor:
        """``log p(h_t | theta_t, phi)`` at headings ``theta [...]`` for ``evidence`` that
        broadcasts with them (:meth:`HeadingEvidence.per_particle`), marginalised over the
        frame's belief where it holds one; zero where no direction is seen: ``[...]``."""
        seen = evidence.seen()
        frame = torch.as_tensor(evidence.frame, dtype=theta.dtype).nan_to_num()  # (unseen)
        d = self.heading_dist(theta, frame, evidence.std().to(theta.dtype))
        return torch.where(seen, d.log_prob(evidence.direction.nan_to_num()), 0.0)

    def map_prior(self):
        """``p(M)`` per cell (event ``[D_m]``): the given prior, or ``N(0, 1)``."""
        if self.prior is not None:
            return self.prior
        loc = self.init_scale.new_zeros(self.grid.dim)
        return dist.Normal(loc, torch.ones_like(loc)).to_event(1)

    def prior_std(self) -> torch.Tensor:
        """The map prior's marginal std, broadcastable to ``[w, h, D_m]``: what the particle
        filter's trust compares the map belief's std with."""
        if self.prior is None:
            return self.init_scale.new_ones(())
        try:
            var = self.prior.variance
        except NotImplementedError:
            raise ValueError(
                f"the map prior {type(self.prior).__name__} must expose its marginal variance "
                "(.variance): the marginal emission compares the belief's variance with it"
            ) from None
        return var.sqrt()
