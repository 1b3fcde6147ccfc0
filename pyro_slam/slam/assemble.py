"""Putting a SLAM run together: from its configuration and data to the model, the guides, the
pose filter, the particle cache and history, the training objective with SVI, scan insertion
and the heading factor's data, set on the run (:class:`~pyro_slam.slam.runner.SLAM`)."""

from __future__ import annotations

import warnings

import pyro
import torch
from pyro import poutine
from pyro.infer import SVI
from pyro.optim import Adam

from .. import pretrained
from ..inference import (
    PROPOSALS,
    HeadingProposal,
    ParticleCache,
    ParticleChunkELBO,
    ParticleFilter,
    ParticleHistory,
    PyroSMCFilter,
)
from ..model import GlobalGuide
from ..model.guide import MapLeaves
from .build import build_model
from .components import emission_kind
from .heading import ManhattanHeading
from .insertion import ScanInserter, make_inserter


def assemble(run, transition, emission, learn_emission, guide, prior, noise, smc: bool):
    """Set the run's ``gen``, ``model``, ``map_guide``, ``heading``, ``guide``, ``proposal``,
    ``pf``, ``cache``, ``history``, ``elbo``, ``optim``, ``svi`` and ``inserter`` (inside the
    run's parameter scope; see :class:`~pyro_slam.slam.runner.SLAM` for the arguments)."""
    cfg = run.cfg
    if transition is None and cfg.transition.kind == "learned":
        transition = pretrained.transition_for(run.tr)
    kind = emission_kind(cfg.emission.kind)
    if emission is None and kind.shipped is not None:
        emission = kind.shipped(run.tr)
    if learn_emission is None:
        learn_emission = emission is None and kind.learned
    pyro.set_rng_seed(run.seed)  # (after loading: building a network draws its weights)
    run.gen = torch.Generator().manual_seed(run.seed)
    run.model, run.map_guide = build_model(run.tr, cfg, transition, emission, prior, noise)
    run.model.learn_emission = bool(learn_emission)
    if guide is not None:
        run.map_guide = guide(run.model)
    run.heading = heading_data(run)
    if run.heading is not None:
        run.model.heading = run.heading.factor()
    run.guide = GlobalGuide(run.map_guide, None if run.heading is None else run.heading.frame)
    name = cfg.filter.proposal
    proposal = HeadingProposal() if run.heading and name == "transition" else PROPOSALS[name]()
    run.proposal = proposal
    run.pf = ParticleFilter(run.model, proposal, run.gen)
    if smc:
        run.pf = PyroSMCFilter(run.model, proposal)
    run.cache = ParticleCache(run.T, cfg.training.cache_particles)
    run.history = ParticleHistory(run.T, cfg.filter.particles)
    run.elbo = ParticleChunkELBO(
        ParticleFilter(run.model, proposal, run.gen),
        run.cache,
        run.obs,
        run.ctl,
        run.mask,
        num_particles=cfg.training.particles,
        headings=None if run.heading is None else run.heading.evidence(),
    )
    lr, lr_emission = cfg.training.lr, cfg.training.lr_emission
    run.optim = Adam(lambda name, _p: {"lr": lr_emission if name.startswith("emission") else lr})
    run.svi = SVI(run.model.global_model, run.guide, run.optim, loss=run.elbo)
    create_guide_params(run.map_guide)
    run.inserter = None if cfg.emission.insert is None else inserter(run)


def heading_data(run) -> ManhattanHeading | None:
    """The wall directions of the run's scans and the walls' frame guide (with the configured
    heading factor; None without)."""
    cfg = run.cfg
    if cfg.heading is None:
        return None
    image = cfg.emission.observation == "image"
    drift = float(run.model.transition.sigma[2])
    return ManhattanHeading(
        run.tr, run.obs, run.mask, cfg.heading, image, drift, cfg.emission.outlier_prob
    )


def inserter(run) -> ScanInserter | None:
    """Scan insertion into the run's map guide, where the guide's marginal mean and std can be
    read and written (:class:`~pyro_slam.model.guide.MapLeaves`); otherwise insertion is
    switched off with a warning."""
    leaves = MapLeaves.of(run.map_guide, run.model.grid.shape)
    if leaves is None:
        warnings.warn(
            f"scan insertion is off: the map guide {type(run.map_guide).__name__} keeps no "
            "marginal mean and std to update with scans (MapLeaves)",
            stacklevel=4,
        )
        return None
    return make_inserter(run.cfg.emission.insert, run.model, leaves)


def create_guide_params(map_guide) -> None:
    """Create a map guide's parameters now (checkpoints need them): a
    :class:`~pyro_slam.model.MapGuide` through ``params()``; another guide by one draw
    (outside any inference)."""
    if hasattr(map_guide, "params"):
        map_guide.params()
        return
    with torch.no_grad(), poutine.block():
        map_guide()
