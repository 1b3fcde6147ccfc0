"""The SLAM algorithms, as small units over a run's components and state (as Pyro's
``SMCFilter`` is ``init``/``step`` over an ``SMCState``):

* :func:`filter_step` -- one step of the pose filter under a map belief (from the prior, from
  given start particles, or from the last step's particles), recorded in the particle cache and
  the particles' history;
* :func:`svi_step` -- one SVI step on a minibatch of chunks;
* :func:`online_sweep` -- filter, insert, refine the walls' frame and learn, step after step;
* :func:`offline` -- the online sweep, then rounds of SVI on chunks from anywhere
  (:func:`offline_round`), then the final poses (:func:`filter_pass` or :func:`cache_pass`).

Each takes the run (a :class:`~pyro_slam.slam.runner.SLAM`: its data, model, filter, cache,
history, SVI, inserter, heading, generator) and advances its :class:`SLAMState`, saving
checkpoints where the run asks for them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
import torch
from tqdm.auto import tqdm

from ..geometry import wrap_angle
from ..inference import ChunkBatch
from ..model import MapBelief


class Phase(StrEnum):
    """Where a run is: the online sweep of an online run (``ONLINE``) or of offline SLAM
    (``SWEEP``), an offline round's SVI steps (``SVI``) or its filter pass (``FILTER``), or
    finished (``DONE``). Its value is what checkpoints store."""

    ONLINE = "online"
    SWEEP = "online-init"
    SVI = "offline-svi"
    FILTER = "offline-filter"
    DONE = "done"


@dataclass
class SLAMState:
    """Everything a run needs to continue: written to and read from checkpoints."""

    mode: str
    phase: Phase = Phase.ONLINE
    t: int = 0  # next time step (online) / next SVI step (offline)
    round: int = 0
    estimates: list = field(default_factory=list)  # per step [3]
    stds: list = field(default_factory=list)
    losses: list = field(default_factory=list)
    # per step: the placement variance of the map the pose is localised against (world_std)
    anchors: list = field(default_factory=list)
    # offline SLAM: the initial online sweep's pose means, per step [3]
    sweep_estimates: list = field(default_factory=list)
    wall_time_s: float = 0.0  # the run's wall time so far, summed over resumes

    def __post_init__(self):
        self.phase = Phase(self.phase)


def filter_step(run, t: int, M: MapBelief, start=None, store: bool = True) -> None:
    """Step ``t`` of the pose filter under ``M``: from the initial pose prior (``t = 0``), from
    the start particles ``start [K, 3]`` (a new lineage), or from the run's particles; the result
    becomes ``run.particles``, enters the cache (``store``) and the history."""
    x, m = run.obs[t], None if run.mask is None else run.mask[t]
    heading = None if run.heading is None else run.heading.evidence().at(t)
    fresh = t == 0 or start is not None
    if fresh:
        if start is None:
            K = run.cfg.filter.particles
            eps = torch.randn(K, 3, generator=run.gen, dtype=run.obs.dtype)
            start = run.init_pose + run.model.init_scale * eps
        run.particles, _ = run.pf.init(start.to(run.obs.dtype), M, x, m, step=t, heading=heading)
    else:
        u = run.ctl[t - 1]
        run.particles, _ = run.pf.step(run.particles, M, x, u, m, step=t, heading=heading)
    if store:
        run.cache.store(torch.tensor([t]), run.particles.batched(), run.gen)
    run.history.record(t, run.particles, fresh=fresh)


def world_std(run, mean: torch.Tensor, std: torch.Tensor) -> tuple[torch.Tensor, float]:
    """A pose's world-frame std ``[3]`` from the cloud's (``mean [3]``, ``std [3]``, relative to
    the map): on x and y, the placement variance of the map where its beams stop added
    (:meth:`~pyro_slam.slam.insertion.ScanInserter.placement_at`; without scan insertion, the
    cloud's own). Returns it and that placement variance."""
    if run.inserter is None:
        return std, 0.0
    var = run.inserter.placement_at(mean)
    out = std.clone()
    out[:2] = (std[:2] ** 2 + var).sqrt()
    return out, var


def svi_step(run, lo: int, hi: int, newest: int | None) -> float:
    """One SVI step on chunks starting in ``[lo, hi]`` (plus the chunk at ``newest``)."""
    tc = run.cfg.training
    starts = torch.randint(lo, hi + 1, (tc.chunks - (newest is not None),), generator=run.gen)
    if newest is not None:
        starts = torch.cat([torch.tensor([newest]), starts])
    loss = run.svi.step(ChunkBatch(starts, tc.chunk_length))
    if not math.isfinite(loss):
        raise FloatingPointError(f"SVI loss became {loss} (step t={run.state.t})")
    return loss


def _checkpoint(run, every: bool = True) -> None:
    if run.checkpoint and (not every or run.state.t % run.checkpoint_every == 0):
        run.save(run.checkpoint)


def online_sweep(run, progress: bool) -> None:
    """The online sweep from ``state.t``: at each step the filter under the current map belief,
    scan insertion at the cloud's mean, the walls' frame refined with its heading, and every
    ``training.every`` steps one SVI step on the newest chunk and replayed older ones."""
    st, T, L = run.state, run.T, run.cfg.training.chunk_length
    bar = tqdm(total=T, initial=st.t, desc="online SLAM", disable=not progress)
    while st.t < T:
        t = st.t
        with torch.no_grad():
            filter_step(run, t, run.map_belief())
        mean, std, anchor = _cloud(run)
        if st.phase == Phase.ONLINE:
            st.estimates.append(mean.tolist())
            st.stds.append(std.tolist())
            st.anchors.append(anchor)
        else:  # offline SLAM's initial sweep: kept for diagnostics (result's "sweep_mean")
            st.sweep_estimates.append(mean.tolist())
        if run.inserter is not None:
            var = float((std[:2] ** 2).mean())
            run.inserter.insert(run.obs[t], run.valid(t), mean, var)
        if run.heading is not None:
            run.heading.refine(t, float(mean[2]), float(std[2]))
        if t >= L - 1 and t % run.cfg.training.every == 0:
            run.elbo.num_steps_seen = t + 1
            st.losses.append(svi_step(run, 0, t - L + 1, t - L + 1))
        st.t += 1
        bar.update(1)
        _checkpoint(run)
    bar.close()
    run.elbo.num_steps_seen = T


def filter_pass(run, progress: bool, desc: str):
    """Filter the whole traversal under the map belief (refreshes the cache); the pose means,
    world-frame stds and placement variances per step (:func:`world_std`)."""
    M = run.map_belief()
    out = ([], [], [])
    with torch.no_grad():
        for t in tqdm(range(run.T), desc=desc, disable=not progress, leave=False):
            filter_step(run, t, M)
            _record(run, out)
    return out


def _cloud(run) -> tuple[torch.Tensor, torch.Tensor, float]:
    """The cloud's mean ``[3]``, world-frame std ``[3]`` and placement variance
    (:func:`world_std`)."""
    mean = run.particles.mean()
    return mean, *world_std(run, mean, run.particles.std())


def _record(run, out: tuple) -> None:
    """Append the cloud's mean, world-frame std and placement variance to ``out``."""
    mean, std, anchor = _cloud(run)
    out[0].append(mean.tolist())
    out[1].append(std.tolist())
    out[2].append(anchor)


def cache_pass(run, progress: bool, desc: str):
    """Offline poses as the paper's Appendix B-I filters them: the traversal in consecutive
    chunks of ``chunk_length`` steps, each started from its first step's cached particles
    (categorical over the cache, plus 1e-3 noise) and filtered under the map belief; no
    particles cross a chunk boundary and the cache is left as it is."""
    M, L, K = run.map_belief(), run.cfg.training.chunk_length, run.cfg.filter.particles
    out = ([], [], [])
    with torch.no_grad():
        for s in tqdm(range(0, run.T, L), desc=desc, disable=not progress, leave=False):
            start = run.cache.propose(torch.tensor([s]), K, "categorical", generator=run.gen)[0]
            for t in range(s, min(s + L, run.T)):
                filter_step(run, t, M, start if t == s else None, store=False)
                _record(run, out)
    return out


def offline_round(run, progress: bool) -> None:
    """One offline round: (a forward filter pass, then) ``offline.svi_steps`` SVI steps."""
    st, L = run.state, run.cfg.training.chunk_length
    if st.phase == Phase.FILTER:
        if run.cfg.offline.estimate == "forward":  # "cache": only the SVI chunks refresh it
            filter_pass(run, progress, f"filter pass {st.round + 1}")
        st.phase, st.t = Phase.SVI, 0
    n = run.cfg.offline.svi_steps
    bar = tqdm(total=n, initial=st.t, desc=f"offline SVI {st.round + 1}", disable=not progress)
    while st.t < n:
        st.losses.append(svi_step(run, 0, run.T - L, None))
        st.t += 1
        bar.update(1)
        _checkpoint(run)
    bar.close()
    st.round += 1
    st.phase, st.t = Phase.FILTER, 0
    _checkpoint(run, every=False)


def offline(run, progress: bool) -> None:
    """Offline SLAM from where the state stands: the online sweep, the rounds, the final
    poses."""
    st = run.state
    if st.phase == Phase.SWEEP:
        online_sweep(run, progress)
        st.phase, st.t = Phase.SVI, 0
        _checkpoint(run, every=False)
    while st.round < run.cfg.offline.rounds:
        offline_round(run, progress)
    final = cache_pass if run.cfg.offline.estimate == "cache" else filter_pass
    st.estimates, st.stds, st.anchors = final(run, progress, "final filter pass")


def estimates(run) -> dict:
    """The run's pose estimates (see :meth:`~pyro_slam.slam.runner.SLAM.result`): the filtered
    means and world-frame stds ``[T, 3]``, smoothed over the particles' history once the run is
    done (with the placement variance of :func:`world_std` added), the SVI losses and the
    offline sweep's means."""
    st = run.state
    filtered = np.asarray(st.estimates, dtype=np.float64).reshape(-1, 3)
    filtered_std = np.asarray(st.stds, dtype=np.float64).reshape(-1, 3)
    mean, std = filtered, filtered_std
    if st.phase == Phase.DONE and run.history.filled.any():
        lag = run.T if st.mode == "offline" else run.cfg.filter.lag
        m, sd = run.history.smoothed(lag)
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
