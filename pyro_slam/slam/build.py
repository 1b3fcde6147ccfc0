"""From a traversal and a configuration to the model SLAM runs: the traversal as SLAM sees it
(:func:`prepare_traversal`), the :class:`~pyro_slam.model.DVBFLM` and its map guide
(:func:`build_model`), and dead reckoning (:func:`path_integration`)."""

from __future__ import annotations

import copy
import functools
import hashlib
import math
from dataclasses import replace

import numpy as np
import pyro.distributions as dist
import torch

from ..data import DatasetError, Traversal
from ..geometry import wrap_angle
from ..io.common import odometry_poses
from ..model import (
    DVBFLM,
    Emission,
    EmissionMLP,
    KinematicTransition,
    LearnedTransition,
    LidarEmission,
    MapGrid,
    MapGuide,
    Transition,
)
from .components import RAY_SAMPLES, emission_kind, ray_settings
from .config import MAP_PRIORS, NOISES, ConfigError, SLAMConfig

PRIOR_STD_WIDE = 2.0  # the "wide" map prior's std
PRIOR_DF = 4.0  # the "student-t" map prior's degrees of freedom (finite variance, 2)
NOISE_DF = 3.0  # the "student-t" emission noise's degrees of freedom


def map_prior(name: str, dim: int):
    """The named map prior ``p(M)`` per cell (event ``[dim]``; ``emission.prior``): None for
    ``"normal"``, the model's own ``N(0, 1)``; ``"wide"`` ``N(0, 2^2)``; ``"student-t"``
    Student-t with :data:`PRIOR_DF` degrees of freedom, location 0 and scale 1."""
    if name not in MAP_PRIORS:
        raise ConfigError(f"emission.prior must be one of {list(MAP_PRIORS)}, got {name!r}")
    if name == "normal":
        return None
    zeros = torch.zeros(dim)
    if name == "wide":
        return dist.Normal(zeros, torch.full((dim,), PRIOR_STD_WIDE)).to_event(1)
    return dist.StudentT(torch.full((dim,), PRIOR_DF), zeros, torch.ones(dim)).to_event(1)


def emission_noise(name: str):
    """The named emission noise (``emission.noise``), a callable ``(loc, scale) ->
    distribution``: None for ``"normal"``, the model's own Gaussian; ``"student-t"`` Student-t
    with :data:`NOISE_DF` degrees of freedom."""
    if name not in NOISES:
        raise ConfigError(f"emission.noise must be one of {list(NOISES)}, got {name!r}")
    return None if name == "normal" else functools.partial(dist.StudentT, NOISE_DF)


def _describe_value(v) -> str:
    """A tensor (or number) as text: its values rounded to 6 digits, or, beyond 16 entries,
    its shape and a hash of the rounded values."""
    if not torch.is_tensor(v):
        return repr(round(v, 6) if isinstance(v, float) else v)
    t = v.detach().cpu().double().round(decimals=6)
    if t.numel() <= 16:
        return repr(t.tolist())
    digest = hashlib.sha256(t.contiguous().numpy().tobytes()).hexdigest()[:16]
    return f"<{tuple(t.shape)} {digest}>"


def describe_prior(prior) -> str:
    """A map prior as text for a checkpoint's fingerprint: class name and parameters, e.g.
    ``Independent(Normal(loc=[0.0], scale=[2.0]), 1)``; ``"Normal(0, 1)"`` for None (the
    model's default)."""
    if prior is None:
        return "Normal(0, 1)"
    if isinstance(prior, dist.Independent):
        base = describe_prior(prior.base_dist)
        return f"Independent({base}, {prior.reinterpreted_batch_ndims})"
    names = getattr(prior, "arg_constraints", {}) or {}
    params = [
        f"{n}={_describe_value(getattr(prior, n))}" for n in sorted(names) if hasattr(prior, n)
    ]
    return f"{type(prior).__name__}({', '.join(params)})"


