"""Emission kinds: what SLAM needs to know of an emission, on the emission's own registration.

An :class:`EmissionKind` says how to build a new emission for a traversal and carries the facts
the rest of the library reads (which observation it explains, the map's features per cell, whether
it reads the map along rays, whether SVI learns a new one, and a pretrained one where there is
one), as Pyro's ``DynamicModel`` carries its dimension. The configuration names a kind
(``emission.kind``); no other module switches on the name. Adding an emission is one call of
:func:`register_emission`::

    register_emission(EmissionKind("my-lidar", make=lambda tr, cfg, reach: MyEmission(...)))
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from ..data import Traversal
from ..model import (
    Emission,
    EmissionMLP,
    EndPointEmission,
    ImageEmission,
    RayEmission,
    RayImageEmission,
)
from ..model.networks import (
    IMAGE_BINS,
    IMAGE_HIDDEN,
    IMAGE_LAYERS,
    LIDAR_MAP_DIM,
    MIN_WORLD_DIRECTIONS,
)
from ..pretrained import load_emission, shipped_emission
from .insertion import wall_ramp
from .kinds import EMISSIONS

RAY_SAMPLES = 48  # points per ray of the ray-cast emissions (their constructors' default)
# the occupancy's density per grid spacing of the ray-cast emissions (their constructors' 100
# per unit length on the mazes' 1/63 grid)
DENSITY_PER_SPACING = 100 / 63
# half the width of the walls' ramp that the end-point emission reads its distance from (grid
# spacings): twice the ray march's, so that a reading within 3 spacings of its wall is scored
# by its distance (the field is flat beyond)
ENDPOINT_RAMP = 3.0


@dataclass(frozen=True)
class EmissionKind:
    """An emission kind (module doc).

    Args:
        name: the ``emission.kind`` that names it.
        make: ``(prepared traversal, config, reach) -> emission``, a new (untrained) one;
            ``reach`` is the sensor's range after the configuration's clip.
        observation: ``"lidar"`` (ranges) or ``"image"`` (camera frames, flattened).
        map_dim: the map's features per cell, or a function of the prepared traversal.
        rays: it reads the map along rays (``emission.ray_spacing``, scan insertion, memory
            per ray point).
        insertion: the scan insertion kind it needs (None: any, or none).
        learned: SVI learns a new one (False: it has nothing to learn).
        shipped: ``traversal -> emission or None``, a pretrained one where there is one (it is
            then frozen).
        load: ``(path, traversal) -> emission``, a pretrained one from a network file (None:
            the kind has no network files).
    """

    name: str
    make: Callable[[Traversal, object, float], Emission | EmissionMLP]
    observation: str = "lidar"
    map_dim: int | Callable[[Traversal], int] = 1
    rays: bool = False
    insertion: str | None = None
    learned: bool = True
    shipped: Callable[[Traversal], Emission | EmissionMLP | None] | None = None
    load: Callable[[object, Traversal], Emission | EmissionMLP] | None = None

    def features(self, traversal: Traversal) -> int:
        """The map's features per cell for a prepared traversal."""
        return self.map_dim(traversal) if callable(self.map_dim) else int(self.map_dim)


def register_emission(kind: EmissionKind) -> EmissionKind:
    """Make ``kind`` available as ``emission.kind = kind.name`` (replacing one of that name) in
    the registry :data:`~pyro_slam.slam.kinds.EMISSIONS`."""
    if kind.observation not in ("lidar", "image"):
        raise ValueError(f"observation must be 'lidar' or 'image', got {kind.observation!r}")
    EMISSIONS[kind.name] = kind
    return kind


def emission_kind(name: str) -> EmissionKind:
    """The registered kind ``name``; ``KeyError`` naming the registered ones otherwise."""
    try:
        return EMISSIONS[name]
    except KeyError:
        raise KeyError(f"unknown emission kind {name!r}; registered: {list(EMISSIONS)}") from None


def ray_settings(config, reach: float) -> dict:
    """The ray-cast emissions' ``samples`` and ``density`` for a configuration (see
    :class:`~pyro_slam.slam.config.EmissionConfig`'s ``ray_spacing``); empty: their defaults."""
    e = config.emission
    out = {"tolerance": e.march_tolerance} if e.march_tolerance else {}
    if e.ray_spacing is None:
        return out
    samples = max(2, math.ceil(reach / (e.ray_spacing * e.resolution)))
    return out | {"samples": samples, "density": DENSITY_PER_SPACING / e.resolution}


def _image_shape(traversal: Traversal) -> tuple[int, int]:
    rows, cols = traversal.metadata["image_shape"]
    return rows, cols


def _lidar_mlp(traversal, config, reach):
    n_world = max(traversal.num_beams, MIN_WORLD_DIRECTIONS)
    return EmissionMLP(LIDAR_MAP_DIM, n_world, scale=reach)


def _raycast(traversal, config, reach):
    return RayEmission(traversal.beam_angles, reach, **ray_settings(config, reach))


def _endpoint(traversal, config, reach):
    em = EndPointEmission(traversal.beam_angles, reach, **ray_settings(config, reach))
    insert, spacing = config.emission.insert, config.emission.resolution
    em.ramp = wall_ramp(insert, em, spacing, half_width=ENDPOINT_RAMP)
    return em


def _image_mlp(traversal, config, reach):
    rows, cols = _image_shape(traversal)
    angles = traversal.beam_angles[:cols]
    return ImageEmission(
        IMAGE_BINS, rows, cols, hidden=IMAGE_HIDDEN, layers=IMAGE_LAYERS, column_angles=angles
    )


def _ray_camera(traversal, config, reach):
    rows, cols = _image_shape(traversal)
    angles = traversal.beam_angles[:cols]
    return RayImageEmission(angles, rows, reach, **ray_settings(config, reach))


register_emission(
    EmissionKind(
        "mlp", _lidar_mlp, map_dim=LIDAR_MAP_DIM, shipped=shipped_emission, load=load_emission
    )
)
register_emission(EmissionKind("raycast", _raycast, rays=True, learned=False))
register_emission(EmissionKind("endpoint", _endpoint, rays=True, insertion="fusion", learned=False))
register_emission(
    EmissionKind(
        "image_mlp",
        _image_mlp,
        observation="image",
        map_dim=lambda tr: IMAGE_BINS * _image_shape(tr)[0],
    )
)
register_emission(
    EmissionKind("ray_camera", _ray_camera, observation="image", map_dim=9, rays=True)
)
