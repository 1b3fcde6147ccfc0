"""What changes while a SLAM run runs (:class:`SLAMState`), as Pyro's ``SMCState`` holds the
particles and log-weights of an ``SMCFilter``: where the run is, its outputs so far, the pose
particles, the particle cache and history, and the random stream."""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from enum import StrEnum

import torch

from ..inference import ParticleCache, ParticleHistory, Particles

# the state's plain fields, as a checkpoint stores them
COUNTERS = (
    "mode",
    "phase",
    "t",
    "round",
    "estimates",
    "stds",
    "losses",
    "anchors",
    "sweep_estimates",
    "wall_time_s",
)


class Phase(StrEnum):
    """Where a run is: the online sweep of an online run (``ONLINE``) or of offline SLAM
    (``SWEEP``), an offline round's SVI steps (``SVI``) or its filter pass (``FILTER``), or
    finished (``DONE``). Its value is what checkpoints store."""

    ONLINE = "online"
    SWEEP = "online-init"
    SVI = "offline-svi"
    FILTER = "offline-filter"
    DONE = "done"


@dataclass(eq=False)
class SLAMState:
    """Everything of a SLAM run that changes as it runs, which a checkpoint writes and a resume
    reads back (:meth:`state_dict`); the run's fixed parts are its
    :class:`~pyro_slam.slam.parts.Components`.

    Args:
        gen: the run's random stream: every draw of the filter, the particle cache and the SVI
            chunks comes from it (the filters and the objective hold this generator).
        cache: the particle cache ``[T, N, 3]`` the objective starts its chunks from (the
            objective holds this cache; the filter refreshes it).
        history: each step's particles, weights and ancestors, for smoothing.
        mode: ``"online"`` or ``"offline"``; None until the run starts (:meth:`begin`).
        phase: where the run is (:class:`Phase`).
        t: the next time step (online, the sweep) or the next SVI step (an offline round).
        round: offline rounds done.
        estimates, stds: per step the cloud's mean and world-frame std ``[3]`` (lists).
        losses: the SVI losses.
        anchors: per step the placement variance of the map the pose is localised against.
        sweep_estimates: offline SLAM's initial sweep: its pose means per step ``[3]``.
        wall_time_s: the run's wall time so far, summed over resumes.
        particles: the last step's particle cloud ``z [K, 3]`` (None before the first step).
    """

    gen: torch.Generator
    cache: ParticleCache
    history: ParticleHistory
    mode: str | None = None
    phase: Phase = Phase.ONLINE
    t: int = 0
    round: int = 0
    estimates: list = field(default_factory=list)  # per step [3]
    stds: list = field(default_factory=list)  # per step [3]
    losses: list = field(default_factory=list)
    anchors: list = field(default_factory=list)
    sweep_estimates: list = field(default_factory=list)  # per step [3]
    wall_time_s: float = 0.0
    particles: Particles | None = None

    def __post_init__(self):
        self.phase = Phase(self.phase)

    @classmethod
    def new(cls, seed: int, num_steps: int, cached: int, particles: int) -> SLAMState:
        """A run's state before its first step: the generator seeded with ``seed``, an empty
        cache of ``cached`` particles and history of ``particles`` per step, over ``num_steps``
        steps."""
        gen = torch.Generator().manual_seed(seed)
        return cls(gen, ParticleCache(num_steps, cached), ParticleHistory(num_steps, particles))

    def begin(self, mode: str) -> None:
        """Start a run in ``mode``: the online sweep's phase of an online or offline run."""
        self.mode, self.phase = mode, Phase.ONLINE if mode == "online" else Phase.SWEEP

    def state_dict(self) -> dict:
        """Tensors and plain data: the counters and outputs, the particles, the cache, the
        history, the generator's state and torch's global random state (Pyro's draws)."""
        p = self.particles
        counters = copy.deepcopy({k: getattr(self, k) for k in COUNTERS})
        return {
            **counters,
            "phase": self.phase.value,
            "particles": None if p is None else {"z": p.z, "logw": p.logw, "scan": p.scan},
            "cache": self.cache.state_dict(),
            "history": self.history.state_dict(),
            "gen": self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
        }

    def load_state_dict(self, d: dict) -> None:
        """Restore :meth:`state_dict` (the cache, history and generator in place)."""
        self.cache.load_state_dict(d["cache"])
        self.particles = None if d["particles"] is None else Particles(**d["particles"])
        self.gen.set_state(d["gen"])
        torch.set_rng_state(d["torch_rng"])
        self.history.load_state_dict(d["history"])
        for k in COUNTERS:
            setattr(self, k, copy.deepcopy(d[k]))
        self.phase = Phase(self.phase)
