"""The differentiable, batched particle filter over DVBF-LM poses.

:class:`ParticleFilter` is the custom SMC guide over poses of DVBF-LM (paper III-C), run as
:class:`pyro.infer.SMCFilter` runs a model: at each step a :class:`~.proposals.Proposal` (the
transition, or a guide with its importance correction) samples the site ``z_t`` for every
particle, and the model's own step, a one-step :class:`~pyro_slam.model.Window` of
:meth:`DVBFLM.model <pyro_slam.model.DVBFLM.model>` under whatever handlers the model holds
(:meth:`~pyro_slam.model.DVBFLM.handled`), is traced with that sample replayed and vectorised
over the particles in a plate. A particle's incremental log-weight is the trace's: the
log-densities of the observed sites (the scan ``x_t``, under a map belief ``q(M)`` the model's
stated marginalisation over it, :meth:`~pyro_slam.model.DVBFLM.marginal_emission`; the wall
direction ``h_t``), plus, for each latent site, the model's log-density minus the proposal's
-- with the handlers' scales and masks. The global sites (the map, the walls' frame) are
resolved once per step by tracing the model's global window, so a handler that conditions
them reaches the weights. Weights are kept in log space, with ESS-triggered resampling.

Unlike :class:`pyro.infer.SMCFilter` it keeps the autograd graph from the map and emission
parameters to the log-evidence estimate

    log p^(x_{1:T} | M) = sum_t log sum_k w_{t-1,k} p(x_t | z_t^k, M) p(z_t^k | .) / q(z_t^k | .)

(resampling indices and particle positions are treated as samples, i.e. no gradient flows
through them), so the same step serves training (:class:`~.elbo.ParticleChunkELBO`) and
filtering. Particles may carry a batch shape: ``[K, 3]`` or ``[C, K, 3]``.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pyro
import torch
from pyro import poutine
from pyro.poutine.util import site_is_subsample

from ..model.model import FrameBelief, HeadingEvidence, MapBelief, Window
from . import resampling
from .particles import Particles
from .proposals import Drawn, Proposal, TransitionProposal


def _weighed(site) -> bool:
    """Sites that weigh: samples other than ``pyro.deterministic``'s and the plates'."""
    if site["type"] != "sample" or site_is_subsample(site):
        return False
    return not site["infer"].get("_deterministic", False)


def _is_own(site, guide_site) -> bool:
    """Whether the guide drew the model's site from the model's own distribution there (the
    same object, unscaled and unmasked: a bootstrap proposal)."""
    q = getattr(guide_site["fn"], "q", guide_site["fn"])
    return (
        q is site["fn"]
        and site["mask"] is None
        and isinstance(site["scale"], float)
        and (site["scale"] == 1.0)
    )


def step_log_weights(model_trace, guide_trace=None) -> torch.Tensor:
    """A traced window's incremental log-weights ``[..., K]``: the observed sites'
    log-densities (with their scale and mask), plus each latent site's model log-density minus
    its guide's (``guide_trace``, the proposal's site)."""
    model_trace.compute_log_prob(lambda name, site: _weighed(site))
    observed, corrections = None, []
    for name, site in model_trace.nodes.items():
        if not _weighed(site):
            continue
        lp = site["log_prob"]
        if site["is_observed"]:
            observed = lp if observed is None else observed + lp
            continue
        q = None if guide_trace is None else guide_trace.nodes.get(name)
        if q is None:
            raise ValueError(f"the model's latent site {name!r} has no proposal in the filter")
        if _is_own(site, q):
            continue  # drawn from the model's own distribution at the site: no correction
        corrections.append(lp - q["fn"].log_prob(q["value"]))
    out = observed
    for c in corrections:
        out = c if out is None else out + c
    return out


def resolve_globals(model, M, heading: HeadingEvidence | None = None):
    """The global values a filter step runs under: the map (or map belief) ``M`` and the frame
    belief of ``heading`` (its frame and variance), unless the model's handlers set others
    (traced once in the model's global :class:`~pyro_slam.model.Window`; without handlers,
    these). Returns ``(M, frame, trace)``: ``frame`` None without heading evidence, ``trace``
    None without handlers."""
    frame = None if heading is None else FrameBelief(heading.frame, heading.frame_var)
    if model.handler is None:
        return M, frame, None
    with poutine.block(), pyro.validation_enabled(False):
        tr = poutine.trace(model.handled()).get_trace(
            None, None, None, window=Window(map=M, frame=frame)
        )
    if frame is not None and "frame" in tr.nodes:
        frame = tr.nodes["frame"]["value"]
    return tr.nodes["map"]["value"], frame, tr


class ParticleFilter:
    """Particle filter over DVBF-LM poses (module doc).

    Args:
        model: the :class:`~pyro_slam.model.DVBFLM` (its handlers included:
            :meth:`~pyro_slam.model.DVBFLM.handled`).
        proposal: the pose proposal (:class:`~.proposals.Proposal`; default the transition).
        generator: ``torch.Generator`` for reproducible noise and resampling.
        ess_threshold: resample when ``ESS < ess_threshold * K``.
        scheme: ``"systematic"`` or ``"multinomial"`` (:mod:`.resampling`).
        autocast_dtype: e.g. ``torch.bfloat16``: run the emission in reduced precision when no
            gradient is needed (filtering under a fixed map); ~2-3x faster on CPU.
    """

    def __init__(
        self,
        model,
        proposal: Proposal | None = None,
        generator: torch.Generator | None = None,
        ess_threshold: float = 0.5,
        scheme: str = "systematic",
        autocast_dtype: torch.dtype | None = None,
    ):
        if scheme not in resampling.SCHEMES:
            raise ValueError(f"unknown resampling scheme {scheme!r}")
        self.model = model
        self.proposal = TransitionProposal() if proposal is None else proposal
        self.generator = generator
        self.ess_threshold, self.scheme = ess_threshold, scheme
        self.autocast_dtype = autocast_dtype
        self.last_trace = None  # the model's trace of the last step (after weighing)
        self.last_globals = None  # the model's trace of the last global window (or None)

    def resolve(self, M, heading: HeadingEvidence | None = None):
        """The global values of the step (:func:`resolve_globals`); the model's trace of them
        is ``last_globals`` (None without handlers)."""
        M, frame, self.last_globals = resolve_globals(self.model, M, heading)
        return M, frame

    @staticmethod
    def _evidence(heading: HeadingEvidence | None, frame) -> HeadingEvidence | None:
        """The step's wall directions per particle, in the resolved ``frame``."""
        if heading is None:
            return None
        if isinstance(frame, FrameBelief):
            heading = replace(heading, frame=frame.mean, frame_var=frame.var)
        elif frame is not None:
            heading = replace(heading, frame=frame, frame_var=0.0)
        return heading.per_particle()

    def _trace(self, window: Window, guide_trace=None):
        """The model's trace of ``window`` (the proposal's sites replayed), and the
        incremental log-weights ``[..., K]``."""
        model = self.model.handled()
        if guide_trace is not None:
            model = poutine.replay(model, trace=guide_trace)
        if self.autocast_dtype is not None and not isinstance(window.map, MapBelief):
            window.dtype = self.autocast_dtype
        with poutine.block(), pyro.validation_enabled(False):
            tr = poutine.trace(model).get_trace(None, None, None, window=window)
            self.last_trace = tr
            return tr, step_log_weights(tr, guide_trace)

    def log_likelihood(self, z, M, x, mask=None, heading=None):
        """The model's log-likelihood of the step's observations at poses ``z [..., K, 3]``:
        the scan ``x [..., B]`` (``mask [..., B]``) under the map ``M [w, h, D]`` or marginalised
        over a :class:`~pyro_slam.model.MapBelief`, plus the heading factor's log-density of
        ``heading`` (:class:`~pyro_slam.model.HeadingEvidence`, batch ``[...]``), from a trace
        of the model's step at these poses. Returns ``(loglik [..., K], scan [..., K, B])``,
        the scans predicted at the map (mean)."""
        M, frame = self.resolve(M, heading)
        w = self._window(None, z, M, frame, x, None, mask, heading, given=True)
        tr, ll = self._trace(w)
        return ll, tr.nodes["_RETURN"]["value"][1]

    def _window(self, t, z, M, frame, x, u, mask, heading, **kw) -> Window:
        obs = None if x is None else x.unsqueeze(-2)  # [..., 1, B]
        mask = None if mask is None else mask.unsqueeze(-2)
        return Window(
            0 if t is None else int(t),
            M,
            frame,
            poses=z,
            x=obs,
            u=u,
            mask=mask,
            heading=self._evidence(heading, frame),
            **kw,
        )

    def state_dict(self) -> dict:
        """What the next step reads besides the particles and the run's generator: nothing (the
        weights are the model's, the proposal keeps no state); kept so that a checkpoint stores
        any filter alike."""
        return {}

    def load_state_dict(self, d: dict) -> None:
        """Restore :meth:`state_dict`; ``TypeError`` for anything but a dict."""
        if not isinstance(d, dict):
            raise TypeError(f"a filter state must be a dict, got {type(d).__name__}")

    def _weigh(self, tr_logw, logw, step, scan):
        """New weights from the incremental log-weights ``[..., K]``: the particles' normalised
        log-weights and the log-evidence increment ``[...]``."""
        joint = logw + tr_logw
        resampling.check_weights(joint.detach(), step)
        inc = torch.logsumexp(joint, -1)  # [...]
        # normalised weights keep their graph: without resampling, the next step's evidence
        # depends on the map through them too (resampling resets them to constants)
        return joint - inc.unsqueeze(-1), inc

    def init(self, z0, M, x, mask=None, step=0, heading: HeadingEvidence | None = None):
        """Weigh initial particles ``z0 [..., K, 3]`` by ``x [..., B]`` (and ``heading``): the
        model's step ``step`` at these poses (no pose site).

        Returns ``(particles, log_evidence [...])`` with ``log p^(x_0) = log mean_k p(x_0|z^k)``.
        """
        K = z0.shape[-2]
        logw = z0.new_full(z0.shape[:-1], -math.log(K))
        M, frame = self.resolve(M, heading)
        w = self._window(step, z0.detach(), M, frame, x, None, mask, heading, given=True)
        tr, inc_w = self._trace(w)
        scan = tr.nodes["_RETURN"]["value"][1]
        logw, inc = self._weigh(inc_w, logw, step, scan)
        return Particles(w.poses, logw, scan), inc

    def propagate(self, p: Particles, u: torch.Tensor) -> torch.Tensor:
        """Sample ``z_{t+1} ~ p(. | z_t, u_t, mu_E(m_t))``: ``[..., K, 3]`` (no gradient)."""
        return TransitionProposal().propose(self.model, p, u.unsqueeze(-2), self.generator)[0]

    def resample_if_needed(self, p: Particles) -> Particles:
        """Resample the batch elements whose ESS is below ``ess_threshold * K``; the result's
        ``ancestors`` index ``p``'s particles."""
        need = resampling.ess(p.logw) < self.ess_threshold * p.num_particles  # [...]
        if not bool(need.any()):
            return Particles(p.z, p.logw, p.scan, p.identity())
        r = p.resample(self.generator, self.scheme)
        if bool(need.all()):
            return r
        return r.where(need, Particles(p.z, p.logw, p.scan, p.identity()))

    def step(self, p: Particles, M, x, u, mask=None, step=None, heading=None):
        """One filtering step: resample if needed, propose with ``u [..., D_u]`` (the proposal
        may read the scan ``x [..., B]``, the map and the step's ``heading`` evidence), weigh
        by the trace of the model's step (module doc).

        Returns ``(particles, log_evidence_increment [...])``.
        """
        p = self.resample_if_needed(p)
        M, frame = self.resolve(M, heading)
        uk = u.unsqueeze(-2)  # [..., 1, D_u]
        w = self._window(step, p.z, M, frame, x, uk, mask, heading, scans=p.scan)
        z, q = self.proposal.propose(
            self.model, p, uk, self.generator, x=x, mask=mask, M=M, heading=w.heading
        )
        name = f"z_{w.step}"
        guide = poutine.trace(lambda: pyro.sample(name, Drawn(q, z))).get_trace()
        tr, inc_w = self._trace(w, guide)
        scan = tr.nodes["_RETURN"]["value"][1]
        logw, inc = self._weigh(inc_w, p.logw, step, scan)
        return Particles(tr.nodes[name]["value"], logw, scan, p.ancestors), inc

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
        means, stds = [p.mean()], [p.std()]
        for t in range(1, observations.shape[0]):
            m = None if mask is None else mask[t]
            p, inc = self.step(p, M, observations[t], controls[t - 1], m, step=t)
            ev = ev + inc
            means.append(p.mean())
            stds.append(p.std())
        return {
            "mean": torch.stack(means),
            "std": torch.stack(stds),
            "log_evidence": float(ev),
            "particles": p,
        }
