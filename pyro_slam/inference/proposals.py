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
  allow, however narrow the cloud);
* :class:`ScanMatchProposal` -- the transition corrected by the step's scan (and heading
  evidence), matched against the map: the improved proposal of Grisetti et al. (2007), with a
  defensive share of the transition.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pyro
import pyro.distributions as dist
import torch
from pyro.distributions import TorchDistribution, constraints

from ..geometry import wrap_angle
from ..model.model import HeadingEvidence, MapBelief
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
    has_rsample = True

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

    def squeeze_particle(self):
        """The same distribution without its last batch dimension (of size 1)."""
        return PoseProposal(
            self.loc[..., 0, :],
            self.scale[..., 0, :],
            self.alt_loc[..., 0],
            self.alt_scale[..., 0],
            self.alt_weight[..., 0],
        )

    def log_prob(self, z: torch.Tensor) -> torch.Tensor:
        xy = _normal_log_prob(z[..., :2], self.loc[..., :2], self.scale[..., :2]).sum(-1)
        base = _normal_log_prob(z[..., 2], self.loc[..., 2], self.scale[..., 2])
        alt = _normal_log_prob(z[..., 2], self.alt_loc, self.alt_scale)
        w = self.alt_weight
        h = torch.logaddexp(torch.log(w) + alt, torch.log1p(-w) + base)
        return xy + torch.where(w > 0, h, base)

    def sample(self, sample_shape=(), generator=None):
        with torch.no_grad():
            return self.rsample(sample_shape, generator)

    def rsample(self, sample_shape=(), generator=None):
        """A draw, differentiable in the parameters within the component it falls in (the
        heading's mixture weight gets no gradient)."""
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
        """Sample ``z_t [..., K, 3]`` for the particles ``p`` with ``generator``; returns it
        with ``q`` (the distribution it was drawn from, batch ``[..., K]``: for the transition,
        the model's own transition distribution, whose importance correction is then exactly
        zero). ``u [..., 1, D_u]`` and ``step`` (:meth:`dist`'s, ``heading`` per particle,
        :meth:`~pyro_slam.model.HeadingEvidence.per_particle`) broadcast against the
        particles."""
        q = self.dist(model, p.z, p.scan, u, **step)
        z = q.sample(generator=generator)
        if self.is_transition:
            q = model.transition_dist(p.z, u, p.scan, validate=False)
        return z, q


class Drawn(TorchDistribution):
    """A distribution ``q`` with a value already drawn from it (by the filter's own generator):
    ``sample()`` returns ``value``, ``log_prob`` is ``q``'s. The pose site of the filter's
    one-step guide, which the model's trace replays."""

    arg_constraints = {}
    has_rsample = False

    def __init__(self, q, value: torch.Tensor):
        self.q, self.value = q, value
        super().__init__(q.batch_shape, q.event_shape, validate_args=False)

    @property
    def support(self):
        return self.q.support

    def sample(self, sample_shape=()):
        if sample_shape:
            raise ValueError("a drawn value has no further samples")
        return self.value

    def log_prob(self, value):
        return self.q.log_prob(value)


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
        r = wrap_angle(m - value, period)
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


class MatchedProposal(TorchDistribution):
    """``q(z) = a N(loc, diag(scale^2)) + (1 - a) N(mu, cov)`` over poses (event ``[3]``, batch
    ``[...]``): the transition and a full-covariance Gaussian, with the defensive share ``a``
    of the transition."""

    arg_constraints = {}
    support = constraints.real_vector
    has_rsample = True

    def __init__(self, loc, scale, mu, cov, defensive: float):
        self.loc, self.scale, self.mu, self.defensive = loc, scale, mu, float(defensive)
        self.tril = torch.linalg.cholesky(cov)
        super().__init__(loc.shape[:-1], loc.shape[-1:], validate_args=False)

    def squeeze_particle(self):
        """The same distribution without its last batch dimension (of size 1)."""
        cov = self.tril @ self.tril.transpose(-1, -2)
        return MatchedProposal(
            self.loc[..., 0, :],
            self.scale[..., 0, :],
            self.mu[..., 0, :],
            cov[..., 0, :, :],
            self.defensive,
        )

    def expand(self, batch_shape, _instance=None):
        e3, e33 = torch.Size(batch_shape) + (3,), torch.Size(batch_shape) + (3, 3)
        cov = self.tril @ self.tril.transpose(-1, -2)
        return MatchedProposal(
            self.loc.expand(e3),
            self.scale.expand(e3),
            self.mu.expand(e3),
            cov.expand(e33),
            self.defensive,
        )

    def log_prob(self, z: torch.Tensor) -> torch.Tensor:
        lt = _normal_log_prob(z, self.loc, self.scale).sum(-1)
        d = torch.linalg.solve_triangular(self.tril, (z - self.mu).unsqueeze(-1), upper=False)
        half_logdet = torch.log(torch.diagonal(self.tril, dim1=-2, dim2=-1)).sum(-1)
        lm = -0.5 * d.squeeze(-1).pow(2).sum(-1) - half_logdet - 1.5 * math.log(2 * math.pi)
        a = self.defensive
        if a <= 0:
            return lm
        return torch.logaddexp(math.log(a) + lt, math.log1p(-a) + lm)

    def sample(self, sample_shape=(), generator=None):
        with torch.no_grad():
            return self.rsample(sample_shape, generator)

    def rsample(self, sample_shape=(), generator=None):
        """A draw, differentiable in the parameters of the component it falls in (the
        defensive share is a constant)."""
        shape = torch.Size(sample_shape) + self.loc.shape
        eps = torch.randn(shape, generator=generator, dtype=self.loc.dtype)
        zt = self.loc + eps * self.scale
        zm = self.mu + (self.tril @ eps.unsqueeze(-1)).squeeze(-1)
        pick = torch.rand(shape[:-1], generator=generator, dtype=zt.dtype) < self.defensive
        return torch.where(pick.unsqueeze(-1), zt, zm)


