"""The differentiable, batched bootstrap particle filter and the asynchronous particle cache.

:class:`ParticleFilter` is the custom SMC guide over poses of DVBF-LM (paper III-C): particles
are proposed from the transition and weighted by the emission likelihood under a (sampled) map,
in log space, with ESS-triggered resampling. Unlike :class:`pyro.infer.SMCFilter` it keeps the
autograd graph from the map and emission parameters to the log-evidence estimate

    log p^(x_{1:T} | M) = sum_t log sum_k w_{t-1,k} p(x_t | z_t^k, M)

(resampling indices and particle positions are treated as samples, i.e. no gradient flows
through them), so the same step serves training (:class:`ParticleChunkELBO`) and filtering.
Particles may carry any batch shape: ``[..., K, 3]``.

:class:`ParticleCache` is the asynchronous particle representation of paper eq. (3): ``N``
cached particles per time step, from which a chunk of consecutive steps starts (moment-matched
Gaussian or categorical proposal), refreshed by every chunk that runs over them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import pyro.distributions as dist
import torch
from pyro import poutine
from pyro.infer import ELBO
from torch.distributions import kl_divergence

from . import resampling
from .geometry import reproject_scan, wrap_angle
from .model import DVBFLM

WEIGHTINGS = ("marginal", "shared", "tempered", "predictive")
PROPOSALS = ("bootstrap", "linearised")


@dataclass
class MapBelief:
    """A Gaussian map belief, ``loc`` and ``scale`` ``[w, h, D]`` (e.g. a mean-field ``q(M)``)."""

    loc: torch.Tensor
    scale: torch.Tensor
    usable: torch.Tensor | None = None  # [w, h] in [0, 1]: cells the weights may use
    trust: float = 1.0  # in [0, 1]: one factor on the trust of every particle (cloud-wide)


@dataclass
class HeadingObservation:
    """A direct observation of the heading modulo ``period``: ``heading = value (mod period)``
    up to Gaussian noise of std ``sigma`` (rad). E.g. the Manhattan-world one: a scan's walls
    run along the world axes, so ``heading + wall_direction`` is a multiple of ``pi / 2``
    (:func:`~pyro_slam.geometry.wall_direction`, ``value = -direction``)."""

    value: torch.Tensor  # [...] (one per batch element; nan: no observation there)
    sigma: float
    period: float = math.pi / 2

    def at(self, t) -> HeadingObservation:
        """The observation of step(s) ``t`` from one that holds a sequence ``value [T]``."""
        return HeadingObservation(self.value[t], self.sigma, self.period)


@dataclass
class Particles:
    """A weighted particle set. ``z [..., K, 3]``, ``logw [..., K]`` (normalised),
    ``scan [..., K, B]`` predicted scan at ``z`` (the transition's input), detached;
    ``past [..., K, L, 3]`` each particle's ancestors at the last ``L`` steps, oldest first
    (kept by a filter with ``history = L``; ``None`` otherwise)."""

    z: torch.Tensor
    logw: torch.Tensor
    scan: torch.Tensor | None = None
    past: torch.Tensor | None = None

    @property
    def num_particles(self) -> int:
        return self.z.shape[-2]

    def mean(self) -> torch.Tensor:
        """Weighted mean pose ``[..., 3]`` (circular mean of the heading, wrapped)."""
        return _weighted_pose_mean(self.z, self.logw)

    def std(self) -> torch.Tensor:
        """Weighted std ``[..., 3]`` (the heading's about its circular mean, see
        :func:`pose_moments`)."""
        return pose_moments(self.z, self.logw)[1]

    def smoothed(self, lag: int) -> torch.Tensor:
        """Fixed-lag smoothed pose of ``lag`` steps ago ``[..., 3]``: the weighted mean of the
        particles' ancestors there under the current weights (needs ``past``, ``lag <= L``).
        ``lag = 0`` is :meth:`mean`."""
        if lag == 0:
            return self.mean()
        if self.past is None or not 0 < lag <= self.past.shape[-2]:
            L = 0 if self.past is None else self.past.shape[-2]
            raise ValueError(f"smoothed(lag={lag}) needs the ancestors of {lag} steps; have {L}")
        return _weighted_pose_mean(self.past[..., -lag, :], self.logw)

    def resample(self, generator=None, scheme="systematic") -> Particles:
        idx = resampling.SCHEMES[scheme](self.logw, generator)
        scan = None if self.scan is None else resampling.gather_particles(self.scan, idx)
        past = None
        if self.past is not None:  # [..., K, L, 3] -> gather along K
            flat = self.past.flatten(-2)  # [..., K, L * 3]
            past = resampling.gather_particles(flat, idx).unflatten(-1, self.past.shape[-2:])
        return Particles(
            resampling.gather_particles(self.z, idx),
            torch.full_like(self.logw, -math.log(self.num_particles)),
            scan,
            past,
        )

    def detach(self) -> Particles:
        return Particles(
            self.z.detach(),
            self.logw.detach(),
            None if self.scan is None else self.scan.detach(),
            None if self.past is None else self.past.detach(),
        )


def _weighted_pose_mean(z: torch.Tensor, logw: torch.Tensor) -> torch.Tensor:
    """``z [..., K, 3]`` weighted by ``exp(logw) [..., K]`` -> ``[..., 3]`` (circular mean of
    the heading, wrapped)."""
    w = logw.exp().unsqueeze(-1)
    xy = (w * z[..., :2]).sum(-2)
    h = z[..., 2:3]
    c, s = (w * torch.cos(h)).sum(-2), (w * torch.sin(h)).sum(-2)
    return torch.cat([xy, torch.atan2(s, c)], -1)


class ParticleFilter:
    """Bootstrap particle filter over DVBF-LM poses.

    Args:
        model: the :class:`~pyro_slam.model.DVBFLM`.
        ess_threshold: resample when ``ESS < ess_threshold * K``.
        scheme: ``"systematic"`` or ``"multinomial"`` (:mod:`pyro_slam.resampling`).
        sigma_emission: emission std used for the weights (default: the model's ``sigma_E``;
            the paper filters with a smaller one, Appendix B-I).
        uncertainty_gain: when the map is given as a belief ``(loc, scale)`` (a
            :class:`MapBelief`), the weights use the map mean and an emission std inflated by the
            chart's uncertainty, ``sigma / (1 - gain * mean_d var(m_t))`` (clamped): an
            approximate marginalisation of ``q(M)`` that leaves the weights flat where the map
            is still at its prior (``var = 1``) and sharp where it is well determined.
        generator: ``torch.Generator`` for reproducible noise and resampling.
        weighting: ``"marginal"`` (inflated sigma, above), ``"shared"`` (the same, with one
            inflation for the whole cloud: the weighted mean of the particles' trust, so the
            normaliser ``-B log sigma`` cancels and cannot favour particles in cells written more
            often) or ``"tempered"`` (likelihood raised to ``trust^2`` without the normaliser,
            so unmapped charts are neutral).
        outlier_prob: per-beam outlier probability ``eps``. Tempered weights: a floor
            ``log eps`` under each beam's term. Other weightings: the classic beam mixture
            (Thrun et al., *Probabilistic Robotics* 6.3), ``(1 - eps) N(x; mu, sigma) + eps /
            outlier_range`` per beam, so that a few beams the map cannot explain (a wall not
            yet written, a ray grazing a corner) cannot dominate a sharp ``sigma``.
        outlier_range: width of the uniform outlier density (the sensor's range).
        proposal: ``"bootstrap"`` (sample the transition) or ``"linearised"``: the Gaussian
            optimal proposal of the emission linearised at each particle's transition mean
            (Doucet et al. 2000), ``q(z) = N(mu, S)`` with ``S^-1 = Sigma_T^-1 + J^T J /
            sigma^2`` and ``mu`` the transition mean moved by ``S J^T (x - h) / sigma^2``
            (``J``: finite-difference Jacobian of the predicted scan ``h`` in the pose; beams
            more than ``proposal_gate`` sigma off are left out of it), weighted by
            ``p(x | z) p(z | z_prev) / q(z)``, so the particles go where the scan puts them even
            when the transition's noise is much wider than the likelihood (a scan-matching
            proposal, as in GMapping).
        proposal_gate: see ``proposal``.
        prior_predictive_std: ``"predictive"`` weighting: per-beam std of scans under the map
            prior (SLAM sets it to the std of the observed ranges); the predictive std is
            ``sqrt(sigma^2 + (1 - trust) * prior_predictive_std^2)``.
        autocast_dtype: e.g. ``torch.bfloat16``: run the emission MLP in reduced precision when
            no gradient is needed (filtering); ~2-3x faster on CPU, range error ~1e-3.
        beam_trust: with an emission that has ``beam_variance``
            (:class:`~pyro_slam.networks.RayEmission`), one trust per beam from the map's
            variance where that beam stops, instead of one per particle from its own chart;
            ``"path"``: from the variance where it stops or anywhere on its way there.
        history: keep each particle's ancestors at the last ``history`` steps
            (:attr:`Particles.past`, gathered on resampling) for fixed-lag smoothing
            (:meth:`Particles.smoothed`); 0: none.
    """

    def __init__(
        self,
        model: DVBFLM,
        ess_threshold: float = 0.5,
        scheme: str = "systematic",
        sigma_emission: float | None = None,
        generator: torch.Generator | None = None,
        uncertainty_gain: float = 1.0,
        weighting: str = "marginal",
        outlier_prob: float = 0.0,
        autocast_dtype: torch.dtype | None = None,
        prior_predictive_std: float = 0.15,
        beam_trust: bool | str = False,
        outlier_range: float = 1.0,
        proposal: str = "bootstrap",
        proposal_gate: float = 3.0,
        history: int = 0,
    ):
        if not (isinstance(history, int) and history >= 0):
            raise ValueError(f"history must be an int >= 0, got {history!r}")
        self.history = history
        if proposal not in PROPOSALS:
            raise ValueError(f"proposal must be one of {PROPOSALS}, got {proposal!r}")
        if proposal == "linearised" and weighting == "tempered":
            raise ValueError("the linearised proposal needs Gaussian weights, not 'tempered'")
        self.proposal, self.proposal_gate = proposal, proposal_gate
        if not 0.0 <= outlier_prob < 1.0:
            raise ValueError(f"outlier_prob must be in [0, 1), got {outlier_prob!r}")
        if outlier_range <= 0:
            raise ValueError(f"outlier_range must be positive, got {outlier_range!r}")
        self.outlier_range = outlier_range
        if beam_trust not in (False, True, "path"):
            raise ValueError(f"beam_trust must be False, True or 'path', got {beam_trust!r}")
        if beam_trust and not hasattr(model.emission, "beam_variance"):
            raise ValueError(
                "beam_trust needs an emission with beam_variance (RayEmission), "
                f"got {type(model.emission).__name__}"
            )
        self.beam_trust = beam_trust
        self.prior_predictive_std = prior_predictive_std
        self.outlier_prob = outlier_prob
        self.autocast_dtype = autocast_dtype
        if weighting not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
        self.uncertainty_gain, self.weighting = uncertainty_gain, weighting
        if scheme not in resampling.SCHEMES:
            raise ValueError(f"unknown resampling scheme {scheme!r}")
        self.model = model
        self.ess_threshold = ess_threshold
        self.scheme = scheme
        self.sigma_emission = sigma_emission
        self.generator = generator

    def trust(self, z: torch.Tensor, M: MapBelief) -> torch.Tensor:
        """How far the weights trust the map belief at poses ``z [..., K, 3]``: ``[..., K, 1]``
        in ``[0.01, 1]``, one minus the chart's variance under ``M`` relative to the prior's
        (of its first ``emission.trust_features`` features where the emission says so; times
        ``uncertainty_gain``, ``M.usable`` and ``M.trust``). With ``beam_trust`` and an emission
        that reads the map along its beams (``beam_variance``,
        :class:`~pyro_slam.networks.RayEmission`) one trust per beam, ``[..., K, B]``, from the
        variance where each beam stops."""
        g, xy = self.model.grid, z[..., :2]
        if self.beam_trust:
            path = self.beam_trust == "path"
            var = self.model.emission.beam_variance(g, M.loc, M.scale, z, path=path)  # [.., K, B]
        else:
            n = getattr(self.model.emission, "trust_features", None)  # None: every feature
            scale = M.scale if n is None else M.scale[..., :n]
            var = g.relative_variance(scale, xy)  # [..., K, 1]
        # prior variance is 1: charts of unmapped cells (var -> 1) give flat weights
        trust = (1.0 - self.uncertainty_gain * var).clamp_min(1e-2)  # [..., K, 1]
        if M.usable is not None:
            usable = g.attend(M.usable.unsqueeze(-1), xy)  # [..., K, 1]
            trust = (trust * usable).clamp_min(1e-2)
        if M.trust != 1.0:
            trust = (trust * M.trust).clamp_min(1e-2)
        return trust

    def cloud_trust(self, p: Particles, M: MapBelief) -> torch.Tensor:
        """The weighted mean of :meth:`trust` over the particles ``p``: ``[...]``."""
        return (p.logw.exp() * self.trust(p.z, M).mean(-1)).sum(-1)

    def _likelihood_params(self, z, M, logw):
        """The map mean and the weights' emission std ``sigma`` (or tempering ``beta``) at
        ``z [..., K, 3]`` under ``M`` (a tensor or a :class:`MapBelief`, see the class doc):
        ``(M, sigma, beta, s0)`` with ``s0`` the base std."""
        sigma, beta = self.sigma_emission, None
        s0 = self.model.sigma_emission if sigma is None else sigma
        if isinstance(M, MapBelief):
            trust = self.trust(z, M)  # [..., K, 1]
            if self.weighting == "shared":
                # one trust for the cloud: the normaliser is then the same for every particle
                trust = (logw.exp().unsqueeze(-1) * trust).sum(-2, keepdim=True)  # [..., 1, 1]
            M = M.loc
            if self.weighting == "predictive":
                # linearised marginal of q(M): predictive variance s0^2 + v * s_p^2, where
                # v = 1 - trust is the chart's remaining prior variance and s_p the spread of
                # scans under the prior; an unmapped chart scores the prior predictive -- below
                # a correct match of a mapped cell, above a wrong one
                v = (1.0 - trust).clamp(0.0, 1.0)
                sigma = (s0**2 + v * self.prior_predictive_std**2).sqrt()  # [..., K, 1]
            elif self.weighting == "tempered":
                # p(x | z, E[M])^beta with beta = trust^2: the same as inflating sigma_E by
                # 1 / trust but without the normaliser, so charts of unmapped cells are neutral
                # (beta -> 0) instead of being out-weighed by any mapped cell
                beta = trust**2  # [..., K, 1] (or one per beam, [..., K, B])
            else:
                sigma = s0 / trust
        return M, sigma, beta, s0

    def _weigh(self, z, M, x, mask, logw, step, correction=None):
        """Emission weights at ``z [..., K, 3]`` (plus ``correction [..., K]``, a proposal's
        log transition-over-proposal density ratio).

        Returns new particles and the log-evidence ``[...]``.
        """
        M, sigma, beta, s0 = self._likelihood_params(z, M, logw)
        if self.autocast_dtype is not None and not torch.is_grad_enabled():
            # reduced-precision emission MLP for filtering only (training keeps full precision)
            with torch.autocast(z.device.type, dtype=self.autocast_dtype):
                scan = self.model.emission_mean(M, z).to(z.dtype)  # [..., K, B]
        else:
            scan = self.model.emission_mean(M, z)  # [..., K, B]
        m = None if mask is None else mask.unsqueeze(-2)
        if beta is None and self.outlier_prob > 0:
            s = s0 if sigma is None else sigma
            loglik = self._mixture_log_prob(x.unsqueeze(-2), scan, m, s)  # [..., K]
        elif beta is None:
            loglik = self.model.emission_log_prob(x.unsqueeze(-2), scan, m, sigma)  # [..., K]
        else:
            # log-likelihood relative to a perfect match (no normaliser), so an unmapped chart
            # (beta = 0) scores the same as a perfectly predicted scan: no pull towards mapped
            # cells at the frontier of the map
            lb = -0.5 * ((x.unsqueeze(-2) - scan) / s0).pow(2)  # [..., K, B]
            if self.outlier_prob > 0:
                # per-beam mixture with an outlier floor: one wrong beam cannot dominate
                eps = self.outlier_prob
                lb = torch.logaddexp(lb + math.log1p(-eps), lb.new_tensor(math.log(eps)))
            loglik = (beta * (lb if m is None else lb * m)).sum(-1)  # [..., K]
        if correction is not None:
            loglik = loglik + correction
        joint = logw + loglik
        resampling.check_weights(joint.detach(), step)
        inc = torch.logsumexp(joint, -1)  # [...]
        # normalised weights keep their graph: without resampling, the next step's evidence
        # depends on the map through them too (resampling resets them to constants)
        return Particles(z, joint - inc.unsqueeze(-1), scan.detach()), inc

    def _mixture_log_prob(self, x, scan, mask, sigma) -> torch.Tensor:
        """Per-beam ``log((1 - eps) N(x; scan, sigma) + eps / outlier_range)`` summed over the
        (unmasked) beams: ``x [..., 1, B]``, ``scan [..., K, B]`` -> ``[..., K]``."""
        eps = self.outlier_prob
        s = torch.as_tensor(sigma, dtype=scan.dtype)
        r = (x - scan) / s
        lg = -0.5 * r * r - (torch.log(s) + 0.9189385332046727) + math.log1p(-eps)  # [..., K, B]
        lb = torch.logaddexp(lg, lg.new_tensor(math.log(eps / self.outlier_range)))
        return (lb if mask is None else lb * mask).sum(-1)

    def init(self, z0, M, x, mask=None, step=0):
        """Weigh initial particles ``z0 [..., K, 3]`` by ``x [..., B]``.

        Returns ``(particles, log_evidence [...])`` with ``log p^(x_0) = log mean_k p(x_0|z^k)``.
        """
        K = z0.shape[-2]
        logw = z0.new_full(z0.shape[:-1], -math.log(K))
        return self._weigh(z0.detach(), M, x, mask, logw, step)

    def propagate(self, p: Particles, u: torch.Tensor, sigma=None) -> torch.Tensor:
        """Sample ``z_{t+1} ~ p(. | z_t, u_t, mu_E(m_t))``: ``[..., K, 3]`` (no gradient).

        ``sigma``: the transition std to use instead of the model's ``sigma_T`` (``[3]`` or
        ``[..., 1, 3]``)."""
        with torch.no_grad():
            mean = self.model.transition.mean(p.z, u.unsqueeze(-2), p.scan)
            eps = torch.randn(mean.shape, generator=self.generator, dtype=mean.dtype)
            return mean + eps * (self.model.transition.sigma if sigma is None else sigma)

    def step(self, p: Particles, M, x, u, mask=None, step=None, sigma=None, heading=None):
        """One filtering step: resample if needed, propagate with ``u [..., D_u]`` (transition
        std ``sigma``, default the model's), weigh ``x``.

        ``heading``: a :class:`HeadingObservation` of the new pose, sampled exactly by
        :meth:`_heading_proposal` (bootstrap proposal only).

        Returns ``(particles, log_evidence_increment [...])``.
        """
        if heading is not None and self.proposal != "bootstrap":
            raise ValueError("a heading observation needs the bootstrap proposal")
        need = resampling.ess(p.logw) < self.ess_threshold * p.num_particles  # [...]
        if bool(need.any()):
            r = p.resample(self.generator, self.scheme)
            if not bool(need.all()):
                m = need.unsqueeze(-1)
                r = Particles(
                    torch.where(m.unsqueeze(-1), r.z, p.z),
                    torch.where(m, r.logw, p.logw),
                    None if p.scan is None else torch.where(m.unsqueeze(-1), r.scan, p.scan),
                    None if p.past is None else torch.where(m[..., None, None], r.past, p.past),
                )
            p = r
        if self.proposal == "linearised":
            z, correction = self._linearised_proposal(p, M, x, u, mask, sigma)
            out, inc = self._weigh(z, M, x, mask, p.logw, step, correction)
        else:
            correction = None
            if heading is None:
                z = self.propagate(p, u, sigma)
            else:
                z, correction = self._heading_proposal(p, u, heading, sigma)
            out, inc = self._weigh(z, M, x, mask, p.logw, step, correction)
        if self.history:  # the resampled parents join their ancestors: [..., K, <= L, 3]
            past = p.z.detach().unsqueeze(-2)
            if p.past is not None:
                past = torch.cat([p.past, past], -2)[..., -self.history :, :]
            out.past = past
        return out, inc

    @torch.no_grad()
    def _heading_proposal(self, p: Particles, u: torch.Tensor, obs: HeadingObservation, sigma=None):
        """Sample ``z [..., K, 3]`` from the transition conditioned on a heading observation.

        The transition's heading is Gaussian about its mean ``m`` (std ``s`` from ``sigma`` or
        the model's) and independent of its position noise, and the observation is Gaussian in
        the wrapped residual (std ``sigma_o``), so the optimal proposal is exact: with
        ``r = wrap_period(m - value)`` and ``v = s^2 + sigma_o^2``, the heading is drawn from
        ``N(m - r s^2 / v, s^2 sigma_o^2 / v)`` and the weight gains the predictive
        ``log N(r; 0, sqrt(v))``. With a sharp observation (``sigma_o << s``) every particle
        lands on a heading the observation allows, however narrow the cloud. Where the value is
        nan the heading is the transition's sample and the weight unchanged. Returns
        ``(z, log_weight [..., K])``."""
        mean = self.model.transition.mean(p.z, u.unsqueeze(-2), p.scan)  # [..., K, 3]
        std = self.model.transition.sigma if sigma is None else sigma
        std = torch.as_tensor(std, dtype=mean.dtype)
        eps = torch.randn(mean.shape, generator=self.generator, dtype=mean.dtype)
        z = mean + eps * std
        s = std[..., 2]
        value = torch.as_tensor(obs.value, dtype=mean.dtype).unsqueeze(-1)  # [..., 1]
        seen = ~torch.isnan(value)  # [..., 1]
        half = obs.period / 2
        r = torch.remainder(mean[..., 2] - value.nan_to_num() + half, obs.period) - half
        v = s**2 + obs.sigma**2  # r: [..., K]
        h = mean[..., 2] - r * s**2 / v + eps[..., 2] * (s * obs.sigma / v.sqrt())
        h = torch.where(seen, wrap_angle(h), z[..., 2])
        logw = torch.where(seen, -0.5 * r**2 / v - 0.5 * torch.log(2 * math.pi * v), 0.0)
        return torch.cat([z[..., :2], h.unsqueeze(-1)], -1), logw

    @torch.no_grad()
    def _linearised_proposal(self, p: Particles, M, x, u, mask=None, sigma=None, fd=2e-3):
        """Sample ``z [..., K, 3]`` from the linearised optimal proposal (class doc) and return
        it with ``log p(z | z_prev, u) - log q(z)`` ``[..., K]``."""
        mean = self.model.transition.mean(p.z, u.unsqueeze(-2), p.scan)  # [..., K, 3]
        st = self.model.transition.sigma if sigma is None else sigma
        st = torch.as_tensor(st, dtype=mean.dtype).expand_as(mean)  # [..., K, 3]
        Mloc, s_lik, _, s0 = self._likelihood_params(mean, M, p.logw)
        s_lik = torch.as_tensor(s0 if s_lik is None else s_lik, dtype=mean.dtype)
        if s_lik.dim() < 2:
            s_lik = s_lik.reshape(1, 1)  # else [..., K | 1, 1 | B]
        steps = fd * torch.eye(3, dtype=mean.dtype)  # [3, 3]
        pts = torch.cat([mean.unsqueeze(-2), mean.unsqueeze(-2) + steps], -2)  # [..., K, 4, 3]
        h = self.model.emission_mean(Mloc, pts)  # [..., K, 4, B]
        h0 = h[..., 0, :]  # [..., K, B]
        jt = (h[..., 1:, :] - h0.unsqueeze(-2)) / fd  # [..., K, 3, B] J^T
        r = x.unsqueeze(-2) - h0  # [..., K, B]
        use = (r.abs() < self.proposal_gate * s_lik).to(mean.dtype)  # [..., K, B]
        if mask is not None:
            use = use * mask.unsqueeze(-2).to(mean.dtype)
        jt = jt * use.unsqueeze(-2) / s_lik.unsqueeze(-2)  # [..., K, 3, B] J^T / sigma
        prec = torch.diag_embed(st.pow(-2)) + jt @ jt.transpose(-1, -2)  # [..., K, 3, 3]
        cov = torch.linalg.inv(prec)
        shift = cov @ (jt @ (r * use / s_lik).unsqueeze(-1))  # [..., K, 3, 1]
        q = dist.MultivariateNormal(mean + shift.squeeze(-1), covariance_matrix=cov)
        eps = torch.randn(mean.shape, generator=self.generator, dtype=mean.dtype)
        z = q.loc + (q.scale_tril @ eps.unsqueeze(-1)).squeeze(-1)  # [..., K, 3]
        log_t = dist.Normal(mean, st).log_prob(z).sum(-1)  # [..., K]
        return z, log_t - q.log_prob(z)

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
        T = observations.shape[0]
        means = [p.mean()]
        stds = [p.std()]
        for t in range(1, T):
            p, inc = self.step(
                p, M, observations[t], controls[t - 1], None if mask is None else mask[t], step=t
            )
            ev = ev + inc
            means.append(p.mean())
            stds.append(p.std())
        return {
            "mean": torch.stack(means),
            "std": torch.stack(stds),
            "log_evidence": float(ev),
            "particles": p,
        }


def pose_moments(z: torch.Tensor, logw: torch.Tensor | None = None):
    """Weighted mean and std ``[..., 3]`` of poses ``z [..., N, 3]`` (weights ``exp(logw)
    [..., N]``, normalised; None: uniform). The heading's mean is the circular mean and its
    std that of the wrapped deviations from it, so a cloud that straddles +-pi (heading ~pi)
    has the mean ~pi and a small std, not 0 and ~pi."""
    if logw is None:
        logw = torch.full(z.shape[:-1], -math.log(z.shape[-2]), dtype=z.dtype)
    mean = _weighted_pose_mean(z, logw)  # [..., 3]
    d = torch.cat(
        [z[..., :2] - mean[..., None, :2], wrap_angle(z[..., 2:] - mean[..., None, 2:])], -1
    )
    w = logw.exp().unsqueeze(-1)  # [..., N, 1]
    dm = (w * d).sum(-2, keepdim=True)
    return mean, (w * (d - dm) ** 2).sum(-2).sqrt()


class ParticleCache:
    """``N`` cached pose particles for each of ``T`` steps (paper III-D2).

    ``propose`` draws the start particles of a chunk from the moment-matched Gaussian
    ``q^(z_t) = N(mean(xi_t), var(xi_t))`` (paper eq. 3) or, with ``kind="categorical"``, from
    the cached particles plus a little noise (paper Appendix B-I).
    """

    def __init__(self, num_steps: int, num_particles: int = 50, dtype=torch.float32):
        self.z = torch.zeros(num_steps, num_particles, 3, dtype=dtype)
        self.filled = torch.zeros(num_steps, dtype=torch.bool)

    @property
    def num_particles(self) -> int:
        return self.z.shape[1]

    def store(self, t: torch.Tensor, p: Particles, generator=None) -> None:
        """Store particles ``p`` (batch ``[C]``) at steps ``t [C]``, resampled to N by weight."""
        N = self.num_particles
        K = p.num_particles
        logw = p.logw.detach()
        if K != N:
            # systematic resampling to N from K particles: replicate the log weights' grid
            w = logw.exp()
            cdf = torch.cumsum(w, -1)
            cdf[..., -1] = 1.0
            u0 = torch.rand(logw.shape[:-1] + (1,), generator=generator, dtype=w.dtype)
            u = (u0 + torch.arange(N, dtype=w.dtype)) / N
            idx = torch.searchsorted(cdf, u.contiguous()).clamp_(max=K - 1)
        else:
            idx = resampling.systematic(logw, generator)
        self.z[t] = resampling.gather_particles(p.z.detach(), idx).to(self.z.dtype)
        self.filled[t] = True

    def moments(self, t: torch.Tensor):
        """Mean and std ``[C, 3]`` of the cached particles at steps ``t [C]`` (the heading's
        circular, :func:`pose_moments`)."""
        return pose_moments(self.z[t])

    def propose(
        self,
        t: torch.Tensor,
        K: int,
        kind="gaussian",
        noise=1e-3,
        min_std=1e-4,
        generator=None,
        shrink: float = 1.0,
    ):
        """``K`` start particles ``[C, K, 3]`` for chunks starting at ``t [C]``.

        ``shrink`` scales the moment-matched std (``< 1`` concentrates the map's training poses
        around the cached posterior mean).
        """
        if not bool(self.filled[t].all()):
            missing = t[~self.filled[t]].tolist()
            raise ValueError(f"particle cache has no particles at steps {missing[:5]}")
        if kind == "gaussian":
            loc, scale = self.moments(t)
            eps = torch.randn(len(t), K, 3, generator=generator, dtype=loc.dtype)
            z = loc.unsqueeze(1) + eps * (shrink * scale).clamp_min(min_std).unsqueeze(1)
            return torch.cat([z[..., :2], wrap_angle(z[..., 2:])], -1)
        if kind == "categorical":
            N = self.num_particles
            idx = torch.randint(N, (len(t), K), generator=generator)
            z = torch.gather(self.z[t], 1, idx.unsqueeze(-1).expand(-1, -1, 3))
            return z + noise * torch.randn(z.shape, generator=generator, dtype=z.dtype)
        raise ValueError(f"unknown proposal kind {kind!r}")

    def state_dict(self):
        return {"z": self.z.clone(), "filled": self.filled.clone()}

    def load_state_dict(self, d):
        self.z.copy_(d["z"])
        self.filled.copy_(d["filled"])


@dataclass
class ChunkBatch:
    """A minibatch of chunk start steps ``starts [C]`` of length ``length`` over one sequence."""

    starts: torch.Tensor
    length: int


class ParticleChunkELBO(ELBO):
    """Negative ELBO of paper eq. (3) for :class:`pyro.infer.SVI`, on chunks of one traversal.

    ``model`` must sample the site ``"map"`` (e.g. :meth:`DVBFLM.map_model`) and ``guide`` any
    guide over it (:class:`~pyro_slam.guide.MapGuide`, an autoguide, ...). For each chunk the
    start particles come from the cache, the particle filter runs ``length`` steps under one
    reparameterised map sample, and the cache is refreshed with the filtered particles (and one
    step beyond the chunk through the transition). The loss, divided by ``T`` to keep the scale
    per time step, is

        -(T / (C L)) sum_chunks log p^(x_chunk | M) + KL(q(M) || p(M)),

    with an analytic KL when both sides are Normal (Monte Carlo otherwise).

    Args:
        pf: the :class:`ParticleFilter` (shares the model).
        cache: the :class:`ParticleCache`.
        observations ``[T, B]``, controls ``[T-1, D_u]``, mask ``[T, B]`` or None.
        num_particles: particles per chunk during training.
        num_steps_seen: ``T`` in the scaling (online SLAM: steps seen so far); default all.
        reproject_radius: if > 0, each chunk step also writes the map around its pose: the scan
            is reprojected (:func:`~pyro_slam.geometry.reproject_scan`) to ``reproject_samples``
            positions drawn uniformly within this radius of the filtered mean pose, and the
            emission log-likelihood of these pseudo-scans there, times ``reproject_weight``, is
            added to the chunk's evidence in the loss (LiDAR only; ``max_range`` needed). The map
            then learns, from one scan, the sub-cell parallax a scan matcher uses, and the cells
            just ahead of the agent before it reaches them.
        headings: a :class:`HeadingObservation` with ``value [T]`` (nan where none): each chunk
            step samples its heading conditioned on it, as the online filter does.
    """

    def __init__(
        self,
        pf: ParticleFilter,
        cache: ParticleCache,
        observations,
        controls,
        mask=None,
        num_particles: int = 32,
        proposal: str = "gaussian",
        proposal_shrink: float = 1.0,
        refresh: bool = True,
        reproject_radius: float = 0.0,
        reproject_samples: int = 4,
        reproject_weight: float = 1.0,
        max_range: float | None = None,
        headings: HeadingObservation | None = None,
    ):
        super().__init__(num_particles=1)
        self.headings = headings
        if reproject_radius < 0 or reproject_samples < 1 or reproject_weight < 0:
            raise ValueError(
                "reproject_radius and reproject_weight must be >= 0 and reproject_samples >= 1, "
                f"got {reproject_radius}, {reproject_samples}, {reproject_weight}"
            )
        if reproject_radius > 0 and (pf.model.beam_angles is None or max_range is None):
            raise ValueError("reproject_radius > 0 needs a LiDAR emission and max_range")
        self.reproject_radius, self.reproject_samples = reproject_radius, reproject_samples
        self.reproject_weight, self.max_range = reproject_weight, max_range
        self.pf, self.cache = pf, cache
        self.observations, self.controls, self.mask = observations, controls, mask
        self.K = num_particles
        self.proposal, self.proposal_shrink = proposal, proposal_shrink
        self.refresh = refresh
        self.num_steps_seen = observations.shape[0]
        self.last_log_evidence = None
        self._poses = None  # [C, L, 3] filtered mean poses of the last chunks (reprojection)

    def chunk_log_evidence(self, M, batch: ChunkBatch):
        """Run the filter over the chunks; returns ``log p^ [C]`` and refreshes the cache."""
        obs, ctl, mask = self.observations, self.controls, self.mask
        T = obs.shape[0]
        t = batch.starts
        z0 = self.cache.propose(
            t, self.K, self.proposal, generator=self.pf.generator, shrink=self.proposal_shrink
        )
        z0 = z0.to(obs.dtype)
        p, ev = self.pf.init(z0, M, obs[t], None if mask is None else mask[t], step=int(t[0]))
        self.cache.store(t, p, self.pf.generator)
        poses = [p.mean().detach()]  # L x [C, 3]
        for l in range(1, batch.length):
            tl = t + l
            heading = None if self.headings is None else self.headings.at(tl)  # value [C]
            m = None if mask is None else mask[tl]
            p, inc = self.pf.step(p, M, obs[tl], ctl[tl - 1], m, step=int(tl[0]), heading=heading)
            ev = ev + inc
            self.cache.store(tl, p, self.pf.generator)
            poses.append(p.mean().detach())
        self._poses = torch.stack(poses, -2)  # [C, L, 3]
        if self.refresh:
            nxt = t + batch.length
            ok = nxt < min(T, self.num_steps_seen)
            if bool(ok.any()):
                p = p.detach()
                q = Particles(p.z[ok], p.logw[ok], None if p.scan is None else p.scan[ok])
                q = q.resample(self.pf.generator, self.pf.scheme)
                z = self.pf.propagate(q, ctl[nxt[ok] - 1])
                self.cache.store(nxt[ok], Particles(z, q.logw), self.pf.generator)
        return ev

    def reprojection_log_lik(self, M, batch: ChunkBatch) -> torch.Tensor:
        """Emission log-likelihood of the chunks' scans reprojected around their filtered mean
        poses (see ``reproject_radius``), averaged over the samples, summed over steps: ``[C]``.
        Call after :meth:`chunk_log_evidence` on the same batch."""
        model, z = self.pf.model, self._poses  # [C, L, 3]
        steps = batch.starts.unsqueeze(-1) + torch.arange(batch.length)  # [C, L]
        x = self.observations[steps]  # [C, L, B]
        mask = None if self.mask is None else self.mask[steps]
        shape = (*z.shape[:-1], self.reproject_samples)  # [C, L, A]
        g = self.pf.generator
        r = self.reproject_radius * torch.rand(shape, generator=g, dtype=z.dtype).sqrt()
        a = (2 * math.pi) * torch.rand(shape, generator=g, dtype=z.dtype)
        d = torch.stack([r * torch.cos(a), r * torch.sin(a)], -1)  # [C, L, A, 2]
        world = z[..., 2:3] + model.beam_angles.to(z.dtype)  # [C, L, B]
        xs, valid = reproject_scan(x, world, d, self.max_range, mask)  # [C, L, A, B]
        zs = z.unsqueeze(-2) + torch.cat([d, torch.zeros_like(d[..., :1])], -1)  # [C, L, A, 3]
        sigma = self.pf.sigma_emission
        ll = model.emission_log_prob(xs, model.emission_mean(M, zs), valid, sigma)  # [C, L, A]
        return ll.mean(-1).sum(-1)

    def differentiable_loss(self, model, guide, batch: ChunkBatch, *args, **kwargs):
        guide_tr = poutine.trace(guide).get_trace()
        model_tr = poutine.trace(poutine.replay(model, trace=guide_tr)).get_trace()
        g, m = guide_tr.nodes["map"], model_tr.nodes["map"]
        M = g["value"]
        try:
            kl = kl_divergence(g["fn"], m["fn"]).sum()
        except NotImplementedError:
            kl = g["fn"].log_prob(M).sum() - m["fn"].log_prob(M).sum()
        # other guide sites (e.g. an autoguide's auxiliary latent) enter by Monte Carlo
        for name, site in guide_tr.nodes.items():
            if site["type"] == "sample" and name != "map" and not site["is_observed"]:
                kl = kl + site["fn"].log_prob(site["value"]).sum()
        ev = self.chunk_log_evidence(M, batch)  # [C]
        self.last_log_evidence = ev.detach()
        if self.reproject_radius > 0 and self.reproject_weight > 0:
            ev = ev + self.reproject_weight * self.reprojection_log_lik(M, batch)
        T = self.num_steps_seen
        C, L = len(batch.starts), batch.length
        return (-(T / (C * L)) * ev.sum() + kl) / T

    def _get_trace(self, model, guide, args, kwargs):  # pragma: no cover - not trace-based
        raise NotImplementedError("ParticleChunkELBO evaluates the pose part by filtering")

    def loss(self, model, guide, *args, **kwargs):
        with torch.no_grad():
            return float(self.differentiable_loss(model, guide, *args, **kwargs))

    def loss_and_grads(self, model, guide, *args, **kwargs):
        loss = self.differentiable_loss(model, guide, *args, **kwargs)
        loss.backward()
        return float(loss.detach())


def heading_error(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Absolute wrapped heading difference."""
    return wrap_angle(a - b).abs()
