"""The SLAM configuration, made of component choices.

A :class:`SLAMConfig` holds one object per component: the emission (and with it the map grid
and, for the ray-cast LiDAR, scan insertion), the transition, the pose filter, the SVI schedule
of the training objective, the offline passes and the optional heading factor. Each component
validates itself on construction, so an impossible combination cannot be written down.

Every default is written once, here: a component's field defaults are the default preset's
values, and ``SLAMConfig()`` *is* the default preset (its scan insertion and heading factor,
which not every component choice allows, are added by ``SLAMConfig``'s own defaults). The other
named configurations (:mod:`pyro_slam.slam.presets`) state how they differ from it;
:func:`with_overrides` applies a nested dict of changes (the CLI's ``--config`` JSON).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import typing
from dataclasses import dataclass, field, fields
from pathlib import Path

from .kinds import EMISSIONS

TRANSITIONS = ("kinematic", "learned")
PROPOSALS = ("transition", "scan-match")
ESTIMATES = ("forward", "cache")
INSERTION_KINDS = ("occupancy", "fusion")
# the named map priors and emission noises (built by :mod:`pyro_slam.slam.build`)
MAP_PRIORS = ("normal", "wide", "student-t")
NOISES = ("normal", "student-t")


class ConfigError(ValueError):
    """A configuration value is out of range or of the wrong type; the message names it."""


def _finite(value, integer: bool) -> bool:
    """Whether ``value`` is a finite number (an ``int`` if ``integer``; never a bool)."""
    types = int if integer else (int, float)
    return isinstance(value, types) and not isinstance(value, bool) and math.isfinite(value)


def _positive(name: str, value, integer: bool = False, optional: bool = False) -> None:
    if value is None and optional:
        return
    kind = "a positive integer" if integer else "a positive number"
    if not _finite(value, integer) or value <= 0:
        raise ConfigError(f"{name} must be {kind}, got {value!r}")


def _non_negative(name: str, value, integer: bool = False) -> None:
    kind = "an integer >= 0" if integer else "a number >= 0"
    if not _finite(value, integer) or value < 0:
        raise ConfigError(f"{name} must be {kind}, got {value!r}")


def _probability(name: str, p) -> None:
    if not (isinstance(p, (int, float)) and not isinstance(p, bool) and 0 <= p < 1):
        raise ConfigError(f"{name} must be in [0, 1), got {p!r}")


def _choice(name: str, value, choices) -> None:
    if value not in choices:
        raise ConfigError(f"{name} must be one of {list(choices)}, got {value!r}")


def _triple(name: str, value, optional: bool = False, positive: bool = True) -> None:
    if value is None and optional:
        return
    ok = isinstance(value, (tuple, list)) and len(value) == 3
    ok = ok and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    ok = ok and all(math.isfinite(v) and (v > 0 if positive else v >= 0) for v in value)
    if not ok:
        raise ConfigError(f"{name} must be 3 positive numbers (x, y, heading), got {value!r}")


@dataclass(frozen=True)
class ScanInsertionConfig:
    """Scan insertion (ray-cast LiDAR only), the guide's update of ``q(M)`` with each online
    scan placed from the cloud's mean pose (:mod:`pyro_slam.slam.insertion`); SVI then refines
    the map. Its inverse sensor model: a wall's grid point reads the wall level ``occupancy``,
    a grid point a beam passed the free level ``-occupancy / 2``, each with Gaussian noise of
    std ``noise``; a Gaussian update of the model's map prior with those readings. ``kind``
    ``"occupancy"``: the hits, joined into a polyline (neighbouring hits closer than ``gap``
    form one wall), are read once per grid point (walls without thickness, as in the simulated
    mazes); ``"fusion"``: a truncated signed distance fused over the scans gives the reading on
    a ramp from free to ``occupancy`` across each wall, with the precision of the scans fused
    (real walls, with a back side no beam sees)."""

    kind: str = "occupancy"
    # a wall's reading and its noise: under the default prior N(0, 1) a first reading puts the
    # belief at the emission's wall level 2.0 with std 0.3 (mean y / (1 + noise^2), std
    # noise / sqrt(1 + noise^2)), where the ray-cast emission stops a ray within a grid spacing
    occupancy: float = 2.2
    noise: float = 0.315
    gap: float = 0.05

    def __post_init__(self):
        _choice("emission.insert.kind", self.kind, INSERTION_KINDS)
        _positive("emission.insert.occupancy", self.occupancy)
        _positive("emission.insert.noise", self.noise)
        _positive("emission.insert.gap", self.gap)


@dataclass(frozen=True)
class EmissionConfig:
    """The emission ``p(x_t | m_t)`` and the map grid it reads.

    ``kind``: ``"mlp"`` (the paper's LiDAR chart + ``mu_E`` MLP), ``"raycast"`` (LiDAR ranges
    volume-rendered through an occupancy map, each beam's uncertainty read where it stops),
    ``"endpoint"`` (the likelihood field: each reading's end point scored by the distance that
    the fused occupancy map says there; ``"fusion"`` insertion only),
    ``"image_mlp"`` (the paper's visual row MLPs) or ``"ray_camera"`` (a pinhole camera through
    an occupancy and albedo map). ``resolution``: grid spacing (world units); ``margin``: the
    grid's margin around the walls; ``sigma``: the model's ``sigma_E``; ``outlier_prob``: the
    model's beam-mixture outlier probability (uniform over the sensor's range); ``insert``:
    scan insertion (``"raycast"``); ``ray_spacing``: the ray-cast emissions' points along a
    ray, in grid spacings (None: 48 points over the range), with the occupancy's density per
    unit length scaled to the grid (the same per grid spacing at every resolution);
    ``march_tolerance``: the transmittance below which the filter's march stops a beam (0: the
    full range; :class:`~pyro_slam.model.emissions.RayEmission`'s ``tolerance``).
    ``prior``: the map prior ``p(M)`` per cell, ``"normal"`` (``N(0, 1)``), ``"wide"``
    (``N(0, 2^2)``) or ``"student-t"`` (Student-t, 4 degrees of freedom, scale 1);
    ``noise``: the emission noise about the predicted reading, ``"normal"`` or
    ``"student-t"`` (3 degrees of freedom), both with std (scale) ``sigma``
    (:func:`pyro_slam.slam.build.map_prior`, :func:`pyro_slam.slam.build.emission_noise`).
    """

    kind: str = "raycast"
    resolution: float = 1 / 63
    margin: float = 0.05
    sigma: float = 0.05
    outlier_prob: float = 0.1
    insert: ScanInsertionConfig | None = None
    ray_spacing: float | None = None
    march_tolerance: float = 0.0
    prior: str = "normal"
    noise: str = "normal"

    def __post_init__(self):
        _choice("emission.kind", self.kind, EMISSIONS)
        _choice("emission.prior", self.prior, MAP_PRIORS)
        _choice("emission.noise", self.noise, NOISES)
        kind = EMISSIONS[self.kind]
        _positive("emission.resolution", self.resolution)
        _non_negative("emission.margin", self.margin)
        _positive("emission.sigma", self.sigma)
        _probability("emission.outlier_prob", self.outlier_prob)
        _positive("emission.ray_spacing", self.ray_spacing, optional=True)
        _probability("emission.march_tolerance", self.march_tolerance)
        if self.insert is not None and not (kind.rays and kind.observation == "lidar"):
            raise ConfigError(
                "emission.insert writes LiDAR hits into an occupancy map: it needs a ray-cast "
                f"LiDAR emission.kind such as 'raycast', got {self.kind!r}"
            )
        need = getattr(kind, "insertion", None)
        if need is not None and (self.insert is None or self.insert.kind != need):
            raise ConfigError(
                f"emission.kind {self.kind!r} reads the map that {need!r} scan insertion "
                f"writes: it needs emission.insert.kind = {need!r}"
            )

    @property
    def observation(self) -> str:
        """``"image"`` for the camera emissions, ``"lidar"`` otherwise."""
        return EMISSIONS[self.kind].observation


@dataclass(frozen=True)
class TransitionConfig:
    """The transition ``p(z_{t+1} | z_t, u_t)``: ``kind`` ``"kinematic"`` (the control model's
    kinematics with std ``sigma``) or ``"learned"`` (the shipped ``mu_T`` network and its own
    ``sigma_T``). The model's ``sigma_T`` is that std times ``scale``."""

    kind: str = "learned"
    sigma: tuple[float, float, float] = (5e-4, 5e-4, 8e-3)
    scale: tuple[float, float, float] = (3.0, 3.0, 1.0)

    def __post_init__(self):
        _choice("transition.kind", self.kind, TRANSITIONS)
        _triple("transition.sigma", self.sigma)
        _triple("transition.scale", self.scale)
        for f in ("sigma", "scale"):  # JSON gives lists: keep tuples
            object.__setattr__(self, f, tuple(float(x) for x in getattr(self, f)))