def _cloud_centre(loc: torch.Tensor) -> torch.Tensor:
    """The mean ``[..., 3]`` of poses ``loc [..., K, 3]``, the heading's circular mean kept on
    the branch of the first particle's (headings are not wrapped in the model)."""
    ref = loc[..., :1, 2]
    d = wrap_angle(loc[..., 2] - ref, 2 * math.pi)
    h = ref[..., 0] + torch.atan2(torch.sin(d).mean(-1), torch.cos(d).mean(-1))
    return torch.cat([loc[..., :2].mean(-2), h.unsqueeze(-1)], -1)


class ScanMatchProposal(Proposal):
    """The transition corrected by the step's scan: the improved proposal of Grisetti et al.
    (2007), written as an SMC guide.

    1. **Match**: from the cloud's mean predicted pose, ``iterations`` Gauss-Newton steps on
       the model's log-likelihood of the scan under the map (a sampled map, or a belief's mean
       with each reading's chance of being unknown, :meth:`~pyro_slam.model.DVBFLM.
       marginal_emission`) plus the heading factor's evidence, each reading weighted by its
       inlier responsibility under the beam mixture (iteratively reweighted least squares),
       with the transition at the cloud's mean as a prior; Jacobians by finite differences of
       the emission (any emission).
    2. **Linearise** the log-likelihood at the match: a Gaussian factor in information form
       (``H = J^T W J``, the gradient ``b``); a direction the scan does not constrain (a
       corridor) keeps ``H``'s null space, so the transition rules there.
    3. Each particle's proposal is its transition times that factor (an exact Gaussian
       product), mixed with the transition itself with weight ``defensive`` (defensive
       importance sampling: a bounded weight where the match misleads); where the match fails
       (non-finite) the proposal is the transition.

    The filter weighs by ``p(z_t | z_{t-1}) p(x_t | z_t) / q(z_t)``, so the target is the
    model's posterior whatever the match found.
    """

    def __init__(self, iterations: int = 3, defensive: float = 0.1):
        self.iterations, self.defensive = int(iterations), float(defensive)

    def dist(self, model, z, scan, u, *, x=None, mask=None, M=None, heading=None, **step):
        if z.dim() == 1 and x is not None and M is not None:  # a single path (a Pyro guide's)
            scan = None if scan is None else scan[None]
            q = self._cloud(model, z[None], scan, u, x, mask, M, heading, single=True)
            return q.squeeze_particle()
        return self._cloud(model, z, scan, u, x, mask, M, heading, single=False)

    def _cloud(self, model, z, scan, u, x, mask, M, heading, single: bool):
        """:meth:`dist` for particles ``z [..., K, 3]``; ``single``: one path (a cloud of
        one), which has no weights to bring a stray heading back, so the match always reads
        the heading factor (:func:`_heading_terms`)."""
        loc, scale = gaussian_transition(model, z, u, scan)  # [..., K, 3]
        if x is None or M is None:
            return PoseProposal(loc, scale)
        centre = _cloud_centre(loc.reshape(-1, *loc.shape[-2:])).reshape(*loc.shape[:-2], 3)
        prior = (scale**-2).mean(-2)  # [..., 3] the transition's precision at the centre
        h = None if heading is None else _squeeze_particles(heading, loc.dim())
        zm, H, b = _match(model, M, x, mask, h, centre, prior, self.iterations, single)
        if not (torch.isfinite(H).all() and torch.isfinite(zm).all()):
            return PoseProposal(loc, scale)
        zm = zm.unsqueeze(-2)  # [..., 1, 3], heading on each particle's branch
        turns = torch.round((loc[..., 2] - zm[..., 2]) / (2 * math.pi)) * (2 * math.pi)
        zm = torch.cat([zm[..., :2].expand_as(loc[..., :2]), (zm[..., 2] + turns)[..., None]], -1)
        P = torch.diag_embed(scale**-2)  # [..., K, 3, 3]
        Hk = H.unsqueeze(-3)
        eta = (P @ loc.unsqueeze(-1) + Hk @ zm.unsqueeze(-1)).squeeze(-1) + b.unsqueeze(-2)
        cov = torch.linalg.inv(P + Hk)
        cov = 0.5 * (cov + cov.transpose(-1, -2))
        mu = (cov @ eta.unsqueeze(-1)).squeeze(-1)
        return MatchedProposal(loc, scale, mu, cov, self.defensive)