def describe_noise(noise) -> str:
    """An emission noise (a callable ``(loc, scale) -> distribution``) as text for a
    checkpoint's fingerprint: ``"Normal"`` for None (the model's default), a partial's function
    and arguments (``StudentT(3.0)``), a class's or function's qualified name otherwise."""
    if noise is None:
        return "Normal"
    if isinstance(noise, functools.partial):
        args = [_describe_value(a) for a in noise.args]
        args += [f"{k}={_describe_value(v)}" for k, v in sorted(noise.keywords.items())]
        return f"{describe_noise(noise.func)}({', '.join(args)})"
    if isinstance(noise, type):
        return noise.__name__
    name = getattr(noise, "__qualname__", None) or type(noise).__qualname__
    return f"{getattr(noise, '__module__', '')}.{name}".lstrip(".")


def prepare_traversal(traversal: Traversal, config: SLAMConfig) -> Traversal:
    """The traversal SLAM sees: every ``config.beam_stride``-th beam, readings clipped at
    ``config.range_clip`` (both no-ops by default); for a camera emission the flattened camera
    frames as observations (:func:`image_traversal`)."""
    if config.emission.observation == "image":
        return image_traversal(traversal)
    tr = traversal.subsample_beams(config.beam_stride)
    if config.range_clip is not None:
        tr = tr.clip_ranges(config.range_clip)
    return tr


def image_traversal(traversal: Traversal) -> Traversal:
    """The traversal with its camera frames ``images [T, H, W]`` as observations ``[T, H * W]``
    (row-major), ``beam_angles`` the bearing of each pixel's column
    (``metadata["camera"]["fov"]``, default 90 deg), ``max_range`` 1 and
    ``metadata["image_shape"] = [H, W]``; already prepared traversals are returned as they are."""
    if "image_shape" in traversal.metadata:
        return traversal
    if traversal.images is None:
        raise ValueError("a camera emission needs a traversal with images")
    T, H, W = traversal.images.shape
    fov = float((traversal.metadata.get("camera") or {}).get("fov", math.pi / 2))
    cols = fov / 2 - (np.arange(W) + 0.5) * (fov / W)
    return replace(
        traversal,
        observations=traversal.images.reshape(T, H * W),
        beam_angles=np.tile(cols, H),
        max_range=1.0,
        obs_mask=None,
        metadata={**traversal.metadata, "image_shape": [H, W]},
    )


def make_emission(traversal: Traversal, config: SLAMConfig) -> Emission | EmissionMLP:
    """A new (untrained) emission of ``config.emission.kind`` for a prepared traversal
    (:func:`~pyro_slam.slam.components.register_emission`)."""
    reach = float(config.range_clip or traversal.max_range)
    return emission_kind(config.emission.kind).make(traversal, config, reach)


def _extent(traversal: Traversal, config: SLAMConfig):
    """The box ``(xmin, ymin, xmax, ymax)`` the map covers: the walls, or (logs without
    walls) the odometry path plus the sensor's practical range."""
    if traversal.walls.shape[0]:
        pts = traversal.walls.reshape(-1, 2)
        return (*pts.min(0), *pts.max(0))
    reach = float(config.range_clip or traversal.max_range)
    path = odometry_poses(traversal, traversal.start_pose)[:, :2]
    return (*(path.min(0) - reach), *(path.max(0) + reach))


def transition_kind(transition) -> str:
    """The ``transition.kind`` that a transition is: ``"learned"`` for the network,
    ``"kinematic"`` for the control model (another class: its name)."""
    if isinstance(transition, LearnedTransition):
        return "learned"
    if isinstance(transition, KinematicTransition):
        return "kinematic"
    return type(transition).__name__


MAX_BYTES = 8 << 30  # the largest working set a configuration may ask for (8 GiB)
# the most offline SVI steps a configuration may ask for (each takes milliseconds to a second)
MAX_SVI_STEPS = 1_000_000
MAX_FILTER_STEPS = 100_000_000  # the most steps offline rounds may filter (1e8: about a month)