@dataclass(frozen=True)
class FilterConfig:
    """The SLAM particle filter: ``particles`` per step and the pose ``proposal``
    (:mod:`pyro_slam.inference.proposals`; with the heading factor, the transition is
    conditioned on it). The weights are the model's likelihood, under the map belief its
    stated marginalisation (:meth:`~pyro_slam.model.DVBFLM.marginal_emission`). The reported
    online poses are smoothed with the weights of the step ``lag`` steps later carried back
    by the transition's backward kernels (:class:`~pyro_slam.inference.ParticleHistory`; 0: the
    filtered means); offline, with those of the final pass's last step."""

    particles: int = 128
    proposal: str = "scan-match"
    lag: int = 20

    def __post_init__(self):
        _positive("filter.particles", self.particles, integer=True)
        _choice("filter.proposal", self.proposal, PROPOSALS)
        _non_negative("filter.lag", self.lag, integer=True)


@dataclass(frozen=True)
class TrainingConfig:
    """SVI on the particle-chunk ELBO of the model (paper eq. 3): ``chunks`` chunks of
    ``chunk_length`` steps with ``particles`` particles each per SVI step, map learning rate
    ``lr`` (Adam; ``lr_emission`` for an emission learned from scratch); the online sweep takes
    one SVI step every ``every`` steps (0: none, the map belief is scan insertion's alone); the
    particle cache keeps ``cache_particles`` per step (paper III-D2)."""

    particles: int = 16
    chunk_length: int = 4
    chunks: int = 4
    lr: float = 0.02
    every: int = 2
    lr_emission: float = 1e-3
    cache_particles: int = 50

    def __post_init__(self):
        for name in ("particles", "chunk_length", "chunks", "cache_particles"):
            _positive(f"training.{name}", getattr(self, name), integer=True)
        _non_negative("training.every", self.every, integer=True)
        _positive("training.lr", self.lr)
        _positive("training.lr_emission", self.lr_emission)


