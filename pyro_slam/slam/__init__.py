"""SLAM with DVBF-LM: the configuration (:mod:`.config`) and its named presets (:mod:`.presets`),
the model built for a traversal (:mod:`.build`), scan insertion (:mod:`.insertion`), the
Manhattan heading observation (:mod:`.heading`), the SLAM run (:mod:`.runner`) and fitting
with known poses (:mod:`.training`).

The names below are imported from their modules on first use, so that reading the
configuration (``pyro_slam.slam.config``, plain data) loads neither torch nor the networks."""

from __future__ import annotations

import importlib

# exported name -> the module that defines it (a module's own name: the module)
_EXPORTS = {
    "SLAM": "runner",
    "ConfigError": "config",
    "EmissionConfig": "config",
    "FilterConfig": "config",
    "HeadingConfig": "config",
    "OfflineConfig": "config",
    "Phase": "state",
    "SLAMConfig": "config",
    "SLAMState": "state",
    "ScanInsertionConfig": "config",
    "TrainingConfig": "config",
    "TransitionConfig": "config",
    "build_model": "build",
    "fit_map": "training",
    "fit_noise": "training",
    "from_dict": "config",
    "image_traversal": "build",
    "path_integration": "build",
    "presets": "presets",
    "prepare_traversal": "build",
    "pretrain_emission": "training",
    "with_overrides": "config",
}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    """The exported ``name``, imported from its module on first use (PEP 562)."""
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module = importlib.import_module(f".{_EXPORTS[name]}", __name__)
    value = module if _EXPORTS[name] == name else getattr(module, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