def _gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB"


def check_hits(traversal: Traversal, config: SLAMConfig, src: str = "traversal") -> None:
    """Refuse a (prepared) LiDAR traversal without one usable hit: a valid reading below the
    range clip (or, without one, the sensor's range). Nothing could be mapped, and the scan
    metrics would be undefined."""
    if config.emission.observation != "lidar":
        return
    reach = min(float(config.range_clip or traversal.max_range), traversal.max_range)
    obs = np.asarray(traversal.observations)
    hit = obs < reach * (1 - 1e-6)
    if traversal.obs_mask is not None:
        hit &= traversal.obs_mask
    if not hit.any():
        at = f"the sensor's range {traversal.max_range:g}"
        if config.range_clip:
            at = f"the range clip {config.range_clip:g} (range_clip)"
        raise DatasetError(
            f"{src}: field 'observations' has no usable hit: every valid reading lies at or "
            f"beyond {at}"
        )


def check_size(traversal: Traversal, config: SLAMConfig) -> None:
    """Refuse, before anything is allocated, a configuration whose map grid or particle
    tensors for this (prepared) traversal would not fit in memory, naming the field; and a
    traversal without a usable hit (:func:`check_hits`)."""
    check_hits(traversal, config)
    x0, y0, x1, y1 = _extent(traversal, config)
    e = config.emission
    cells = [(hi - lo + 2 * e.margin) / e.resolution + 1 for lo, hi in ((x0, x1), (y0, y1))]
    kind = emission_kind(e.kind)
    dim = kind.features(traversal)
    grid = cells[0] * cells[1] * dim * 4 * 8  # q(M) loc, scale, their gradients and Adam moments
    if grid > MAX_BYTES:
        raise ConfigError(
            f"emission.resolution {e.resolution:g} over the data's {x1 - x0:.4g} x {y1 - y0:.4g} "
            f"extent needs a {cells[0]:.0f} x {cells[1]:.0f} grid ({_gib(grid)}; at most "
            f"{_gib(MAX_BYTES)}): use a coarser resolution"
        )
    reach = float(config.range_clip or traversal.max_range)
    samples = ray_settings(config, reach).get("samples", RAY_SAMPLES)
    per_point = traversal.num_beams * (samples if kind.rays else 1)
    per_point *= 4 * 8  # float32 points, stops, weights and their gradients
    t = config.training
    for name, n in (
        ("filter.particles", config.filter.particles),
        ("training.particles x chunks x chunk_length", t.particles * t.chunks * t.chunk_length),
    ):
        if n * per_point > MAX_BYTES:
            raise ConfigError(
                f"{name} {n} would need {_gib(n * per_point)} for its particles' predicted "
                f"observations (at most {_gib(MAX_BYTES)})"
            )
    _check_cost(traversal, config)


def _check_cost(traversal: Traversal, config: SLAMConfig) -> None:
    """Refuse the particle cache that would not fit in memory (its poses and weights, ``[T,
    K, 4]`` float32, twice for the refresh), and more offline filter steps or SVI steps than
    :data:`MAX_FILTER_STEPS` / :data:`MAX_SVI_STEPS`, which would run for days."""
    k = config.training.cache_particles
    cache = traversal.num_steps * k * 4 * 4 * 2
    if cache > MAX_BYTES:
        raise ConfigError(
            f"training.cache_particles {k} would need {_gib(cache)} for the particle cache of "
            f"{traversal.num_steps} steps (at most {_gib(MAX_BYTES)})"
        )
    o = config.offline
    if o.rounds * traversal.num_steps > MAX_FILTER_STEPS:
        raise ConfigError(
            f"offline.rounds {o.rounds} over {traversal.num_steps} steps would filter for days "
            f"(at most {MAX_FILTER_STEPS:g} filter steps in all)"
        )
    if o.rounds * o.svi_steps > MAX_SVI_STEPS:
        raise ConfigError(
            f"offline.rounds x offline.svi_steps {o.rounds} x {o.svi_steps} SVI steps would run "
            f"for days (at most {MAX_SVI_STEPS:g} in all)"
        )


