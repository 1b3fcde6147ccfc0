"""Pose proposals: the SMC guides over ``z_t`` of the particle filter, in Pyro's
:class:`~pyro.infer.SMCFilter` sense.

A :class:`Proposal` gives ``q(z_t | z_{t-1}, u_{t-1}, ...)`` as a Pyro distribution
(:meth:`Proposal.dist`, event ``[3]``): the Pyro guide of :class:`~.smc.PyroSMCFilter` samples it,
and Pyro's SMCFilter weighs by ``p / q`` itself. The batched filter samples it with its own
generator (:meth:`Proposal.propose`) and adds the importance correction ``log p(z_t | z_{t-1})
- log q(z_t)`` to the weights, so that every proposal targets the model's posterior:

* :class:`TransitionProposal` -- the model's transition (bootstrap; no correction);
* :class:`HeadingProposal` -- the transition conditioned exactly on the model's heading factor
  (the optimal proposal for that observation: every particle lands on a heading the walls
  allow, however narrow the cloud).
"""

from __future__ import annotations

import math
from dataclasses import replace

import pyro
import pyro.distributions as dist
import torch
from pyro.distributions import TorchDistribution, constraints

from ..model.model import HeadingEvidence
from ..model.noise import wrap_period
from .particles import Particles


def _normal_log_prob(x, loc, scale):
    return -0.5 * ((x - loc) / scale) ** 2 - torch.log(scale) - 0.5 * math.log(2 * math.pi)


def gaussian_transition(model, z, u, scan):
    """The model's transition at poses ``z [..., 3]`` as ``(loc, scale)`` ``[..., 3]``; a
    transition that is not Gaussian is refused where a proposal needs one."""
    d = model.transition_dist(z, u, scan, validate=False)
    base = getattr(d, "base_dist", d)
    if not hasattr(base, "loc") or not hasattr(base, "scale"):
        raise ValueError(f"this proposal needs a Gaussian transition, got {type(base).__name__}")
    return base.loc, base.scale.expand_as(base.loc)


class PoseProposal(TorchDistribution):
    """``q(z)`` over poses (event ``[3]``, batch ``[...]``): position Gaussian ``N(loc_xy,
    scale_xy)``; heading the mixture ``w N(alt_loc, alt_scale) + (1 - w) N(loc_h, scale_h)``
    (``w [...]`` the weight of the alternative component; 0: the Gaussian ``N(loc, scale)``)."""

    arg_constraints = {}
    support = constraints.real_vector
    has_rsample = False

    def __init__(self, loc, scale, alt_loc=None, alt_scale=None, alt_weight=None):
        self.loc, self.scale = loc, scale
        zero = torch.zeros_like(loc[..., 2])
        self.alt_loc = zero if alt_loc is None else alt_loc
        self.alt_scale = torch.ones_like(zero) if alt_scale is None else alt_scale
        self.alt_weight = zero if alt_weight is None else alt_weight
        super().__init__(loc.shape[:-1], loc.shape[-1:], validate_args=False)

    def expand(self, batch_shape, _instance=None):
        shape = torch.Size(batch_shape)
        e3 = shape + (3,)
        return PoseProposal(
            self.loc.expand(e3),
            self.scale.expand(e3),
            self.alt_loc.expand(shape),
            self.alt_scale.expand(shape),
            self.alt_weight.expand(shape),
        )

    def log_prob(self, z: torch.Tensor) -> torch.Tensor:
        xy = _normal_log_prob(z[..., :2], self.loc[..., :2], self.scale[..., :2]).sum(-1)
        base = _normal_log_prob(z[..., 2], self.loc[..., 2], self.scale[..., 2])
        alt = _normal_log_prob(z[..., 2], self.alt_loc, self.alt_scale)
        w = self.alt_weight
        h = torch.logaddexp(torch.log(w) + alt, torch.log1p(-w) + base)
        return xy + torch.where(w > 0, h, base)

    def sample(self, sample_shape=(), generator=None):
        shape = torch.Size(sample_shape) + self.loc.shape
        eps = torch.randn(shape, generator=generator, dtype=self.loc.dtype)
        z = self.loc + eps * self.scale
        alt = self.alt_loc + eps[..., 2] * self.alt_scale
        pick = torch.rand(shape[:-1], generator=generator, dtype=z.dtype) < self.alt_weight
        return torch.cat([z[..., :2], torch.where(pick, alt, z[..., 2]).unsqueeze(-1)], -1)


