"""The SLAM algorithms, as small units over a run's components, state and data (as Pyro's
``SMCFilter`` is ``init``/``step`` over an ``SMCState``):

* :func:`filter_step` -- one step of the pose filter under a map belief (from the prior, from
  given start particles, or from the last step's particles), recorded in the particle cache and
  the particles' history;
* :func:`svi_step` -- one SVI step on a minibatch of chunks;
* :func:`online_sweep` -- filter, insert, refine the walls' frame and learn, step after step;
* :func:`offline` -- the online sweep, then rounds of SVI on chunks from anywhere
  (:func:`offline_round`), then the final poses (:func:`filter_pass` or :func:`cache_pass`).

Each takes the run's :class:`~pyro_slam.slam.parts.Components` ``c`` (model, filter, SVI,
inserter, heading), its :class:`~pyro_slam.slam.state.SLAMState` ``st`` (advanced in place:
particles, cache, history, generator, counters and outputs) and its
:class:`~pyro_slam.slam.parts.RunData` ``data``; the sweeps call ``checkpoint(every)`` where a
checkpoint may be written (``every``: only on the run's checkpoint interval).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from tqdm.auto import tqdm

from ..geometry import wrap_angle
from ..inference import ChunkBatch, transition_log_density
from ..model import MapBelief
from .insertion import ScanInserter
from .parts import Components, RunData
from .state import Phase, SLAMState


def _never(every: bool = True) -> None:
    """Write no checkpoint (the default ``checkpoint`` of the sweeps)."""


def filter_step(
    c: Components,
    st: SLAMState,
    data: RunData,
    t: int,
    M: MapBelief,
    start: torch.Tensor | None = None,
    store: bool = True,
) -> None:
    """Step ``t`` of the pose filter under ``M``: from the initial pose prior (``t = 0``), from
    the start particles ``start [K, 3]`` (a new lineage), or from the state's particles; the
    result becomes ``st.particles``, enters the cache (``store``) and the history."""
    obs, mask = data.obs, data.mask
    x, m = obs[t], None if mask is None else mask[t]
    heading = None if c.heading is None else c.heading.evidence().at(t)
    fresh = t == 0 or start is not None
    if fresh:
        if start is None:
            K = data.cfg.filter.particles
            eps = torch.randn(K, 3, generator=st.gen, dtype=obs.dtype)
            start = data.init_pose + c.model.init_scale * eps
        st.particles, _ = c.pf.init(start.to(obs.dtype), M, x, m, step=t, heading=heading)
    else:
        u = data.ctl[t - 1]
        st.particles, _ = c.pf.step(st.particles, M, x, u, m, step=t, heading=heading)
    if store:
        st.cache.store(torch.tensor([t]), st.particles.batched(), st.gen)
    st.history.record(t, st.particles, fresh=fresh)


def world_std(
    inserter: ScanInserter | None, mean: torch.Tensor, std: torch.Tensor
) -> tuple[torch.Tensor, float]:
    """A pose's world-frame std ``[3]`` from the cloud's (``mean [3]``, ``std [3]``, relative to
    the map): on x and y, the placement variance of the map where its beams stop added
    (:meth:`~pyro_slam.slam.insertion.ScanInserter.placement_at`; without scan insertion, the
    cloud's own). Returns it and that placement variance."""
    if inserter is None:
        return std, 0.0
    var = inserter.placement_at(mean)
    out = std.clone()
    out[:2] = (std[:2] ** 2 + var).sqrt()
    return out, var


def insertion_scale(pf, t: int) -> float | None:
    """How scan insertion reads step ``t``'s scan under the model's handlers, from the filter's
    traces of the step: the scale of the site ``x_t`` (1 without a handler), or None where a
    handler gives the map (the site ``"map"`` observed: no belief to update)."""
    glob = getattr(pf, "last_globals", None)
    if glob is not None and glob.nodes["map"]["is_observed"]:
        return None
    tr = getattr(pf, "last_trace", None)
    site = None if tr is None else tr.nodes.get(f"x_{t}")
    if site is None or site["mask"] is False:
        return 1.0 if site is None else 0.0
    return float(site["scale"])


def svi_step(
    c: Components, st: SLAMState, data: RunData, lo: int, hi: int, newest: int | None
) -> float:
    """One SVI step on chunks starting in ``[lo, hi]`` (plus the chunk at ``newest``)."""
    tc = data.cfg.training
    starts = torch.randint(lo, hi + 1, (tc.chunks - (newest is not None),), generator=st.gen)
    if newest is not None:
        starts = torch.cat([torch.tensor([newest]), starts])
    loss = c.svi.step(ChunkBatch(starts, tc.chunk_length))
    if not math.isfinite(loss):
        raise FloatingPointError(f"SVI loss became {loss} (step t={st.t})")
    return loss


def online_sweep(
    c: Components,
    st: SLAMState,
    data: RunData,
    progress: bool,
    checkpoint: Callable[[bool], None] = _never,
) -> None:
    """The online sweep from ``st.t``: at each step the filter under the current map belief,
    scan insertion at the cloud's mean, the walls' frame refined with its heading, and every
    ``training.every`` steps (0: never) one SVI step on the newest chunk and replayed older
    ones."""
    T, L, every = data.T, data.cfg.training.chunk_length, data.cfg.training.every
    bar = tqdm(total=T, initial=st.t, desc="online SLAM", disable=not progress)
    while st.t < T:
        t = st.t
        with torch.no_grad():
            filter_step(c, st, data, t, c.map_belief())
        mean, std, anchor = _cloud(c, st)
        if st.phase == Phase.ONLINE:
            st.estimates.append(mean.tolist())
            st.stds.append(std.tolist())
            st.anchors.append(anchor)
        else:  # offline SLAM's initial sweep: kept for diagnostics (result's "sweep_mean")
            st.sweep_estimates.append(mean.tolist())
        scale = insertion_scale(c.pf, t) if c.inserter is not None else None
        if scale is not None:
            var = float((std[:2] ** 2).mean())
            c.inserter.insert(data.obs[t], data.valid(t), mean, var, scale)
        if c.heading is not None:  # (with the weighted cloud's heading std)
            c.heading.refine(t, float(mean[2]), float(st.particles.std()[2]))
        if every and t >= L - 1 and t % every == 0:
            c.elbo.num_steps_seen = t + 1
            st.losses.append(svi_step(c, st, data, 0, t - L + 1, t - L + 1))
        st.t += 1
        bar.update(1)
        checkpoint(True)
    bar.close()
    c.elbo.num_steps_seen = T


def filter_pass(c: Components, st: SLAMState, data: RunData, progress: bool, desc: str):
    """Filter the whole traversal under the map belief (refreshes the cache); the pose means,
    world-frame stds and placement variances per step (:func:`world_std`)."""
    M = c.map_belief()
    out = ([], [], [])
    with torch.no_grad():
        for t in tqdm(range(data.T), desc=desc, disable=not progress, leave=False):
            filter_step(c, st, data, t, M)
            _record(c, st, out)
    return out


def _cloud(c: Components, st: SLAMState) -> tuple[torch.Tensor, torch.Tensor, float]:
    """The cloud's mean ``[3]``, world-frame std ``[3]`` (its own,
    :meth:`~pyro_slam.inference.Particles.posterior_std`, with the placement added) and
    placement variance (:func:`world_std`)."""
    mean = st.particles.mean()
    return mean, *world_std(c.inserter, mean, st.particles.posterior_std())


def _record(c: Components, st: SLAMState, out: tuple) -> None:
    """Append the cloud's mean, world-frame std and placement variance to ``out``."""
    mean, std, anchor = _cloud(c, st)
    out[0].append(mean.tolist())
    out[1].append(std.tolist())
    out[2].append(anchor)


def cache_pass(c: Components, st: SLAMState, data: RunData, progress: bool, desc: str):
    """Offline poses as the paper's Appendix B-I filters them: the traversal in consecutive
    chunks of ``chunk_length`` steps, each started from its first step's cached particles
    (categorical over the cache, plus 1e-3 noise) and filtered under the map belief; no
    particles cross a chunk boundary and the cache is left as it is."""
    M, L, K = c.map_belief(), data.cfg.training.chunk_length, data.cfg.filter.particles
    out = ([], [], [])
    with torch.no_grad():
        for s in tqdm(range(0, data.T, L), desc=desc, disable=not progress, leave=False):
            start = st.cache.propose(torch.tensor([s]), K, "categorical", generator=st.gen)[0]
            for t in range(s, min(s + L, data.T)):
                filter_step(c, st, data, t, M, start if t == s else None, store=False)
                _record(c, st, out)
    return out


def offline_round(
    c: Components,
    st: SLAMState,
    data: RunData,
    progress: bool,
    checkpoint: Callable[[bool], None] = _never,
) -> None:
    """One offline round: (a forward filter pass, then) ``offline.svi_steps`` SVI steps."""
    cfg, L = data.cfg, data.cfg.training.chunk_length
    if st.phase == Phase.FILTER:
        if cfg.offline.estimate == "forward":  # "cache": only the SVI chunks refresh it
            filter_pass(c, st, data, progress, f"filter pass {st.round + 1}")
        st.phase, st.t = Phase.SVI, 0
    n = cfg.offline.svi_steps
    bar = tqdm(total=n, initial=st.t, desc=f"offline SVI {st.round + 1}", disable=not progress)
    while st.t < n:
        st.losses.append(svi_step(c, st, data, 0, data.T - L, None))
        st.t += 1
        bar.update(1)
        checkpoint(True)
    bar.close()
    st.round += 1
    st.phase, st.t = Phase.FILTER, 0
    checkpoint(False)


def offline(
    c: Components,
    st: SLAMState,
    data: RunData,
    progress: bool,
    checkpoint: Callable[[bool], None] = _never,
) -> None:
    """Offline SLAM from where the state stands: the online sweep, the rounds, the final
    poses."""
    if st.phase == Phase.SWEEP:
        online_sweep(c, st, data, progress, checkpoint)
        st.phase, st.t = Phase.SVI, 0
        checkpoint(False)
    while st.round < data.cfg.offline.rounds:
        offline_round(c, st, data, progress, checkpoint)
    final = cache_pass if data.cfg.offline.estimate == "cache" else filter_pass
    st.estimates, st.stds, st.anchors = final(c, st, data, progress, "final filter pass")


def estimates(st: SLAMState, data: RunData, model) -> dict:
    """The run's pose estimates (see :meth:`~pyro_slam.slam.runner.SLAM.result`): the filtered
    means and world-frame stds ``[T, 3]``, smoothed over the particles' history once the run is
    done (with the placement variance of :func:`world_std` added), the SVI losses and the
    offline sweep's means. ``model``: the :class:`~pyro_slam.model.DVBFLM` whose transition
    density the smoother's backward kernels use."""
    filtered = np.asarray(st.estimates, dtype=np.float64).reshape(-1, 3)
    filtered_std = np.asarray(st.stds, dtype=np.float64).reshape(-1, 3)
    mean, std = filtered, filtered_std
    if st.phase == Phase.DONE and st.history.filled.any():
        lag = data.T if st.mode == "offline" else data.cfg.filter.lag
        log_f = transition_log_density(model, st.history, data.ctl)
        m, sd = st.history.smoothed(lag, log_f)
        mean, std = m.double().numpy(), sd.double().numpy()
        mean[:, 2] = wrap_angle(mean[:, 2])
        if len(st.anchors) == len(std):
            std[:, :2] = np.sqrt(std[:, :2] ** 2 + np.asarray(st.anchors)[:, None])
    return {
        "mean": mean,
        "std": std,
        "filtered_mean": filtered,
        "filtered_std": filtered_std,
        "losses": np.asarray(st.losses),
        "sweep_mean": np.asarray(st.sweep_estimates, dtype=np.float64).reshape(-1, 3),
    }