@dataclass(frozen=True)
class OfflineConfig:
    """Offline SLAM after the online sweep: ``rounds`` rounds of ``svi_steps`` SVI steps on
    chunks from anywhere in the traversal; the pose posterior ``estimate`` is ``"forward"`` (a
    filter pass over the whole traversal after each round and at the end) or ``"cache"`` (the
    paper's Appendix B-I: only the SVI chunks refresh the cache, and the final poses are
    filtered in consecutive chunks, each started from the cache)."""

    rounds: int = 2
    svi_steps: int = 800
    estimate: str = "cache"

    def __post_init__(self):
        for name in ("rounds", "svi_steps"):
            _non_negative(f"offline.{name}", getattr(self, name), integer=True)
        _choice("offline.estimate", self.estimate, ESTIMATES)


@dataclass(frozen=True)
class HeadingConfig:
    """The Manhattan-world heading observation (not the paper's model): each scan's straight
    walls give its heading modulo a quarter turn, relative to a walls' frame estimated from the
    data, wherever at least ``support`` wall segments agree; the agreement tolerance and the
    observation's std fit the sensor's noise, with ``sigma`` rad as their floor
    (:mod:`pyro_slam.slam.heading`)."""

    sigma: float = 1e-3
    support: int = 2

    def __post_init__(self):
        _positive("heading.sigma", self.sigma)
        if not (isinstance(self.support, int) and self.support >= 2):
            raise ConfigError(f"heading.support must be an integer >= 2, got {self.support!r}")


