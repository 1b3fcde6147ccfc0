"""SLAM with DVBF-LM: the configuration (:mod:`.config`) and its named presets (:mod:`.presets`),
the model built for a traversal (:mod:`.build`), scan insertion (:mod:`.insertion`), the
Manhattan heading observation (:mod:`.heading`), the SLAM run (:mod:`.runner`) and fitting
with known poses (:mod:`.training`)."""

from . import presets
from .build import build_model, image_traversal, path_integration, prepare_traversal
from .config import (
    ConfigError,
    EmissionConfig,
    FilterConfig,
    HeadingConfig,
    OfflineConfig,
    ScanInsertionConfig,
    SLAMConfig,
    TrainingConfig,
    TransitionConfig,
    from_dict,
    with_overrides,
)
from .loop import Phase, SLAMState
from .runner import SLAM
from .training import fit_map, pretrain_emission

__all__ = [
    "SLAM",
    "ConfigError",
    "EmissionConfig",
    "FilterConfig",
    "HeadingConfig",
    "OfflineConfig",
    "Phase",
    "SLAMConfig",
    "SLAMState",
    "ScanInsertionConfig",
    "TrainingConfig",
    "TransitionConfig",
    "build_model",
    "fit_map",
    "from_dict",
    "image_traversal",
    "path_integration",
    "presets",
    "prepare_traversal",
    "pretrain_emission",
    "with_overrides",
]
