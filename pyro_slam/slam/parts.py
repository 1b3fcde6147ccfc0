"""The fixed parts of a SLAM run: its data (:class:`RunData`) and its components
(:class:`Components`: the model, the guides, the filter, the objective with SVI, scan insertion
and the heading factor's data). What changes as the run runs is its
:class:`~pyro_slam.slam.state.SLAMState`; the algorithms of :mod:`.loop` take all three."""

from __future__ import annotations

from dataclasses import dataclass

import pyro
import torch
from pyro.infer import SVI
from pyro.optim import PyroOptim

from ..data import Traversal
from ..inference import ParticleChunkELBO, ParticleFilter, Proposal, PyroSMCFilter
from ..model import DVBFLM, GlobalGuide, MapBelief, MapGuide, map_marginals
from ..model.guide import MapLeaves, ParamScope
from .checkpoint import load_param_store, param_store_state
from .config import SLAMConfig
from .heading import ManhattanHeading
from .insertion import ScanInserter


@dataclass(frozen=True, eq=False)
class RunData:
    """What a run filters, as tensors, with its configuration and seed.

    Args:
        tr: the prepared traversal (:func:`~pyro_slam.slam.build.prepare_traversal`).
        cfg: the run's :class:`~pyro_slam.slam.config.SLAMConfig`.
        obs: the observations ``[T, N]``.
        ctl: the controls ``[T-1, D_u]``.
        mask: the valid readings ``[T, N]`` (None: all valid).
        init_pose: the start pose ``[3]``.
        seed: the seed of Pyro and of the run's generator.
    """

    tr: Traversal
    cfg: SLAMConfig
    obs: torch.Tensor  # [T, N]
    ctl: torch.Tensor  # [T-1, D_u]
    mask: torch.Tensor | None  # [T, N]
    init_pose: torch.Tensor  # [3]
    seed: int

    @property
    def T(self) -> int:
        """The number of steps."""
        return self.obs.shape[0]

    def valid(self, t: int) -> torch.Tensor:
        """``[N]`` bool: the valid readings of step ``t``."""
        if self.mask is None:
            return torch.ones_like(self.obs[t], dtype=torch.bool)
        return self.mask[t].bool()


@dataclass(frozen=True, eq=False)
class Components:
    """The parts of a SLAM run that stay the same objects for the whole run (built by
    :func:`~pyro_slam.slam.assemble.assemble`), as an ``SMCFilter`` holds its model and guide.
    Some keep state of their own (the parameters in ``scope``, the optimiser's moments, the
    inserter's sites, the walls' frame guide), which a checkpoint stores through
    :meth:`state_dict`.

    Args:
        scope: the run's own parameter store (``with components.scope():``).
        model: the :class:`~pyro_slam.model.DVBFLM`.
        map_guide: the guide of the site ``"map"``.
        guide: the global guide: the map guide and the walls' frame guide.
        heading: the heading factor's data (None without one).
        proposal: the filter's proposal.
        pf: the pose filter (ours or Pyro's ``SMCFilter``).
        elbo: the training objective (:class:`~pyro_slam.inference.ParticleChunkELBO`).
        optim: the optimiser of SVI.
        svi: SVI on ``model.model`` (under its handlers) and ``guide``.
        inserter: scan insertion into the map guide (None: off).
    """

    scope: ParamScope
    model: DVBFLM
    map_guide: object
    guide: GlobalGuide
    heading: ManhattanHeading | None
    proposal: Proposal
    pf: ParticleFilter | PyroSMCFilter
    elbo: ParticleChunkELBO
    optim: PyroOptim
    svi: SVI
    inserter: ScanInserter | None

    def map_belief(self) -> MapBelief:
        """The map belief the filter weighs with: mean and scale of ``q(M)`` ``[w, h, D_m]``
        (detached; with scan insertion into a :class:`~pyro_slam.model.MapGuide`, kept between
        steps, with the variance, by the guide's leaves,
        :meth:`~pyro_slam.model.guide.MapLeaves.marginals`)."""
        if self.inserter is not None and isinstance(self.map_guide, MapGuide):
            kept = self.inserter.leaves.marginals()
            if kept is not None:
                return MapBelief(*kept)
        with self.scope():
            loc, scale = map_marginals(self.map_guide, self.elbo.model_args)
        return MapBelief(loc.detach(), scale.detach())

    def state_dict(self) -> dict:
        """Each component's own state: tensors and plain data only."""
        with self.scope():
            params = param_store_state()
        return {
            "params": params,
            "optim": self.optim.get_state(),
            "model": self.model.state_dict(),
            "filter": self.pf.state_dict(),
            "elbo_seen": self.elbo.num_steps_seen,
            "inserter": None if self.inserter is None else self.inserter.state_dict(),
            "heading": None if self.heading is None else self.heading.state_dict(),
        }

    def load_state_dict(self, d: dict) -> None:
        """Restore :meth:`state_dict` into the components."""
        with self.scope():
            load_param_store(d["params"])
            self.model.load_state_dict(d["model"])
            if self.model.learn_emission:
                # the store now holds *loaded* tensors: make the emission network use (and SVI
                # update) those, as it did before the checkpoint, not its own parameter copies
                pyro.module("emission", self.model.emission, update_module_params=True)
            self.optim.set_state(d["optim"])
            if self.inserter is not None:  # (the loaded parameters are new tensors)
                self.inserter.leaves = MapLeaves.of(self.map_guide, self.model.grid.shape)
                self.inserter.load_state_dict(d["inserter"])
        self.pf.load_state_dict(d["filter"])
        self.elbo.num_steps_seen = int(d["elbo_seen"])
        if self.heading is not None:
            self.heading.load_state_dict(d["heading"])