def _squeeze_particles(heading: HeadingEvidence, dim: int) -> HeadingEvidence:
    """Evidence aligned with particles ``[..., K]`` back to the cloud's batch ``[...]``."""

    def sq(v):
        return v.squeeze(-1) if torch.is_tensor(v) and v.dim() >= dim - 1 else v

    return HeadingEvidence(
        sq(heading.direction), sq(heading.sigma), sq(heading.frame), sq(heading.frame_var)
    )


def _readings(model, M, z, x, mask):
    """The predicted readings at poses ``z [4, ..., 3]`` (a pose and its three offsets) and
    each reading's weight ``[..., B]`` (:func:`reading_weights`: the model's noise family, a
    belief's unknown readings as outliers), masked."""
    if isinstance(M, MapBelief):
        r, eps = model.marginal_emission(M, z, x)
        eps = eps[0]
    else:
        r = model.emission_mean(M, z, x)
        eps = torch.as_tensor(model.outlier_prob, dtype=r.dtype)
    e = x - r[0]
    w = reading_weights(model, x, r[0], e, eps)
    return r, e, w if mask is None else w * mask


def reading_weights(model, x, r, e, eps) -> torch.Tensor:
    """Each reading's weight in the scan match's iteratively reweighted least squares: the
    score of the model's emission (its noise family mixed with the outlier component of
    probability ``eps``) at the predicted reading ``r``, over the residual ``e = x - r``, i.e.
    ``d/dr log p(x | r) / e`` (the noise's precision times the reading's inlier responsibility
    for the Gaussian, in closed form; for another family, e.g. Student-t, by autograd, with
    the residual kept at least 1e-6 sigma_E from zero)."""
    s = model.sigma_emission
    if model.noise is dist.Normal:
        inlier = (1 - eps) * torch.exp(-0.5 * (e / s) ** 2) / (s * math.sqrt(2 * math.pi))
        resp = inlier / (inlier + eps / model.outlier_range).clamp_min(1e-30)
        return resp / s**2
    tiny = 1e-6 * s
    e = torch.where(e.abs() < tiny, torch.where(e < 0, -tiny, tiny), e)
    with torch.enable_grad():
        loc = (x - e).detach().requires_grad_(True)
        lp = model.noise_dist(loc, outlier_prob=eps).log_prob(x)
        (score,) = torch.autograd.grad(lp.sum(), loc)
    return (score / e).clamp_min(0.0)


def _match(model, M, x, mask, heading, centre, prior, iterations: int, single: bool = False):
    """Gauss-Newton from ``centre [..., 3]`` on the log-likelihood plus the prior about it of
    precision ``prior [..., 3]``; the linearisation ``(z*, H [..., 3, 3], b [..., 3])`` of the
    log-likelihood at the match (``single``: :func:`_heading_terms`'s)."""
    spacing = min(s / (c - 1) for s, c in zip(model.grid.size, model.grid.cells))
    delta = torch.tensor([0.2 * spacing, 0.2 * spacing, 0.2 * spacing / model.outlier_range])
    delta = delta.to(centre.dtype)
    offsets = torch.cat([torch.zeros(1, 3, dtype=centre.dtype), torch.diag(delta)])  # [4, 3]
    offsets = offsets.reshape(4, *([1] * (centre.dim() - 1)), 3)
    z = centre
    for i in range(iterations + 1):
        r, e, w = _readings(model, M, z.unsqueeze(0) + offsets, x, mask)
        J = ((r[1:] - r[:1]) / delta.reshape(3, *([1] * (r.dim() - 1)))).movedim(0, -1)
        H = J.transpose(-1, -2) @ (w.unsqueeze(-1) * J)  # [..., 3, 3]
        b = (J * (w * e).unsqueeze(-1)).sum(-2)  # [..., 3]
        if heading is not None and model.heading is not None:
            Hh, bh = _heading_terms(model, heading, z, single)
            H, b = H + Hh, b + bh
        if i == iterations:
            return z, H, b
        A = H + torch.diag_embed(prior * 1.001)
        step = torch.linalg.solve(A, (b - prior * (z - centre)).unsqueeze(-1)).squeeze(-1)
        z = z + step


