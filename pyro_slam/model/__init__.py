"""The DVBF-LM generative model: map grid and model (:mod:`.model`), its factors
(:mod:`.factors`), guides (:mod:`.guide`), emissions (:mod:`.emissions`), networks
(:mod:`.networks`) and transitions (:mod:`.transitions`)."""

from .emissions import (
    Emission,
    EndPointEmission,
    ImageEmission,
    LidarEmission,
    RayEmission,
    RayImageEmission,
    WallRamp,
    rotate_scan,
)
from .guide import FrameGuide, GlobalGuide, MapGuide, autoguide, map_marginals
from .model import DVBFLM, FilterModel, HeadingEvidence, MapBelief, MapGrid, WallHeading
from .networks import EmissionMLP, TransitionMLP, mlp
from .noise import BeamMixture, CircularUniform, WrappedMixture
from .transitions import KinematicTransition, LearnedTransition, Transition, pretrain_transition

__all__ = [
    "DVBFLM",
    "BeamMixture",
    "CircularUniform",
    "Emission",
    "EmissionMLP",
    "EndPointEmission",
    "FilterModel",
    "FrameGuide",
    "GlobalGuide",
    "HeadingEvidence",
    "ImageEmission",
    "KinematicTransition",
    "LearnedTransition",
    "LidarEmission",
    "MapBelief",
    "MapGrid",
    "MapGuide",
    "RayEmission",
    "RayImageEmission",
    "Transition",
    "TransitionMLP",
    "WallHeading",
    "WallRamp",
    "WrappedMixture",
    "autoguide",
    "map_marginals",
    "mlp",
    "pretrain_transition",
    "rotate_scan",
]