@dataclass(frozen=True)
class SLAMConfig:
    """A SLAM configuration: one choice per component, plus how the sensor is read
    (every ``beam_stride``-th beam, readings clipped at ``range_clip``). ``SLAMConfig()`` is
    the default preset: the components' defaults, with scan insertion and the heading
    factor."""

    emission: EmissionConfig = field(
        default_factory=lambda: EmissionConfig(insert=ScanInsertionConfig())
    )
    transition: TransitionConfig = field(default_factory=TransitionConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)
    offline: OfflineConfig = field(default_factory=OfflineConfig)
    heading: HeadingConfig | None = field(default_factory=HeadingConfig)
    beam_stride: int = 1
    range_clip: float | None = None

    def __post_init__(self):
        _check_components(self, "")
        _positive("beam_stride", self.beam_stride, integer=True)
        _positive("range_clip", self.range_clip, optional=True)

    def to_dict(self) -> dict:
        """Plain nested dict (JSON-ready; tuples as lists)."""
        return _plain(dataclasses.asdict(self))


@functools.cache
def component_fields(cls) -> dict[str, tuple[type, bool]]:
    """The fields of the configuration dataclass ``cls`` that hold a configuration dataclass:
    field name -> (that class, whether None is allowed), read from the annotations (e.g.
    ``heading: HeadingConfig | None``)."""
    hints = typing.get_type_hints(cls)
    out = {}
    for f in fields(cls):
        kinds = typing.get_args(hints[f.name]) or (hints[f.name],)
        for kind in kinds:
            if dataclasses.is_dataclass(kind):
                out[f.name] = (kind, type(None) in kinds)
    return out


def _check_components(config, where: str) -> None:
    """Each component field of ``config`` holds its configuration class (or an allowed None);
    :class:`ConfigError` naming the field (``where`` + name) otherwise."""
    for name, (cls, optional) in component_fields(type(config)).items():
        value = getattr(config, name)
        if not isinstance(value, cls) and not (value is None and optional):
            raise ConfigError(f"{where}{name} must be a {cls.__name__}, got {value!r}")


COMPONENTS = {name: cls for name, (cls, _) in component_fields(SLAMConfig).items()}


def _plain(v):
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def _merge(obj, changes: dict, cls, where: str):
    """``obj`` (an instance of the frozen configuration dataclass ``cls``, or None for its
    defaults) with the nested ``changes`` applied: a dict given for a component field
    (:func:`component_fields`) changes that component. Fields are named ``where`` + their dotted
    path in errors."""
    if not isinstance(changes, dict):
        shown = where.rstrip(".") or "the configuration"
        raise ConfigError(f"{shown} must be a JSON object, got {changes!r}")
    names = {f.name for f in fields(cls)}
    if unknown := sorted(set(changes) - names):
        raise ConfigError(
            f"unknown field{'s' if len(unknown) > 1 else ''} "
            f"{', '.join(where + u for u in unknown)}"
            f"; {cls.__name__} has {', '.join(sorted(names))}"
        )
    base = cls() if obj is None else obj
    kw = {}
    for k, v in changes.items():
        if k in component_fields(cls) and isinstance(v, dict):
            v = _merge(getattr(base, k), v, component_fields(cls)[k][0], f"{where}{k}.")
        kw[k] = v
    try:
        return dataclasses.replace(base, **kw)
    except TypeError as e:
        raise ConfigError(f"{where.rstrip('.') or 'configuration'}: {e}") from e


def with_overrides(config: SLAMConfig, changes: dict) -> SLAMConfig:
    """``config`` with a nested dict of changes, e.g. ``{"filter": {"particles": 512}}`` or
    ``{"heading": {"sigma": 0.002}}`` (a component that is None starts from its defaults;
    ``{"heading": None}`` switches it off). Unknown fields and bad values raise
    :class:`ConfigError` naming the field."""
    return _merge(config, changes, SLAMConfig, "")


