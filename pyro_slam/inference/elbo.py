"""The particle-chunk ELBO of DVBF-LM (paper eq. 3) for :class:`pyro.infer.SVI`."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from pyro import poutine
from pyro.infer import ELBO
from torch.distributions import kl_divergence

from ..model.model import FrameBelief, HeadingEvidence, Window
from .cache import ParticleCache
from .filter import ParticleFilter
from .particles import Particles


@dataclass
class ChunkBatch:
    """A minibatch of chunk start steps ``starts [C]`` of length ``length`` over one sequence."""

    starts: torch.Tensor
    length: int


class ParticleChunkELBO(ELBO):
    """Negative ELBO of paper eq. (3) for :class:`pyro.infer.SVI`, on chunks of one traversal.

    ``model`` is :meth:`DVBFLM.model <pyro_slam.model.DVBFLM.model>` (or the model under
    handlers, :meth:`~pyro_slam.model.DVBFLM.handled`) and ``guide`` any guide of its global
    sites -- ``"map"`` and, with a heading factor, ``"frame"`` -- called with the model's
    arguments (:class:`~pyro_slam.model.GlobalGuide`: a :class:`~pyro_slam.model.MapGuide`,
    an autoguide over ``poutine.block(model, expose=["map"])``, ..., with
    :class:`~pyro_slam.model.FrameGuide`). Each SVI step traces the guide, replays it into the
    model's global :class:`~pyro_slam.model.Window` (a handler that sets a global site wins),
    and, for each chunk, starts particles from the cache, filters ``length`` steps through the
    model's one-step windows under that sample of the globals (:class:`~.filter.ParticleFilter`)
    and refreshes the cache with the filtered particles (and one step beyond the chunk through
    the transition). The loss, divided by ``T`` to keep the scale per time step, is

        -(T / (C L)) sum_chunks log p^(x_chunk | M, phi) + KL(q(M, phi) || p(M, phi)),

    with an analytic KL per site where both sides have one (Monte Carlo otherwise), as
    :class:`pyro.infer.TraceMeanField_ELBO` takes it. With one particle and one chunk over the
    whole traversal from the initial-pose prior, its value and gradient times ``T`` are
    ``TraceMeanField_ELBO``'s on the same trace of the model and the SLAM guide
    (:func:`~.proposals.sequence_guide`).

    Args:
        pf: the :class:`~.filter.ParticleFilter` (shares the model).
        cache: the :class:`~.cache.ParticleCache`.
        observations ``[T, B]``, controls ``[T-1, D_u]``, mask ``[T, B]`` or None.
        num_particles: particles per chunk during training.
        proposal: the cache's chunk proposal, ``"gaussian"`` (eq. 3) or ``"categorical"``.
        refresh: also refresh the cache one step beyond each chunk.
        headings: the wall directions seen in the scans, a
            :class:`~pyro_slam.model.HeadingEvidence` with ``direction [T]`` (nan where none),
            observed under the model's heading factor in the sampled frame.
        init_pose: the start pose ``[3]`` (the model's argument; the guide's too).
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
        refresh: bool = True,
        headings: HeadingEvidence | None = None,
        init_pose=None,
    ):
        super().__init__(num_particles=1)
        self.pf, self.cache, self.headings = pf, cache, headings
        self.observations, self.controls, self.mask = observations, controls, mask
        self.init_pose = init_pose
        self.K, self.proposal, self.refresh = num_particles, proposal, refresh
        self.num_steps_seen = observations.shape[0]
        self.last_log_evidence = None

    @property
    def model_args(self) -> tuple:
        """The model's (and guide's) arguments: ``(observations, controls, init_pose, mask,
        headings)``."""
        return self.observations, self.controls, self.init_pose, self.mask, self.headings

    def chunk_log_evidence(self, M, batch: ChunkBatch, frame=None):
        """Run the filter over the chunks under the map ``M`` and the frame ``frame`` (a sample;
        with heading evidence); returns ``log p^ [C]`` and refreshes the cache."""
        obs, ctl, mask = self.observations, self.controls, self.mask
        t = batch.starts
        z0 = self.cache.propose(t, self.K, self.proposal, generator=self.pf.generator)
        z0 = z0.to(obs.dtype)
        headings = None
        loc, var = (frame.mean, frame.var) if isinstance(frame, FrameBelief) else (frame, 0.0)
        if self.headings is not None and loc is not None and not math.isnan(float(loc)):
            headings = replace(self.headings, frame=loc, frame_var=var)
        h0 = None if headings is None else headings.at(t)
        p, ev = self.pf.init(
            z0, M, obs[t], None if mask is None else mask[t], step=int(t[0]), heading=h0
        )
        self.cache.store(t, p, self.pf.generator)
        for l in range(1, batch.length):
            tl = t + l
            heading = None if headings is None else headings.at(tl)  # direction [C]
            m = None if mask is None else mask[tl]
            p, inc = self.pf.step(p, M, obs[tl], ctl[tl - 1], m, step=int(tl[0]), heading=heading)
            ev = ev + inc
            self.cache.store(tl, p, self.pf.generator)
        if self.refresh:
            self._refresh_beyond(p, t + batch.length)
        return ev

    def _refresh_beyond(self, p: Particles, nxt: torch.Tensor) -> None:
        """Propagate the chunks' last particles ``p`` one step to ``nxt [C]`` into the cache
        (where that step has been seen)."""
        ok = nxt < min(self.observations.shape[0], self.num_steps_seen)
        if bool(ok.any()):
            p = p.detach()
            q = Particles(p.z[ok], p.logw[ok], None if p.scan is None else p.scan[ok])
            q = q.resample(self.pf.generator, self.pf.scheme)
            z = self.pf.propagate(q, self.controls[nxt[ok] - 1])
            self.cache.store(nxt[ok], Particles(z, q.logw), self.pf.generator)

    def global_traces(self, model, guide):
        """The guide's trace and the model's trace of its global window, replayed from it."""
        args = self.model_args
        guide_tr = poutine.trace(guide).get_trace(*args)
        model_tr = poutine.trace(poutine.replay(model, trace=guide_tr)).get_trace(
            *args, window=Window(frame=FrameBelief())
        )
        return guide_tr, model_tr

    def differentiable_loss(self, model, guide, batch: ChunkBatch, *args, **kwargs):
        guide_tr, model_tr = self.global_traces(model, guide)
        kl = 0.0
        for name, g in guide_tr.nodes.items():
            if g["type"] != "sample" or g["is_observed"]:
                continue
            m = model_tr.nodes.get(name)
            if m is None:  # a guide-only site (an autoguide's auxiliary latent): Monte Carlo
                kl = kl + g["fn"].log_prob(g["value"]).sum()
                continue
            if m["is_observed"]:  # a handler set the model's value: the guide's is unused
                continue
            try:
                kl = kl + kl_divergence(g["fn"], m["fn"]).sum()
            except NotImplementedError:
                kl = kl + (g["fn"].log_prob(g["value"]) - m["fn"].log_prob(g["value"])).sum()
        M = model_tr.nodes["map"]["value"]
        frame = model_tr.nodes["frame"]["value"] if "frame" in model_tr.nodes else None
        ev = self.chunk_log_evidence(M, batch, frame)  # [C]
        self.last_log_evidence = ev.detach()
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
        if getattr(loss, "requires_grad", False):  # (as Trace_ELBO: nothing to train, no step)
            loss.backward()
        return float(loss.detach())
