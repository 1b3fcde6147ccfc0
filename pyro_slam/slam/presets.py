"""Named SLAM configurations. Each preset is one :class:`Preset` object; the CLI takes
``--preset NAME`` (plus ``--config`` overrides) and the benchmarks name the preset they ran.
The default preset is ``SLAMConfig()`` itself (:mod:`pyro_slam.slam.config` holds every
default); the others say how they differ from it.

========================  ===============================================================
``manhattan`` (default)   the ray-cast LiDAR emission with scan insertion and the beam
                          mixture, the heading factor in a walls' frame estimated from the
                          scans, the scan-matching proposal
``raycast``               ``manhattan`` without the heading factor
``paper``                 the paper's model: pretrained LiDAR emission MLP, the shipped
                          learned transition, the bootstrap filter
``visual``                the paper's visual model (row MLPs)
``visual-raycast``        the ray camera
``visual-manhattan``      the ray camera plus the heading factor read from the frames
``real``                  real laser logs (CARMEN, ROS): end-point (likelihood-field) emission
                          on a metric grid, heading factor; sensor settings derived from the
                          log
========================  ===============================================================

The figures of each are on the results page (``docs/results.md``).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ..data import Traversal
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
    parse_overrides,
    with_overrides,
)
from .heading import odometry_heading_noise

DEFAULT = "manhattan"
ODOMETRY_FLOOR = 0.01  # the smallest transition std a real log's odometry gets (m, rad)


@dataclass(frozen=True)
class Preset:
    """A named configuration; ``adapt(traversal, config)``, if set, fills in the settings that
    depend on the data (e.g. a real log's beam stride and odometry noise)."""

    name: str
    summary: str
    config: SLAMConfig
    adapt: Callable[[Traversal, SLAMConfig], SLAMConfig] | None = None

    def for_traversal(self, traversal: Traversal | None = None) -> SLAMConfig:
        """The configuration for ``traversal`` (``config`` itself when nothing depends on it)."""
        if self.adapt is None or traversal is None:
            return self.config
        return self.adapt(traversal, self.config)


def odometry_sigma(
    controls, trans_frac: float = 0.1, rot_frac: float = 0.1, floor: float = ODOMETRY_FLOOR
):
    """Transition std ``(x, y, heading)`` from a relative-odometry noise model.

    Odometry errors grow with the motion (Thrun et al., Probabilistic Robotics, ch. 5.4): per
    step, ``trans_frac`` of the RMS step length on x and y and ``rot_frac`` of the RMS heading
    change plus ``rot_frac`` rad per metre of the RMS step on the heading, with a floor of
    ``floor`` (units, rad) -- a fixed std, as :class:`~pyro_slam.model.KinematicTransition`
    takes.
    """
    u = np.asarray(controls, dtype=np.float64)  # [T-1, D_u]
    step = float(np.sqrt(np.mean(np.sum(u[:, :2] ** 2, axis=1)))) if len(u) else 0.0
    turn = float(np.sqrt(np.mean(u[:, 2] ** 2))) if len(u) and u.shape[1] >= 3 else 0.0
    s_xy = max(trans_frac * step, floor)
    s_h = max(rot_frac * (turn + step), floor)
    return (s_xy, s_xy, s_h)


@dataclass(frozen=True)
class RealLogAdaptation:
    """The numbers :func:`adapt_real_log` reads a real log with: at most ``target_beams``
    beams, readings clipped at the ``range_quantile`` percentile, transition std on x/y the
    fraction ``odometry_noise`` of the RMS odometry step, and on the heading, where the scans'
    walls do not show odometry's heading drift, the fraction ``heading_noise`` of the RMS turn
    plus the RMS step (per metre)."""

    target_beams: int = 46
    range_quantile: float = 99.0
    odometry_noise: float = 0.08
    heading_noise: float = 0.1


REAL_LOG = RealLogAdaptation()


def adapt_real_log(
    traversal: Traversal,
    config: SLAMConfig,
    *,
    target_beams: int = REAL_LOG.target_beams,
    range_quantile: float = REAL_LOG.range_quantile,
    odometry_noise: float = REAL_LOG.odometry_noise,
    heading_noise: float = REAL_LOG.heading_noise,
) -> SLAMConfig:
    """``config`` for a metric real log: every ``beam_stride``-th beam so that at most
    ``target_beams`` remain (361 -> every 8th); readings clipped at the ``range_quantile``
    percentile of the valid ones (rare long returns then do not set the emission's scale);
    the kinematic ``sigma_T`` on x/y from :func:`odometry_sigma` with fraction
    ``odometry_noise``, and on the heading the drift of odometry's heading that the scans' wall
    directions show (:func:`~pyro_slam.slam.heading.odometry_heading_noise`, with the heading
    factor), else :func:`odometry_sigma`'s with fraction ``heading_noise``."""
    stride = max(1, int(math.ceil(traversal.num_beams / target_beams)))
    valid = traversal.valid_ranges()
    clip = float(np.percentile(valid, range_quantile)) if valid.size else traversal.max_range
    config = replace(config, beam_stride=stride, range_clip=round(clip, 2))
    s_x, s_y, s_h = odometry_sigma(traversal.controls, odometry_noise, heading_noise)
    drift = odometry_heading_noise(traversal, config)
    if drift is not None:  # what the scans show beats a share of the motion
        s_h = max(drift, ODOMETRY_FLOOR)
    return replace(config, transition=replace(config.transition, sigma=(s_x, s_y, s_h)))


# the default: the ray-cast LiDAR emission with scan insertion and the beam mixture, the shipped
# learned transition, the heading factor, the scan-matching proposal, SVI every 2 steps
MANHATTAN = SLAMConfig()
# the same without the heading factor, for worlds without two dominant wall directions
RAYCAST = replace(MANHATTAN, heading=None)
# the paper's LiDAR model: the pretrained emission MLP on a 32 x 32 grid, Gaussian noise, the
# bootstrap filter, SVI at every step
PAPER = replace(
    MANHATTAN,
    emission=EmissionConfig("mlp", resolution=1 / 31, outlier_prob=0.0),
    filter=FilterConfig(proposal="transition"),
    training=TrainingConfig(every=1),
    heading=None,
)
# the paper's visual model: row MLPs, kinematic transition, the bootstrap filter
VISUAL = SLAMConfig(
    emission=EmissionConfig(
        "image_mlp", resolution=1 / 24, margin=0.0, sigma=0.1, outlier_prob=0.0
    ),
    transition=TransitionConfig("kinematic", scale=(0.6, 0.6, 0.15)),
    filter=FilterConfig(proposal="transition"),
    training=TrainingConfig(particles=8, chunks=16, lr=0.05, every=1),
    offline=OfflineConfig(rounds=2, svi_steps=400, estimate="forward"),
    heading=None,
)
VISUAL_RAYCAST = replace(
    VISUAL,
    emission=EmissionConfig(
        "ray_camera", resolution=1 / 63, margin=0.0, sigma=0.1, outlier_prob=0.0
    ),
)
VISUAL_MANHATTAN = replace(VISUAL_RAYCAST, heading=HeadingConfig())
# real logs (metres): the end-point (likelihood-field) emission on a 0.05 m grid, each reading
# scored by the signed distance that the map's wall ramp (3 grid spacings either side) says at
# its end point, sigma_E 0.075 m, the beam mixture; scan insertion (hits farther apart than
# 0.5 m are separate walls) fused as a signed distance (real walls have a back side no beam
# sees); the kinematic odometry transition (its noise read from the log), the heading factor in
# the walls' frame estimated from the log, which switches itself off where the walls do not
# support it. The map belief is scan insertion's (no online SVI: with an SVI step every 32
# scans both logs were less accurate); the filter's 64 particles are drawn by the
# heading-conditioned transition. Offline: one filter pass over the whole log under the online
# map. Predicted scans (planning, sampling) are the ray march's, stopped once a beam's
# transmittance is below 1e-6. Measured over both logs and five seeds against the ray-cast
# emission (docs/results.md): more accurate on both, three times faster.
REAL = SLAMConfig(
    emission=EmissionConfig(
        "endpoint",
        resolution=0.05,
        margin=0.0,
        sigma=0.075,
        insert=ScanInsertionConfig(kind="fusion", gap=0.5),
        ray_spacing=1.0,
        march_tolerance=1e-6,
    ),
    transition=TransitionConfig("kinematic", scale=(1.0, 1.0, 1.0)),
    filter=FilterConfig(particles=64, proposal="transition"),
    training=TrainingConfig(every=0),
    offline=OfflineConfig(rounds=0, estimate="forward"),
)

# the model the planner maps with and plans in (:func:`pyro_slam.planning.learned_env`): the
# paper's LiDAR emission MLP on its 32 x 32 grid, with the paper's Gaussian noise of 0.1 (the
# mapping fits its own, which the planner's rollouts sample) and kinematics (which
# :func:`pyro_slam.planning.learned_env` stops short of the walls the predicted scan shows ahead)
NAVIGATION_MAPPING = SLAMConfig(
    emission=EmissionConfig("mlp", resolution=1 / 31, sigma=0.1, outlier_prob=0.0),
    transition=TransitionConfig("kinematic", scale=(1.0, 1.0, 1.0)),
    heading=None,
)

PRESETS: dict[str, Preset] = {
    p.name: p
    for p in (
        Preset("paper", "the paper's model: pretrained emission MLP, learned transition", PAPER),
        Preset("raycast", "ray-cast LiDAR emission with scan insertion, scan matching", RAYCAST),
        Preset(
            "manhattan",
            "raycast + the heading factor (walls' frame estimated) (default)",
            MANHATTAN,
        ),
        Preset("visual", "the paper's visual model: row MLPs on camera frames", VISUAL),
        Preset("visual-raycast", "ray camera on camera frames", VISUAL_RAYCAST),
        Preset(
            "visual-manhattan", "ray camera + heading observation from the frames", VISUAL_MANHATTAN
        ),
        Preset(
            "real",
            "real laser logs: end-point emission on a metric grid + heading observation",
            REAL,
            adapt_real_log,
        ),
    )
}


def get(name: str) -> Preset:
    """The preset called ``name``; a clear error listing the names otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; presets: {', '.join(PRESETS)}") from None


def describe() -> str:
    """One line per preset (for ``--help``)."""
    return "\n".join(f"{p.name}: {p.summary}" for p in PRESETS.values())


def is_real_log(traversal: Traversal) -> bool:
    """A metric log from a reader (no walls, robot-frame odometry), not a simulated maze."""
    return not traversal.walls.shape[0] and (
        traversal.metadata.get("control_model") == "odometry_delta"
    )


def resolve(config: SLAMConfig | Preset | str | None, traversal: Traversal) -> SLAMConfig:
    """The configuration a SLAM run on ``traversal`` uses for ``config``, as the CLI chooses it:
    None -> :func:`default_for`; a preset name or a :class:`Preset` -> its configuration for
    this traversal (a data-dependent preset such as ``real`` adapted to the log);
    a :class:`SLAMConfig` as it is. A data-dependent preset's unadapted ``.config`` on a real
    log (all beams, no range clip, the simulator's odometry noise) warns and suggests the name.
    """
    if config is None:
        return default_for(traversal)
    if isinstance(config, str):
        config = get(config)
    if isinstance(config, Preset):
        return config.for_traversal(traversal)
    if not isinstance(config, SLAMConfig):
        raise ConfigError(
            f"config must be a preset name, a Preset or a SLAMConfig, got {type(config).__name__}"
        )
    unadapted = [p.name for p in PRESETS.values() if p.adapt is not None and p.config == config]
    if unadapted and is_real_log(traversal):
        warnings.warn(
            f"the {unadapted[0]!r} preset's .config is not adapted to this log (beam stride, "
            f"range clip, odometry noise); pass {unadapted[0]!r} or "
            f"presets.get({unadapted[0]!r}) to adapt it as pyro-slam slam does",
            UserWarning,
            stacklevel=3,
        )
    return config


def configure(
    name: str | None = None,
    traversal: Traversal | None = None,
    overrides=None,
    odometry_noise: float | None = None,
) -> tuple[str, SLAMConfig]:
    """The one way the command line and the benchmarks choose a configuration: the preset
    ``name`` (default: ``real`` for a real log, else the default preset) adapted to
    ``traversal`` (``odometry_noise``: the real-log adaptation's odometry noise fraction), then
    the nested ``overrides`` (a dict, a JSON object's text, the path of a JSON file, or a list of
    those applied in turn; see :func:`~pyro_slam.slam.config.with_overrides`). Returns
    ``(name, config)``; a bad name or override raises
    :class:`~pyro_slam.slam.config.ConfigError` naming it."""
    if name is None:
        name = "real" if traversal is not None and is_real_log(traversal) else DEFAULT
    try:
        preset = get(name)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if odometry_noise is not None and preset.adapt is adapt_real_log and traversal is not None:
        config = adapt_real_log(traversal, preset.config, odometry_noise=odometry_noise)
    else:
        config = preset.for_traversal(traversal)
    for changes in overrides if isinstance(overrides, (list, tuple)) else [overrides]:
        if changes is not None:
            parsed = parse_overrides(changes) if isinstance(changes, str) else changes
            config = with_overrides(config, parsed)
    return name, config


def default_for(traversal: Traversal | None = None) -> SLAMConfig:
    """The default configuration for ``traversal``: the ``real`` preset for a real log, the
    default preset otherwise."""
    if traversal is not None and is_real_log(traversal):
        return PRESETS["real"].for_traversal(traversal)
    return PRESETS[DEFAULT].config


__all__ = [
    "DEFAULT",
    "PRESETS",
    "Preset",
    "adapt_real_log",
    "configure",
    "default_for",
    "describe",
    "get",
    "is_real_log",
    "odometry_sigma",
    "resolve",
]