def _heading_terms(model, heading: HeadingEvidence, z, single: bool = False):
    """The heading factor's Gauss-Newton terms at poses ``z [..., 3]``: ``H [..., 3, 3]`` and
    ``b [..., 3]`` (zero where no direction is seen), each weighted by the direction's inlier
    responsibility. For a cloud, a direction whose inlier density underflows the float at the
    cloud's heading (about 14 std off) has responsibility 0, and, without outliers, 0 / 0:
    the match fails and the proposal is the transition, whose spread the weights then choose
    from (measured more accurate than matching to that direction: the results page's options
    tried). For
    a single path (``single``) the responsibility is taken in log space: the match always
    reads the direction."""
    f, eps = model.heading, model.heading.outlier_prob
    so = heading.std().to(z.dtype)
    value = torch.as_tensor(heading.frame, dtype=z.dtype) - heading.direction.nan_to_num()
    e = wrap_angle(value - z[..., 2], f.period)
    if single:
        resp = torch.ones_like(e)
        if eps > 0:
            log_in = -0.5 * (e / so) ** 2 - torch.log(so * math.sqrt(2 * math.pi))
            resp = torch.sigmoid(log_in + math.log1p(-eps) - math.log(eps / f.period))
    else:
        g = torch.exp(-0.5 * (e / so) ** 2) / (so * math.sqrt(2 * math.pi))
        resp = (1 - eps) * g / ((1 - eps) * g + eps / f.period)
    w = torch.where(heading.seen(), resp / so**2, 0.0)
    H = torch.zeros(*z.shape, 3, dtype=z.dtype)
    H[..., 2, 2] = w
    b = torch.zeros_like(z)
    b[..., 2] = w * e
    return H, b


PROPOSALS = {
    "transition": TransitionProposal,
    "heading": HeadingProposal,
    "scan-match": ScanMatchProposal,
}


def _global_values(out):
    """``(M, frame)`` from what a guide of the global sites returns: a
    :class:`~pyro_slam.model.GlobalGuide`'s pair, an autoguide's dict of sites, or a map."""
    if isinstance(out, dict):
        return out["map"], out.get("frame")
    if isinstance(out, tuple):
        return out
    return out, None


def sequence_guide(model, proposal: Proposal, global_guide):
    """The SLAM guide of a whole traversal as a Pyro guide of :meth:`DVBFLM.model
    <pyro_slam.model.DVBFLM.model>` (same arguments, which it hands to ``global_guide``): the
    global sites from ``global_guide`` (a :class:`~pyro_slam.model.GlobalGuide` returning
    ``(M, phi)``, or any guide of the site ``"map"``, e.g. ``AutoNormal(poutine.block(model,
    expose=["map"]))``), the start pose from the model's prior, then each pose ``z_t`` from
    ``proposal`` at the previous one (a single particle), reading the step's scan, the
    sampled map and the heading evidence in the sampled frame. As the particle cache does
    (paper eq. 3), the proposals read the map and the poses without their gradient: no
    gradient, and no score-function term, comes from the proposal, whose sites are
    reparameterised. With it, Pyro's :class:`~pyro.infer.Trace_ELBO` (and
    ``TraceMeanField_ELBO``, ``TraceGraph_ELBO``) estimates the bound that
    :class:`~.elbo.ParticleChunkELBO` estimates with one particle."""

    def guide(observations, controls, init_pose, mask=None, headings=None):
        M, frame = _global_values(global_guide(observations, controls, init_pose, mask, headings))
        M = M.detach()
        z = pyro.sample("z_0", dist.Normal(init_pose, model.init_scale).to_event(1))
        reads = model.transition.needs_scan
        scan = model.emission_mean(M, z) if reads else None
        if headings is not None and frame is not None:
            headings = replace(headings, frame=frame.detach(), frame_var=0.0)
        for t in range(1, controls.shape[-2] + 1):
            step = {"x": observations[t], "mask": None if mask is None else mask[t], "M": M}
            if headings is not None and frame is not None:
                step["heading"] = headings.at(t)
            q = proposal.dist(model, z.detach(), scan, controls[..., t - 1, :], **step)
            z = pyro.sample(f"z_{t}", q)
            scan = model.emission_mean(M, z.detach()) if reads else None

    return guide
