"""Putting a SLAM run together: from its data and configuration to its
:class:`~pyro_slam.slam.parts.Components`: the model, the guides, the pose filter, the training
objective with SVI, scan insertion and the heading factor's data."""

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
    ParticleChunkELBO,
    ParticleFilter,
    PyroSMCFilter,
)
from ..model import DVBFLM, GlobalGuide
from ..model.guide import MapLeaves, ParamScope
from ..runtime import warm_optimizers
from .build import build_model
from .components import emission_kind
from .heading import ManhattanHeading
from .insertion import ScanInserter, make_inserter
from .parts import Components, RunData
from .state import SLAMState


def assemble(
    data: RunData,
    state: SLAMState,
    scope: ParamScope,
    transition,
    emission,
    learn_emission,
    guide,
    prior,
    noise,
    smc: bool,
    handler=None,
) -> Components:
    """The run's components, inside its parameter ``scope`` (see
    :class:`~pyro_slam.slam.runner.SLAM` for the other arguments): the filters and the
    objective draw from ``state.gen``, and the objective starts its chunks from
    ``state.cache``. Seeds Pyro with ``data.seed`` once the given networks are loaded."""
    cfg = data.cfg
    if transition is None and cfg.transition.kind == "learned":
        transition = pretrained.transition_for(data.tr)
    kind = emission_kind(cfg.emission.kind)
    if emission is None and kind.shipped is not None:
        emission = kind.shipped(data.tr)
    if learn_emission is None:
        learn_emission = emission is None and kind.learned
    pyro.set_rng_seed(data.seed)  # (after loading: building a network draws its weights)
    heading = heading_data(data)
    model, map_guide = build_model(
        data.tr,
        cfg,
        transition,
        emission,
        prior,
        noise,
        heading=None if heading is None else heading.factor(),
        learn_emission=bool(learn_emission),
        handler=handler,
    )
    if guide is not None:
        map_guide = guide(model)
    if heading is not None:
        heading.estimate_frame(data.tr, float(model.transition.sigma[2]))
    global_guide = GlobalGuide(map_guide, None if heading is None else heading.frame)
    name = cfg.filter.proposal
    proposal = HeadingProposal() if heading and name == "transition" else PROPOSALS[name]()
    pf = ParticleFilter(model, proposal, state.gen)
    if smc:
        pf = PyroSMCFilter(model, proposal)
    elbo = ParticleChunkELBO(
        ParticleFilter(model, proposal, state.gen),
        state.cache,
        data.obs,
        data.ctl,
        data.mask,
        num_particles=cfg.training.particles,
        headings=None if heading is None else heading.evidence(),
        init_pose=data.init_pose,
    )
    lr, lr_emission = cfg.training.lr, cfg.training.lr_emission
    optim = Adam(lambda name, _p: {"lr": lr_emission if name.startswith("emission") else lr})
    svi = SVI(handled_model(model), global_guide, optim, loss=elbo)
    warm_optimizers()
    create_guide_params(map_guide, elbo.model_args)
    insert = None if cfg.emission.insert is None else inserter(cfg, model, map_guide)
    return Components(
        scope, model, map_guide, global_guide, heading, proposal, pf, elbo, optim, svi, insert
    )


def heading_data(data: RunData) -> ManhattanHeading | None:
    """The wall directions of the run's scans (with the configured heading factor; None
    without); the walls' frame guide is estimated once the model's transition is known."""
    cfg = data.cfg
    if cfg.heading is None:
        return None
    image = cfg.emission.observation == "image"
    return ManhattanHeading(
        data.tr, data.obs, data.mask, cfg.heading, image, cfg.emission.outlier_prob
    )


def inserter(cfg, model: DVBFLM, map_guide) -> ScanInserter | None:
    """Scan insertion into the map guide, where the guide's marginal mean and std can be read
    and written (:class:`~pyro_slam.model.guide.MapLeaves`); otherwise insertion is switched
    off with a warning."""
    leaves = MapLeaves.of(map_guide, model.grid.shape)
    if leaves is None:
        warnings.warn(
            f"scan insertion is off: the map guide {type(map_guide).__name__} keeps no "
            "marginal mean and std to update with scans (MapLeaves)",
            stacklevel=4,
        )
        return None
    return make_inserter(cfg.emission.insert, model, leaves)


def create_guide_params(map_guide, args=()) -> None:
    """Create a map guide's parameters now (checkpoints need them): a
    :class:`~pyro_slam.model.MapGuide` through ``params()``; another guide by one draw with
    the model's arguments ``args`` (outside any inference)."""
    if hasattr(map_guide, "params"):
        map_guide.params()
        return
    with torch.no_grad(), poutine.block():
        map_guide(*args)


def handled_model(model: DVBFLM):
    """``model.model`` under the model's handlers as they stand at each call
    (:meth:`~pyro_slam.model.DVBFLM.handled`): the model SLAM's SVI steps on."""

    def run(*args, **kwargs):
        return model.handled()(*args, **kwargs)

    return run