class Proposal:
    """A pose proposal (module doc). Subclasses implement :meth:`dist`."""

    #: q is the model's transition itself (no importance correction)
    is_transition = False

    def dist(self, model, z, scan, u, *, heading: HeadingEvidence | None = None, **step):
        """``q(z_t)`` for previous poses ``z [..., 3]`` (their predicted scans ``scan [..., B]``),
        controls ``u`` broadcasting to ``[..., D_u]`` and the step's evidence (``heading``
        broadcasting to ``[...]``; ``step``: ``x``, ``mask`` and the map ``M``, for proposals
        that read the scan); a distribution with batch ``[...]`` and event ``[3]``."""
        raise NotImplementedError

    @torch.no_grad()
    def propose(self, model, p: Particles, u, generator=None, **step):
        """Sample ``z_t [..., K, 3]`` for the particles ``p``; returns it with the importance
        correction ``log p(z_t | z_{t-1}) - log q(z_t)`` ``[..., K]`` (None for the
        transition). ``u [..., D_u]`` (one per batch element); ``step`` as :meth:`dist`, with
        ``heading`` per batch element."""
        if step.get("heading") is not None:
            step["heading"] = step["heading"].per_particle()
        q = self.dist(model, p.z, p.scan, u.unsqueeze(-2), **step)
        z = q.sample(generator=generator)
        if self.is_transition:
            return z, None
        trans = model.transition_dist(p.z, u.unsqueeze(-2), p.scan, validate=False)
        return z, trans.log_prob(z) - q.log_prob(z)


class TransitionProposal(Proposal):
    """``q(z_t | z_{t-1}) = p(z_t | z_{t-1}, u_{t-1}, mu_E(m_{t-1}))``: the bootstrap filter."""

    is_transition = True

    def dist(self, model, z, scan, u, **step):
        return PoseProposal(*gaussian_transition(model, z, u, scan))


class HeadingProposal(Proposal):
    """The transition conditioned on the model's heading factor (:class:`~pyro_slam.model.
    WallHeading`), exactly: the transition's heading is Gaussian about ``m`` (std ``s``) and
    the wall direction ``h`` seen in the scan is ``phi - theta`` modulo the period up to noise
    ``sigma_o`` (with the frame's variance, under a belief of the frame), so with the wrapped
    residual ``r = wrap(m - (phi - h))`` and ``v = s^2 + sigma_o^2`` the heading's posterior is
    ``N(m - r s^2 / v, s^2 sigma_o^2 / v)``. With the factor's outlier probability ``eps`` it
    is the mixture of that (weight ``(1 - eps) N(r; 0, sqrt(v)) / ((1 - eps) N(r; 0,
    sqrt(v)) + eps / period)``) and the transition's heading. The position is the
    transition's. Where no direction is seen this is the transition."""

    def dist(self, model, z, scan, u, *, heading: HeadingEvidence | None = None, **step):
        loc, scale = gaussian_transition(model, z, u, scan)
        if heading is None or model.heading is None:
            return PoseProposal(loc, scale)
        period, eps = model.heading.period, model.heading.outlier_prob
        m, s = loc[..., 2], scale[..., 2]
        so = heading.std().to(m.dtype)
        value = torch.as_tensor(heading.frame, dtype=m.dtype) - heading.direction.nan_to_num()
        r = wrap_period(m - value, period)
        v = s**2 + so**2
        cond_loc, cond_scale = m - r * s**2 / v, s * so / v.sqrt()
        log_in = -0.5 * r**2 / v - 0.5 * torch.log(2 * math.pi * v)
        w = torch.ones_like(m)
        if eps > 0:
            log_in = log_in + math.log1p(-eps)
            w = torch.exp(
                log_in - torch.logaddexp(log_in, log_in.new_tensor(math.log(eps / period)))
            )
        w = torch.where(heading.seen(), w, 0.0)
        return PoseProposal(loc, scale, cond_loc, cond_scale, w)


PROPOSALS = {"transition": TransitionProposal, "heading": HeadingProposal}


def sequence_guide(model, proposal: Proposal, global_guide):
    """The SLAM guide of a whole traversal as a Pyro guide of :meth:`DVBFLM.model
    <pyro_slam.model.DVBFLM.model>` (same arguments): the global sites from ``global_guide``
    (a :class:`~pyro_slam.model.GlobalGuide`, returning ``(M, phi)``), the start pose from the
    model's prior, then each pose ``z_t`` from ``proposal`` at the previous one (a single
    particle), reading the step's scan, the sampled map and the heading evidence in the
    sampled frame. With it, Pyro's :class:`~pyro.infer.Trace_ELBO` estimates the bound that
    :class:`~.elbo.ParticleChunkELBO` estimates with one particle."""

    def guide(observations, controls, init_pose, mask=None, headings=None):
        M, frame = global_guide()
        z = pyro.sample("z_0", dist.Normal(init_pose, model.init_scale).to_event(1))
        scan = model.emission_mean(M, z)
        if headings is not None and frame is not None:
            headings = replace(headings, frame=frame, frame_var=0.0)
        for t in range(1, controls.shape[-2] + 1):
            step = {"x": observations[t], "mask": None if mask is None else mask[t], "M": M}
            if headings is not None and frame is not None:
                step["heading"] = headings.at(t)
            z = pyro.sample(
                f"z_{t}", proposal.dist(model, z, scan, controls[..., t - 1, :], **step)
            )
            scan = model.emission_mean(M, z)

    return guide