def build_model(
    traversal: Traversal,
    config: SLAMConfig,
    transition: Transition | None = None,
    emission: Emission | EmissionMLP | None = None,
    prior=None,
    noise=None,
    **parts,
):
    """A :class:`~pyro_slam.model.DVBFLM` and :class:`~pyro_slam.model.MapGuide` sized to a
    prepared traversal's extent (see :func:`prepare_traversal`); ``prior`` and ``noise``: the
    model's map prior and emission noise (see :class:`~pyro_slam.model.DVBFLM`; the guide
    starts at the prior's std).

    ``prior``/``noise`` None: the configured ones (``emission.prior``, ``emission.noise``;
    :func:`map_prior`, :func:`emission_noise`). ``emission``: a (pretrained) emission, or None
    for a new one of the configured kind (:func:`make_emission`); ``transition``: None for the
    configured kinematic one. SLAM filters
    with ``sigma_T`` times ``config.transition.scale`` (the transition passed in is copied, not
    changed). ``parts``: the model's other constructor arguments (``heading``,
    ``learn_emission``, ``learn_transition``, ``handler``; :class:`~pyro_slam.model.DVBFLM`),
    so that it is built complete."""
    if emission is None:
        emission = make_emission(traversal, config)
    elif isinstance(emission, LidarEmission):  # re-read at this traversal's beams
        emission = emission.net
    e = config.emission
    map_dim = emission.map_dim
    grid = MapGrid.covering(*_extent(traversal, config), e.resolution, map_dim, e.margin)
    prior = map_prior(e.prior, map_dim) if prior is None else prior
    noise = emission_noise(e.noise) if noise is None else noise
    if transition is None:
        control_model = traversal.metadata.get("control_model", "rotate_forward")
        transition = KinematicTransition(config.transition.sigma, control_model)
    scale = torch.as_tensor(config.transition.scale, dtype=transition.sigma.dtype)
    if not bool((scale == 1).all()):
        transition = copy.deepcopy(transition)
        transition.sigma.mul_(scale)
    model = DVBFLM(
        grid,
        emission,
        transition,
        traversal.beam_angles,
        e.sigma,
        prior=prior,
        noise=noise,
        outlier_prob=e.outlier_prob,
        outlier_range=_reading_range(emission),
        **parts,
    )
    return model, MapGuide(grid.shape, init_scale=model.prior_std())


def _reading_range(emission) -> float:
    """The interval a reading lies in (the sensor's range): the outlier component's width."""
    return float(getattr(emission, "reading_range", None) or getattr(emission, "scale", 1.0))


def traversal_tensors(tr: Traversal):
    """``(observations [T, N], controls [T-1, D_u], mask [T, N] or None, start pose [3])``."""
    dtype = torch.get_default_dtype()
    obs = torch.as_tensor(tr.observations, dtype=dtype)
    ctl = torch.as_tensor(tr.controls, dtype=dtype)
    mask = None if tr.obs_mask is None else torch.as_tensor(tr.obs_mask)
    return obs, ctl, mask, torch.as_tensor(tr.start_pose, dtype=dtype)


def path_integration(traversal: Traversal, transition: Transition):
    """Dead reckoning with a transition's mean from the start pose: ``[T, 3]`` (heading wrapped).

    Transitions that need a scan get the *observed* scan (what a pretrained transition saw).
    """
    obs, ctl, _, z = traversal_tensors(traversal)
    out = [z]
    with torch.no_grad():
        for t in range(ctl.shape[0]):
            z = transition.mean(z, ctl[t], obs[t] if transition.needs_scan else None)
            out.append(z)
    poses = torch.stack(out)
    poses[:, 2] = wrap_angle(poses[:, 2])
    return poses.numpy().astype(np.float64)