def parse_overrides(text: str) -> dict:
    """Nested configuration changes from a JSON object's text, or from the JSON file at the path
    ``text``; :class:`ConfigError` naming the problem otherwise."""
    if text.lstrip()[:1] not in ("{", "["):  # a file of JSON
        try:
            text = Path(text).read_text()
        except (OSError, UnicodeDecodeError) as e:
            shown = f"{text[:60]!r}"
            raise ConfigError(f"{shown}: not a JSON object, nor a readable file ({e})") from None
    try:
        changes = json.loads(text)
    except json.JSONDecodeError as e:
        raise ConfigError(f"not JSON ({e})") from None
    except RecursionError:
        raise ConfigError("nested too deeply (no configuration field is)") from None
    if not isinstance(changes, dict):
        raise ConfigError(f"the configuration must be a JSON object, got {changes!r}")
    return changes


def from_dict(d: dict) -> SLAMConfig:
    """The configuration written by :meth:`SLAMConfig.to_dict`."""
    return with_overrides(SLAMConfig(), d)


def _given_fields(changes: dict, where: str = "") -> list[str]:
    """The dotted field names a nested dict of changes sets (``emission.insert.gap``)."""
    names = []
    for key, value in changes.items():
        name = f"{where}{key}"
        names += _given_fields(value, f"{name}.") if isinstance(value, dict) else [name]
    return names


def _ignored(config: SLAMConfig, mode: str, learns_emission: bool | None) -> dict[str, str]:
    """What would ignore each field (dotted name, or a component's prefix ending in ``.``) in
    a run of ``config`` in ``mode``: the field's component and why; only the ignored ones."""
    e, t, o = config.emission, config.training, config.offline
    offline_svi = mode == "offline" and o.rounds > 0 and o.svi_steps > 0
    svi = t.every > 0 or offline_svi
    reads_rays = EMISSIONS[e.kind].rays if e.kind in EMISSIONS else True
    ignored = {}
    if mode == "online":
        ignored["offline."] = "offline SLAM's passes, and --mode online makes none"
    else:
        ignored["filter.lag"] = (
            "the online smoother's lag, and --mode offline smooths over the whole traversal"
        )
    if not reads_rays:
        for name in ("emission.ray_spacing", "emission.march_tolerance"):
            ignored[name] = (
                f"a ray-cast emission's march, and emission.kind {e.kind!r} casts no rays"
            )
    if not svi:
        why = "training.every 0" + ("" if mode == "online" else " and no offline SVI steps")
        ignored["training."] = f"the SVI steps, and this run takes none ({why})"
    elif learns_emission is False:
        ignored["training.lr_emission"] = (
            "the learning rate of an emission SVI learns, and this run's emission (kind "
            f"{e.kind!r}, pretrained or with nothing to learn) is frozen"
        )
    if config.transition.kind == "learned":
        ignored["transition.sigma"] = (
            "the kinematic transition's std, and transition.kind 'learned' uses its network's "
            "own (scale it with transition.scale)"
        )
    return ignored


def check_used(
    changes: dict, config: SLAMConfig, mode: str, learns_emission: bool | None = None
) -> None:
    """Refuse a field of the overrides ``changes`` (what :func:`with_overrides` took to make
    ``config``) that nothing in a run in ``mode`` (``"online"`` or ``"offline"``) would read:
    :class:`ConfigError` naming the field and the component that ignores it.
    ``learns_emission``: whether the run's SVI learns its emission (None: not known yet, so
    ``training.lr_emission`` is not checked)."""
    ignored = _ignored(config, mode, learns_emission)
    for name in _given_fields(changes):
        for key, why in ignored.items():
            if name == key or (key.endswith(".") and name.startswith(key)):
                if name == "training.every":
                    continue
                raise ConfigError(f"{name} configures {why}: it would be ignored")
