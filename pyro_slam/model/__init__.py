"""The DVBF-LM generative model: map grid and model (:mod:`.model`), guides (:mod:`.guide`),
emissions (:mod:`.emissions`), networks (:mod:`.networks`) and transitions
(:mod:`.transitions`)."""

from .emissions import (
    Emission,
    ImageEmission,
    LidarEmission,
    RayEmission,
    RayImageEmission,
    rotate_scan,
)
from .guide import BootstrapGuide, MapGuide, autoguide, map_marginals
from .model import DVBFLM, FilterModel, MapGrid
from .networks import EmissionMLP, TransitionMLP, mlp
from .transitions import KinematicTransition, LearnedTransition, Transition, pretrain_transition

__all__ = [
    "DVBFLM",
    "BootstrapGuide",
    "Emission",
    "EmissionMLP",
    "FilterModel",
    "ImageEmission",
    "KinematicTransition",
    "LearnedTransition",
    "LidarEmission",
    "MapGrid",
    "MapGuide",
    "RayEmission",
    "RayImageEmission",
    "Transition",
    "TransitionMLP",
    "autoguide",
    "map_marginals",
    "mlp",
    "pretrain_transition",
    "rotate_scan",
]
