"""The emission kinds' names and the facts the configuration checks, as plain data (no torch):
which observation a kind explains and whether it reads the map along rays.

:data:`EMISSIONS` is the registry of emission kinds. It starts with these facts of the kinds
the library ships; :mod:`pyro_slam.slam.components` replaces each by its full
:class:`~pyro_slam.slam.components.EmissionKind` (same ``name``, ``observation`` and ``rays``,
plus how to build one) and adds those registered later
(:func:`~pyro_slam.slam.components.register_emission`)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EmissionTraits:
    """What the configuration knows of an emission kind: its ``name`` (``emission.kind``), the
    ``observation`` it explains (``"lidar"`` ranges or ``"image"`` camera frames) and whether
    it reads the map along ``rays`` (scan insertion needs a ray-cast LiDAR); ``insertion``:
    the scan insertion kind it needs (None: any, or none)."""

    name: str
    observation: str = "lidar"
    rays: bool = False
    insertion: str | None = None


BUILTIN = (
    EmissionTraits("mlp"),
    EmissionTraits("raycast", rays=True),
    EmissionTraits("endpoint", rays=True, insertion="fusion"),
    EmissionTraits("image_mlp", "image"),
    EmissionTraits("ray_camera", "image", rays=True),
)
# name -> EmissionTraits, or the EmissionKind registered under that name
EMISSIONS: dict = {t.name: t for t in BUILTIN}
