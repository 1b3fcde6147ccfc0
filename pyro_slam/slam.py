"""SLAM with DVBF-LM: online (sweep t = 1..T) and offline (all steps), with checkpoints.

The estimator is the paper's: SVI (Adam) on the particle-chunk ELBO (eq. 3) for the map belief
``q(M)`` (and optionally the emission network), with the bootstrap particle filter as the pose
guide and the asynchronous particle cache.

* **online**: at every step the particle filter advances under the current map mean, its
  particles enter the cache, and ``svi_steps`` SVI steps run on the newest chunk plus random
  older chunks (replay), with the ELBO scaled to the steps seen so far.
* **offline**: rounds of (a) one particle-filter pass over the whole traversal under the current
  map mean, which refreshes the whole cache forward through the transition, and (b) SVI on random
  chunks from anywhere in the traversal; a final filtering pass gives the pose posterior. The
  first round starts from an online sweep (``offline_init="online"``) or from odometry alone
  (``"odometry"``). With ``offline_estimate="cache"`` (the paper's procedure) there is no
  whole-traversal pass: only the SVI chunks refresh the cache, and the final poses are filtered
  in consecutive chunks, each started from the cache (paper Appendix B-I).

Every long loop shows a tqdm bar and writes atomic checkpoints from which :meth:`SLAM.resume`
continues with the same random stream.
"""

from __future__ import annotations

import copy
import io
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import pyro
import torch
from pyro.infer import SVI
from pyro.optim import Adam
from tqdm.auto import tqdm

from .data import Traversal, atomic_write
from .filtering import (
    PROPOSALS,
    ChunkBatch,
    HeadingObservation,
    MapBelief,
    ParticleCache,
    ParticleChunkELBO,
    ParticleFilter,
    Particles,
)
from .geometry import image_background, image_wall_direction, wall_direction
from .guide import MapGuide
from .model import DVBFLM, MapGrid
from .networks import (
    Emission,
    EmissionMLP,
    ImageEmission,
    LidarEmission,
    RayEmission,
    RayImageEmission,
)
from .transitions import KinematicTransition, Transition

# SLAMConfig.trusted_passes -> the SLAMState phases in which transition_scale_trusted acts
TRUSTED_PASSES = {
    "online": ("online", "online-init"),
    "final": ("online", "online-init", "offline-final"),
    "all": ("online", "online-init", "offline-filter", "offline-final"),
}


@dataclass
class SLAMConfig:
    """Hyper-parameters (defaults tuned on a held-out moderate-medium maze)."""

    map_resolution: float = 1 / 31  # grid spacing, world units (32 x 32 for the unit maze)
    map_dim: int = 10  # D_m
    map_margin: float = 0.05
    emission_hidden: int = 256
    emission_layers: int = 4
    n_world: int = 20  # world-frame directions of the LiDAR emission profile (>= beams)
    sigma_emission: float = 0.1  # sigma_E for training
    filter_sigma: float | None = 0.05  # sigma_E used to weigh the filter's particles
    train_sigma: float | None = None  # sigma_E of the ELBO's chunk filter (None: filter_sigma)
    transition_sigma: tuple[float, float, float] = (5e-4, 5e-4, 8e-3)
    # factors on sigma_T (x, y, heading) of the transition SLAM filters with (the paper lets
    # sigma_T -> 0); the transition passed in is copied, not changed
    transition_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    # the online filter's scale of sigma_T where the map is trusted: interpolated from
    # transition_scale (trust 0) by the cloud's trust in the map at the previous step (None: fixed)
    transition_scale_trusted: tuple[float, float, float] | None = None
    # where transition_scale_trusted acts: "online" (the online sweep, also the one offline SLAM
    # starts from), "final" (also offline SLAM's final filter pass) or "all" (every filter pass)
    trusted_passes: str = "online"
    uncertainty_gain: float = 1.0
    weighting: str = "marginal"  # filter weights under q(M): marginal|shared|tempered|predictive
    # per-beam outlier probability of the filter's weights: a floor under the tempered weights,
    # a uniform-outlier beam mixture under the others (ParticleFilter)
    outlier_prob: float = 0.0
    train_outlier_prob: float | None = None  # the ELBO's chunk filter's (None: outlier_prob)
    filter_particles: int = 128
    train_particles: int = 16
    cache_particles: int = 50
    chunk_length: int = 4
    chunks_per_batch: int = 4
    lr_map: float = 0.02
    lr_map_scale: float | None = None  # lr of q(M)'s scale (default: lr_map)
    lr_emission: float = 1e-3
    learn_emission: bool = True
    svi_every: int = 1
    svi_steps: int = 1
    newest_svi_steps: int = 0  # online: extra SVI steps on the newest chunk alone, per step
    offline_rounds: int = 2
    offline_svi_steps: int = 800
    offline_init: str = "online"
    # (p, s): the filter's heading noise is s for a fraction p of the particles at each step
    # (a heavy-tailed transition; None: off)
    heading_jump: tuple[float, float] | None = None
    # > 0: heading jumps only at revisits, i.e. where the cloud's mean is on a cell first mapped
    # at least this many steps earlier (first mapping as the online sweep recorded it)
    heading_jump_age: int = 0
    # offline SLAM's pose posterior: "forward" (a filter pass over the whole traversal after
    # each round and at the end) or "cache" (the paper's: only the SVI chunks refresh the cache
    # (eq. 3), and the final poses are filtered as in its Appendix B-I, in consecutive chunks of
    # chunk_length steps, each started from its first step's cached particles plus 1e-3 noise)
    offline_estimate: str = "forward"
    proposal: str = "gaussian"
    # the SLAM filter's particle proposal: "bootstrap" or "linearised" (ParticleFilter; the
    # ELBO's chunk filter stays bootstrap)
    filter_proposal: str = "bootstrap"
    proposal_shrink: float = 1.0  # scale of the cache proposal's std for map training
    revisit_gap: int = 0  # online: cells first mapped < gap steps ago do not weigh particles
    revisit_radius: float | None = None  # online: trust by distance to poses >= gap steps old
    write_lag: int = 0  # online: SVI learns the map from steps at least this old
    # > 0: the ELBO also writes each scan, reprojected by the LiDAR geometry, at positions within
    # this radius of its pose (ParticleChunkELBO); samples per step and weight vs the real scan
    reproject_radius: float = 0.0
    reproject_samples: int = 4
    reproject_weight: float = 1.0
    seed: int = 0
    checkpoint_every: int = 1000
    beam_stride: int = 1  # SLAM uses every k-th beam (see prepare_traversal)
    range_clip: float | None = None  # readings clipped here; emission scale + map margin
    observation: str = "lidar"  # lidar | image (traversal.images, see prepare_traversal)
    # LiDAR read-out: "mlp" (the paper's chart + mu_E MLP) or "raycast" (RayEmission: expected
    # ranges marched through a one-feature density map; map_dim and the emission MLP unused)
    lidar_emission: str = "mlp"
    ray_samples: int = 48  # raycast: points per beam
    # raycast, online sweep: each scan's hits, placed from the cloud's mean pose, set the map mean
    # at grid points no scan has hit before to this occupancy (an occupancy-grid warm start of
    # q(M) that SVI then refines; None: off)
    ray_insert: float | None = None
    ray_insert_gap: float = 0.05  # hits of neighbouring beams closer than this form one wall
    # hits farther than this from the sensor are not written (None: all): a heading error e
    # moves a wall seen at range r by e * r, so far walls carry the heading error into the map
    ray_insert_range: float | None = None
    ray_insert_scale: float | None = None  # and q(M)'s scale there (None: left as it is)
    # and this occupancy (e.g. -1) at grid points the beams cross before their hits (or up to
    # the range), with the same scale, where no scan wrote before (None: free space not written)
    ray_insert_free: float | None = None
    # scan t is written at step t + ray_insert_lag, from the pose estimated at t: the filter
    # then matches each scan against walls that older steps saw, not against its own last scans
    ray_insert_lag: int = 0
    # with ray_insert_lag > 0: place scan t from the fixed-lag smoothed pose (the mean of the
    # particles' ancestors at t under the weights of step t + lag) instead of step t's estimate
    ray_insert_smooth: bool = False
    # raycast: the scans of the first ray_anchor steps (taken from the known start pose) are
    # written into q(M) - their hits as walls, the grid points their beams cross as free space,
    # both with scale ray_anchor_scale - and held there through every SVI step, so that the
    # map's frame (its offset and rotation) stays tied to the start pose (0: off)
    ray_anchor: int = 0
    ray_anchor_scale: float = 0.05
    # raycast: the weights' trust in q(M) per beam (variance where each beam stops) instead of
    # per particle (variance of its own chart); per beam screened worse (docs/benchmarks.md);
    # "path": a beam is trusted only where the map is known all the way to its stop
    beam_trust: bool | str = False
    image_bins: int = 32  # image emission: angular bins k of the map (D_m = k * image rows)
    # camera read-out: "mlp" (the paper's rotated chart + row-wise MLPs) or "raycast"
    # (RayImageEmission: one ray per column through an occupancy map, a pinhole camera draws the
    # wall it hits; D_m = 1 + ray_albedo_bins, image_bins and the emission MLP unused)
    image_emission: str = "mlp"
    ray_albedo_bins: int = 8  # raycast camera: albedo directions per cell
    # Not the paper's model: a Manhattan-world heading observation with this std (rad). Each
    # scan's straight walls give its heading modulo pi / 2 (geometry.wall_direction; images:
    # the walls' edges, geometry.image_wall_direction) if the walls run along the world axes,
    # as the simulator's mazes' do; the filter samples the heading exactly conditioned on it
    # (ParticleFilter._heading_proposal) wherever at least wall_heading_support segments agree
    # within wall_heading_tol rad (None: off)
    wall_heading: float | None = None
    wall_heading_tol: float = 1e-3
    wall_heading_support: int = 2

    def to_dict(self):
        return asdict(self)


def build_model(
    traversal: Traversal,
    config: SLAMConfig,
    transition: Transition | None = None,
    emission: Emission | EmissionMLP | None = None,
):
    """A :class:`DVBFLM` and :class:`MapGuide` sized to the traversal's extent.

    ``config.observation == "image"``: an :class:`ImageEmission` (``config.image_bins`` x image
    rows features per cell, ``emission_hidden`` x ``emission_layers`` ReLU row networks) for a
    traversal prepared by :func:`prepare_traversal`; ``config.map_dim`` is then unused.

    The grid covers the maze walls (or, for logs without walls, the odometry path plus the
    sensor's practical range ``config.range_clip or max_range``) with ``config.map_resolution``
    spacing; the emission's output scale is that range too. The traversal is used as given
    (:class:`SLAM` applies :func:`prepare_traversal` first).
    """
    reach = float(config.range_clip or traversal.max_range)
    if traversal.walls.shape[0]:
        lo = traversal.walls.reshape(-1, 2).min(0)
        hi = traversal.walls.reshape(-1, 2).max(0)
    else:
        from .metrics import odometry_poses

        path = odometry_poses(traversal)[:, :2]
        lo = path.min(0) - reach
        hi = path.max(0) + reach
    if config.observation == "image":
        if config.image_emission not in ("mlp", "raycast"):
            raise ValueError(
                f"image_emission must be 'mlp' or 'raycast', got {config.image_emission!r}"
            )
        if emission is None:
            rows, cols = traversal.metadata["image_shape"]
            if config.image_emission == "raycast":
                emission = RayImageEmission(
                    traversal.beam_angles[:cols], rows, reach, config.ray_samples,
                    config.ray_albedo_bins,
                )  # fmt: skip
            else:
                emission = ImageEmission(
                    config.image_bins, rows, cols, hidden=config.emission_hidden,
                    layers=config.emission_layers, column_angles=traversal.beam_angles[:cols],
                )  # fmt: skip
    elif config.observation != "lidar":
        raise ValueError(f"observation must be 'lidar' or 'image', got {config.observation!r}")
    elif config.lidar_emission not in ("mlp", "raycast"):
        raise ValueError(
            f"lidar_emission must be 'mlp' or 'raycast', got {config.lidar_emission!r}"
        )
    elif emission is None and config.lidar_emission == "raycast":
        emission = RayEmission(traversal.beam_angles, reach, config.ray_samples)
    elif emission is None:
        n_world = max(traversal.num_beams, config.n_world)
        emission = EmissionMLP(
            config.map_dim, n_world, config.emission_hidden, config.emission_layers, scale=reach
        )
    elif isinstance(emission, LidarEmission):  # re-read at this traversal's beams
        emission = emission.net
    map_dim = emission.map_dim
    grid = MapGrid.covering(*lo, *hi, config.map_resolution, map_dim, config.map_margin)
    if transition is None:
        control_model = traversal.metadata.get("control_model", "rotate_forward")
        transition = KinematicTransition(config.transition_sigma, control_model)
    scale = torch.as_tensor(config.transition_scale, dtype=transition.sigma.dtype)
    if scale.shape != (3,) or not bool((scale > 0).all()):
        raise ValueError(
            f"transition_scale must be 3 positive factors (x, y, heading), "
            f"got {config.transition_scale!r}"
        )
    if not bool((scale == 1).all()):
        transition = copy.deepcopy(transition)
        transition.sigma.mul_(scale)
    model = DVBFLM(grid, emission, transition, traversal.beam_angles, config.sigma_emission)
    model.learn_emission = config.learn_emission
    guide = MapGuide(grid.shape)
    return model, guide


def prepare_traversal(traversal: Traversal, config: SLAMConfig) -> Traversal:
    """The traversal SLAM sees: every ``config.beam_stride``-th beam, readings clipped at
    ``config.range_clip`` (both no-ops by default).

    ``config.observation == "image"``: the observations become the flattened camera frames
    ``traversal.images [T, H, W] -> [T, H * W]`` (row-major), ``beam_angles`` the bearing of each
    pixel's column (``metadata["camera"]["fov"]``, default 90 deg), ``max_range`` 1 and
    ``metadata["image_shape"] = [H, W]``; already prepared traversals are returned as they are.
    """
    if config.observation == "image":
        return image_traversal(traversal)
    tr = traversal.subsample_beams(config.beam_stride)
    if config.range_clip is not None:
        tr = tr.clip_ranges(config.range_clip)
    return tr


def image_traversal(traversal: Traversal) -> Traversal:
    """The traversal with its camera frames as (flattened) observations, see prepare_traversal."""
    if "image_shape" in traversal.metadata:
        return traversal
    if traversal.images is None:
        raise ValueError("observation='image' needs a traversal with images")
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


def odometry_sigma(controls, trans_frac: float = 0.1, rot_frac: float = 0.1, floor=0.01):
    """Transition std ``(x, y, heading)`` from a relative-odometry noise model.

    Odometry errors grow with the motion (Thrun et al., Probabilistic Robotics, ch. 5.4): per
    step, ``trans_frac`` of the RMS step length on x and y and ``rot_frac`` of the RMS heading
    change plus ``rot_frac`` rad per metre of the RMS step on the heading, with a floor of
    ``floor`` (units, rad) -- a fixed std, as :class:`KinematicTransition` takes.
    """
    u = np.asarray(controls, dtype=np.float64)
    step = float(np.sqrt(np.mean(np.sum(u[:, :2] ** 2, axis=1)))) if len(u) else 0.0
    turn = float(np.sqrt(np.mean(u[:, 2] ** 2))) if len(u) and u.shape[1] >= 3 else 0.0
    s_xy = max(trans_frac * step, floor)
    s_h = max(rot_frac * (turn + step), floor)
    return (s_xy, s_xy, s_h)


def real_log_config(
    traversal: Traversal,
    *,
    target_beams: int = 46,
    resolution: float = 0.5,
    range_quantile: float = 99.0,
    odometry_noise: float = 0.1,
    **overrides,
) -> SLAMConfig:
    """A :class:`SLAMConfig` for a metric real log (metres, hundreds of beams).

    * ``beam_stride`` so that at most ``target_beams`` beams remain (361 -> every 8th);
    * ``map_resolution`` ``resolution`` (log units, 0.5 m);
    * ``range_clip``: the ``range_quantile`` percentile of the valid readings, so that rare
      long returns (and 81.9 m no-returns, which are masked anyway) do not set the emission's
      scale;
    * ``transition_sigma`` from :func:`odometry_sigma` with fraction ``odometry_noise``;
    * emission stds in metres (``sigma_emission`` 0.5 m, filter 1 m, tempered weights);
    * a lighter filter / SVI batch (128 particles, 8 chunks of 16) for thousands of scans on CPU.

    ``overrides`` (any :class:`SLAMConfig` field) win over these.
    """
    stride = max(1, int(math.ceil(traversal.num_beams / target_beams)))
    valid = traversal.valid_ranges()
    clip = float(np.percentile(valid, range_quantile)) if valid.size else traversal.max_range
    cfg = dict(
        beam_stride=stride,
        map_resolution=resolution,
        map_margin=0.0,
        range_clip=round(clip, 2),
        transition_sigma=odometry_sigma(traversal.controls, odometry_noise, odometry_noise),
        sigma_emission=0.5,
        filter_sigma=1.0,
        weighting="tempered",
        outlier_prob=0.05,
        filter_particles=128,
        train_particles=16,
        chunks_per_batch=8,
    )
    cfg.update(overrides)
    return SLAMConfig(**cfg)


def _tensors(tr: Traversal):
    dtype = torch.get_default_dtype()
    obs = torch.as_tensor(tr.observations, dtype=dtype)
    ctl = torch.as_tensor(tr.controls, dtype=dtype)
    mask = None if tr.obs_mask is None else torch.as_tensor(tr.obs_mask)
    if tr.poses is not None:
        init = torch.as_tensor(tr.poses[0], dtype=dtype)
    else:
        init = torch.zeros(3, dtype=dtype)
    return obs, ctl, mask, init


@dataclass
class SLAMState:
    """Everything a run needs to continue: written to and read from checkpoints."""

    mode: str
    phase: str = "online"  # online(-init) | offline-svi | offline-filter | offline-final | done
    t: int = 0  # next time step (online) / next SVI step (offline)
    round: int = 0
    estimates: list = field(default_factory=list)  # per step [3]
    stds: list = field(default_factory=list)
    losses: list = field(default_factory=list)
    # offline SLAM started from an online sweep: that sweep's pose means, per step [3]
    sweep_estimates: list = field(default_factory=list)


class SLAM:
    """A SLAM run over one traversal.

    Example::

        tr = pyro_slam.data.load("traversal.npz")
        slam = SLAM(tr, SLAMConfig(), checkpoint="run/ckpt.pt")
        result = slam.run("online")          # dict: mean [T, 3], std [T, 3], losses
    """

    def __init__(
        self,
        traversal: Traversal,
        config: SLAMConfig | None = None,
        transition: Transition | None = None,
        emission: Emission | EmissionMLP | None = None,
        checkpoint: str | Path | None = None,
    ):
        self.cfg = config or SLAMConfig()
        if self.cfg.revisit_radius is not None and not self.cfg.revisit_radius > 0:
            raise ValueError(f"revisit_radius must be > 0, got {self.cfg.revisit_radius}")
        if self.cfg.write_lag < 0:
            raise ValueError(f"write_lag must be >= 0, got {self.cfg.write_lag}")
        if self.cfg.newest_svi_steps < 0:
            raise ValueError(f"newest_svi_steps must be >= 0, got {self.cfg.newest_svi_steps}")
        hj = self.cfg.heading_jump
        if hj is not None and (len(hj) != 2 or not 0 <= hj[0] <= 1 or not hj[1] > 0):
            raise ValueError(f"heading_jump must be (probability in [0, 1], std > 0), got {hj!r}")
        if self.cfg.heading_jump_age < 0:
            raise ValueError(f"heading_jump_age must be >= 0, got {self.cfg.heading_jump_age}")
        st = self.cfg.transition_scale_trusted
        if st is not None and (len(st) != 3 or not all(f > 0 for f in st)):
            raise ValueError(
                f"transition_scale_trusted must be 3 positive factors (x, y, heading), got {st!r}"
            )
        if self.cfg.ray_insert is not None and (
            self.cfg.observation != "lidar" or self.cfg.lidar_emission != "raycast"
        ):
            raise ValueError(
                "ray_insert writes LiDAR hits into an occupancy map: it needs "
                "observation='lidar' and lidar_emission='raycast'"
            )
        if self.cfg.ray_anchor and (
            self.cfg.observation != "lidar" or self.cfg.lidar_emission != "raycast"
        ):
            raise ValueError(
                "ray_anchor writes LiDAR scans into an occupancy map: it needs "
                "observation='lidar' and lidar_emission='raycast'"
            )
        if not (self.cfg.ray_anchor >= 0 and self.cfg.ray_anchor_scale > 0):
            raise ValueError(
                f"ray_anchor must be >= 0 and ray_anchor_scale positive, got "
                f"{self.cfg.ray_anchor!r}, {self.cfg.ray_anchor_scale!r}"
            )
        if self.cfg.ray_insert_free is not None and self.cfg.ray_insert is None:
            raise ValueError("ray_insert_free writes free space with ray_insert: set ray_insert")
        ris = self.cfg.ray_insert_scale
        if ris is not None and not ris > 0:
            raise ValueError(f"ray_insert_scale must be positive, got {ris!r}")
        lag = self.cfg.ray_insert_lag
        if not (isinstance(lag, int) and lag >= 0):
            raise ValueError(f"ray_insert_lag must be an int >= 0, got {lag!r}")
        if self.cfg.ray_insert_smooth and lag == 0:
            raise ValueError("ray_insert_smooth smooths over ray_insert_lag steps: set it > 0")
        rir = self.cfg.ray_insert_range
        if rir is not None and not rir > 0:
            raise ValueError(f"ray_insert_range must be positive, got {rir!r}")
        if rir is not None and self.cfg.ray_insert is None:
            raise ValueError("ray_insert_range limits what ray_insert writes: set ray_insert")
        if not self.cfg.ray_insert_gap > 0:
            raise ValueError(f"ray_insert_gap must be positive, got {self.cfg.ray_insert_gap!r}")
        if self.cfg.filter_proposal not in PROPOSALS:
            raise ValueError(
                f"filter_proposal must be one of {PROPOSALS}, got {self.cfg.filter_proposal!r}"
            )
        if self.cfg.offline_estimate not in ("forward", "cache"):
            raise ValueError(
                f"offline_estimate must be 'forward' or 'cache', got {self.cfg.offline_estimate!r}"
            )
        if self.cfg.trusted_passes not in TRUSTED_PASSES:
            raise ValueError(
                f"trusted_passes must be one of {sorted(TRUSTED_PASSES)}, "
                f"got {self.cfg.trusted_passes!r}"
            )
        wh = self.cfg.wall_heading
        if wh is not None and not wh > 0:
            raise ValueError(f"wall_heading must be a positive std (rad), got {wh!r}")
        if wh is not None and self.cfg.filter_proposal != "bootstrap":
            raise ValueError("wall_heading samples the heading in the bootstrap proposal only")
        if not (self.cfg.wall_heading_tol > 0 and self.cfg.wall_heading_support >= 2):
            raise ValueError(
                "wall_heading_tol must be positive and wall_heading_support >= 2, got "
                f"{self.cfg.wall_heading_tol!r}, {self.cfg.wall_heading_support!r}"
            )
        self.tr = traversal = prepare_traversal(traversal, self.cfg)
        self.obs, self.ctl, self.mask, self.init_pose = _tensors(traversal)
        self.T = self.obs.shape[0]
        pyro.clear_param_store()
        pyro.set_rng_seed(self.cfg.seed)
        self.gen = torch.Generator().manual_seed(self.cfg.seed)
        self.model, self.guide = build_model(traversal, self.cfg, transition, emission)
        pf_args = dict(
            generator=self.gen,
            uncertainty_gain=self.cfg.uncertainty_gain,
            weighting=self.cfg.weighting,
            outlier_prob=self.cfg.outlier_prob,
            prior_predictive_std=_scan_spread(traversal),
            beam_trust=self.cfg.beam_trust,
            outlier_range=_scan_range(traversal),
        )
        # the filter weighs with a sharper sigma_E than the model's (paper B-I); the ELBO's chunk
        # filter uses the same one unless train_sigma is set (train_sigma=0.1, the model's own
        # sigma_E, measured worse on the benchmark: docs/benchmarks.md)
        self.pf = ParticleFilter(
            self.model,
            sigma_emission=self.cfg.filter_sigma,
            proposal=self.cfg.filter_proposal,
            history=lag if self.cfg.ray_insert_smooth else 0,
            **pf_args,
        )
        ts = self.cfg.filter_sigma if self.cfg.train_sigma is None else self.cfg.train_sigma
        tout = self.cfg.train_outlier_prob
        pf_args["outlier_prob"] = self.cfg.outlier_prob if tout is None else tout
        train_pf = ParticleFilter(self.model, sigma_emission=ts, **pf_args)
        self.cache = ParticleCache(self.T, self.cfg.cache_particles)
        self.headings = None  # wall_heading: HeadingObservation, value [T] (nan: none)
        if wh is not None:
            angles = torch.as_tensor(traversal.beam_angles, dtype=self.obs.dtype)
            tol = self.cfg.wall_heading_tol
            if self.cfg.observation == "image":  # the walls' edges in each frame
                frames = self.obs.reshape(self.T, *traversal.metadata["image_shape"])
                columns = angles.reshape(frames.shape[1:])[0]  # [W] column bearings
                direction, support = image_wall_direction(
                    frames, columns, image_background(frames), tol
                )
            else:
                direction, support = wall_direction(
                    self.obs, angles, float(traversal.max_range), self.mask, tol
                )
            ok = support >= self.cfg.wall_heading_support
            value = torch.where(ok, -direction, torch.full_like(direction, math.nan))  # [T]
            self.headings = HeadingObservation(value, wh)
        w, h, _ = self.model.grid.shape
        self.first_seen = torch.full((w, h), float("inf"))  # [w, h] step of first mapping
        self.inserted = torch.zeros((w, h), dtype=torch.bool)  # [w, h] hit by a ray_insert scan
        self.freed = torch.zeros((w, h), dtype=torch.bool)  # [w, h] ray_insert_free written
        self.anchor = torch.full((w, h), float("nan"))  # [w, h] ray_anchor's held mean (nan: none)
        self.track = torch.full((self.T, 2), float("nan"))  # [T, 2] online position estimates
        self.elbo = ParticleChunkELBO(
            train_pf,
            self.cache,
            self.obs,
            self.ctl,
            self.mask,
            num_particles=self.cfg.train_particles,
            proposal=self.cfg.proposal,
            proposal_shrink=self.cfg.proposal_shrink,
            reproject_radius=self.cfg.reproject_radius,
            reproject_samples=self.cfg.reproject_samples,
            reproject_weight=self.cfg.reproject_weight,
            max_range=float(traversal.max_range),
            headings=self.headings,
        )
        lr = self.cfg

        def per_param(name, _param):
            if name.endswith("_scale") and lr.lr_map_scale is not None:
                return {"lr": lr.lr_map_scale}
            return {"lr": lr.lr_map if name.startswith("map") else lr.lr_emission}

        self.optim = Adam(per_param)
        self.svi = SVI(self.model.map_model, self.guide, self.optim, loss=self.elbo)
        self.guide.params()  # create the map parameters now (checkpoints need them)
        self.checkpoint = None if checkpoint is None else Path(checkpoint)
        self.particles: Particles | None = None
        self.state: SLAMState | None = None
        self.pinned_poses: torch.Tensor | None = None  # [T, 3] set by pin_cache

    # --------------------------------------------------------------------------- helpers
    def map_mean(self, t: int | None = None):
        """The map belief the filter weighs with: mean and scale of ``q(M)``.

        Online (``t`` given, ``revisit_gap > 0``), cells first mapped less than ``revisit_gap``
        steps before ``t`` are masked: a map written from the last few poses repeats what
        odometry already says, and matching against it pulls the estimate back along the path;
        only revisits of older map regions (loop closures) correct drift.

        With ``revisit_radius = r`` instead, the whole particle cloud trusts the map by
        ``exp(-d^2 / (2 r^2))`` (at least 0.01), ``d`` the distance from the cloud's mean to the
        nearest position estimated at least ``revisit_gap`` steps before ``t``: flat weights
        (path integration) at the map's frontier, where the chart is a copy of the one behind,
        full weights where the agent is back on an old track -- one factor for all particles, so
        it does not pull them towards well-covered places.
        """
        loc, scale = self.guide.params()
        usable, trust = None, 1.0
        gap, radius = self.cfg.revisit_gap, self.cfg.revisit_radius
        if t is not None and radius is not None:
            trust = 0.01
            if t - gap > 0 and self.particles is not None:
                d2 = (self.track[: t - gap] - self.particles.mean()[:2]).pow(2).sum(-1).min()
                trust = max(math.exp(-0.5 * float(d2) / radius**2), 0.01)
        elif t is not None and gap > 0:
            usable = (t - self.first_seen >= gap).to(loc.dtype)
        return MapBelief(loc.detach(), scale.detach(), usable, trust)

    def _mean_cell(self) -> tuple[int, int]:
        """Grid cell (lower-left corner) of the particle cloud's mean position."""
        g, z = self.model.grid, self.particles.mean()
        w, h, _ = g.shape
        gx = (z[0] - g.origin[0]) * ((w - 1) / g.size[0])
        gy = (z[1] - g.origin[1]) * ((h - 1) / g.size[1])
        return int(gx.floor().clamp(0, w - 1)), int(gy.floor().clamp(0, h - 1))

    def _mark_seen(self, t: int) -> None:
        """Record the first time each grid cell near the pose estimate was mapped."""
        i0, j0 = self._mean_cell()
        block = self.first_seen[max(i0 - 1, 0) : i0 + 3, max(j0 - 1, 0) : j0 + 3]
        block.clamp_(max=t)

    def _svi_step(self, lo: int, hi: int, newest: int | None) -> float:
        """One SVI step on chunks starting in ``[lo, hi]`` (plus the chunk at ``newest``)."""
        C = self.cfg.chunks_per_batch
        n_rand = C - (newest is not None)
        starts = torch.randint(lo, hi + 1, (n_rand,), generator=self.gen)
        if newest is not None:
            starts = torch.cat([torch.tensor([newest]), starts])
        loss = self.svi.step(ChunkBatch(starts, self.cfg.chunk_length))
        self._hold_anchor()
        if not math.isfinite(loss):
            raise FloatingPointError(f"SVI loss became {loss} (step t={self.state.t})")
        return loss

    def _scan_points(self, t: int, z: torch.Tensor | None = None, hit_range: float | None = None):
        """Scan ``t`` placed from pose ``z [3]`` (default: the cloud's mean), as grid indices:
        the hits (those within ``hit_range`` of the sensor, if given) joined into a polyline
        (hits of neighbouring beams closer than ``ray_insert_gap`` are one wall, sampled at half
        a grid spacing) and the free space the beams cross (the four grid points around each
        point sampled along a beam, up to 1.5 grid spacings before its hit, or to the sensor's
        range for a miss). Returns two ``(i, j)`` pairs of ``[P]`` index tensors, ``hits`` and
        ``free``."""
        em, g = self.model.emission, self.model.grid
        x = self.obs[t]  # [B]
        valid = torch.ones_like(x, dtype=torch.bool) if self.mask is None else self.mask[t].bool()
        hit = (x < em.max_range * (1 - 1e-3)) & valid  # [B]
        z = self.particles.mean() if z is None else z  # [3]
        ang = z[2] + em.beam_angles.to(x.dtype)  # [B]
        u = torch.stack([ang.cos(), ang.sin()], -1)  # [B, 2]
        pts = z[:2] + x[:, None] * u  # [B, 2]
        w, h, _ = g.shape
        spacing = min(g.size[0] / (w - 1), g.size[1] / (h - 1))
        nxt = torch.roll(torch.arange(x.shape[0]), -1)  # [B] the neighbouring beam
        near = hit if hit_range is None else hit & (x <= hit_range)  # [B] hits written as walls
        seg = near & near[nxt] & ((pts[nxt] - pts).norm(dim=-1) < self.cfg.ray_insert_gap)  # [B]
        n = int(math.ceil(self.cfg.ray_insert_gap / (0.5 * spacing))) + 1
        f = torch.linspace(0, 1, n, dtype=x.dtype)[:, None, None]  # [n, 1, 1]
        on = pts[seg] + f * (pts[nxt][seg] - pts[seg])  # [n, S, 2] along joined pairs
        hits = torch.cat([pts[near], on.reshape(-1, 2)])  # [P, 2]
        free_margin = 1.5
        reach = torch.where(hit, (x - free_margin * spacing).clamp_min(0), x)[valid]  # [V]
        n = int(math.ceil(em.max_range / (0.5 * spacing))) + 1
        d = torch.linspace(0, 1, n, dtype=x.dtype)[:, None] * reach  # [n, V]
        free = (z[:2] + d[..., None] * u[valid]).reshape(-1, 2)  # [n * V, 2]

        def cells(p, corners=False):  # [P, 2] -> nearest grid points (i [P], j [P])
            c = [(p[:, k] - g.origin[k]) * ((m - 1) / g.size[k]) for k, m in enumerate((w, h))]
            if not corners:
                return tuple(ck.round().long().clamp(0, m - 1) for ck, m in zip(c, (w, h)))
            # the four grid points a bilinear read at p attends (free space: known around it)
            i0, j0 = c[0].floor().long(), c[1].floor().long()
            i = torch.cat([i0, i0 + 1, i0, i0 + 1]).clamp(0, w - 1)
            j = torch.cat([j0, j0, j0 + 1, j0 + 1]).clamp(0, h - 1)
            return i, j

        return cells(hits), cells(free, corners=True)

    def _write_map(self, i, j, value: float | torch.Tensor, scale: float | None) -> None:
        """Set q(M)'s mean (one value or ``[P]``; and scale, unless None) at grid points
        ``(i [P], j [P])``."""
        loc, _ = self.guide.params()
        with torch.no_grad():
            loc[i, j, 0] = value
            if scale is not None:
                # the store keeps the scale unconstrained (its log)
                raw = dict(pyro.get_param_store().named_parameters())[f"{self.guide.prefix}_scale"]
                raw[i, j, 0] = math.log(scale)

    def _insert_scan(self, t: int, z: torch.Tensor | None = None) -> None:
        """``ray_insert``: write the hits of scan ``t`` into q(M)'s mean, placed from pose
        ``z [3]`` (default: the cloud's mean), as a polyline (see :meth:`_scan_points`): every
        grid point nearest to it that no earlier scan hit gets the occupancy ``ray_insert``.
        Readings at the sensor's range are misses and write no wall, nor (with
        ``ray_insert_range``) do hits farther than that from the sensor. With ``ray_insert_free``,
        the grid points the beams cross that no scan wrote yet get that occupancy (a later hit
        overrides it)."""
        (i, j), (fi, fj) = self._scan_points(t, z, self.cfg.ray_insert_range)
        new = ~self.inserted[i, j]  # [P]
        i, j = i[new], j[new]
        self._write_map(i, j, self.cfg.ray_insert, self.cfg.ray_insert_scale)
        self.inserted[i, j] = True
        if self.cfg.ray_insert_free is not None:  # free space: where nothing was written yet
            new = ~self.inserted[fi, fj] & ~self.freed[fi, fj]
            fi, fj = fi[new], fj[new]
            self._write_map(fi, fj, self.cfg.ray_insert_free, self.cfg.ray_insert_scale)
            self.freed[fi, fj] = True

    def _anchor_scan(self, t: int) -> None:
        """``ray_anchor``: scan ``t`` (one of the first, at the known start) fixes q(M) where it
        saw walls (occupancy ``ray_insert``, 2 if unset) and free space (-1), with scale
        ``ray_anchor_scale``; :meth:`_hold_anchor` restores these cells after each SVI step.
        A wall seen by any anchor scan overrides free space seen by another."""
        (hi, hj), (fi, fj) = self._scan_points(t)
        free = torch.isnan(self.anchor[fi, fj]) | (self.anchor[fi, fj] < 0)
        self.anchor[fi[free], fj[free]] = -1.0
        self.anchor[hi, hj] = 2.0 if self.cfg.ray_insert is None else self.cfg.ray_insert
        self._hold_anchor()

    def _hold_anchor(self) -> None:
        """Write ``ray_anchor``'s cells back into q(M) (after an SVI step moved them)."""
        if not self.cfg.ray_anchor:
            return
        keep = ~torch.isnan(self.anchor)  # [w, h]
        if bool(keep.any()):
            i, j = keep.nonzero(as_tuple=True)
            self._write_map(i, j, self.anchor[i, j].to(self.obs.dtype), self.cfg.ray_anchor_scale)

    def _filter_step(self, t: int, M):
        x = self.obs[t]
        m = None if self.mask is None else self.mask[t]
        if t == 0:
            scale = self.model.init_scale
            z0 = self.init_pose + scale * torch.randn(
                self.cfg.filter_particles, 3, generator=self.gen, dtype=self.obs.dtype
            )
            self.particles, _ = self.pf.init(z0, M, x, m, step=0)
        else:
            sigma = self._heading_jumps(self._transition_sigma(M), t)
            self.particles, _ = self.pf.step(
                self.particles, M, x, self.ctl[t - 1], m, step=t, sigma=sigma,
                heading=self._heading(t),
            )  # fmt: skip
        self.cache.store(torch.tensor([t]), _batched(self.particles), self.gen)

    def _heading(self, t: int) -> HeadingObservation | None:
        """``wall_heading``: step ``t``'s heading observation (None: off, or no walls agree)."""
        if self.headings is None or torch.isnan(self.headings.value[t]):
            return None
        return self.headings.at(t)

    def _heading_jumps(self, sigma, t: int):
        """With ``heading_jump = (p, s)``, a heavy-tailed transition: each particle's heading
        noise is ``s`` with probability ``p`` (else ``sigma``'s), so a cloud that has become far
        narrower than its heading error can still reach the heading the map supports. With
        ``heading_jump_age = G > 0`` only at step ``t`` of a revisit (the cloud's mean on a cell
        first mapped at least ``G`` steps before ``t``): not at the map's frontier, where a
        young chart only repeats the last images. Returns ``sigma`` unchanged, or a per-particle
        std ``[K, 3]``."""
        if self.cfg.heading_jump is None:
            return sigma
        if self.cfg.heading_jump_age > 0:
            if not t - self.first_seen[self._mean_cell()] >= self.cfg.heading_jump_age:
                return sigma
        prob, std = self.cfg.heading_jump
        base = self.model.transition.sigma if sigma is None else sigma
        K = self.cfg.filter_particles
        out = base.reshape(-1, 3)[-1:].expand(K, 3).clone()  # [K, 3]
        jump = torch.rand(K, generator=self.gen) < prob  # [K]
        out[jump, 2] = std
        return out

    def _transition_sigma(self, M):
        """The filter's ``sigma_T`` for the next step (``None``: the model's). With
        ``transition_scale_trusted``, it moves linearly from the model's (scaled by
        ``transition_scale``) to the one scaled by ``transition_scale_trusted`` as the cloud's
        trust in the map belief ``M`` goes from 0 to 1: firm odometry at the frontier of the
        map, where a young chart copies the last scans and misleads the filter, and loose
        odometry (up to the actual residual of the transition) where the map is established.
        By default (``trusted_passes="online"``) only in the online sweep (also the one offline
        SLAM starts from): the offline filter passes run on a finished map that has no
        frontier, where the cloud trusts every chart, and keep the model's sigma_T unless
        ``trusted_passes`` is ``"final"`` (the last pass, which writes no map) or ``"all"``."""
        hi = self.cfg.transition_scale_trusted
        active = self.state is None or self.state.phase in TRUSTED_PASSES[self.cfg.trusted_passes]
        if hi is None or not isinstance(M, MapBelief) or not active:
            return None
        lo = self.model.transition.sigma  # [3], already scaled by transition_scale
        ratio = torch.tensor(hi, dtype=lo.dtype) / torch.tensor(self.cfg.transition_scale)
        hi = lo * ratio
        trust = self.pf.cloud_trust(self.particles, M)  # []
        return lo + trust * (hi - lo)

    # --------------------------------------------------------------------------- phases
    def _online(self, progress: bool):
        st, L = self.state, self.cfg.chunk_length
        bar = tqdm(total=self.T, initial=st.t, desc="online SLAM", disable=not progress)
        while st.t < self.T:
            t = st.t
            with torch.no_grad():
                self._filter_step(t, self.map_mean(t))
                self._mark_seen(t)
                if t < self.cfg.ray_anchor and st.phase == "online":
                    self._anchor_scan(t)
                self.track[t] = self.particles.mean()[:2]
            if st.phase == "online":
                st.estimates.append(self.particles.mean().tolist())
                st.stds.append(self.particles.std().tolist())
            else:  # offline SLAM's initial sweep: kept for diagnostics (result's "sweep_mean")
                st.sweep_estimates.append(self.particles.mean().tolist())
            tl = t - self.cfg.ray_insert_lag  # the scan written now (ray_insert_lag)
            if self.cfg.ray_insert is not None and tl >= 0:
                if self.pinned_poses is not None:  # pin_cache: the map is learned there
                    z = self.pinned_poses[tl].to(self.obs.dtype)
                elif self.cfg.ray_insert_smooth:  # its ancestors at tl, weighed at t
                    z = self.particles.smoothed(t - tl)
                else:  # the cloud's mean at step tl
                    est = st.estimates if st.phase == "online" else st.sweep_estimates
                    z = torch.tensor(est[tl], dtype=self.obs.dtype)
                self._insert_scan(tl, z)
            # the map is learned from the steps up to t - write_lag only: the filter then
            # matches a scan against what older steps wrote (a revisit), not against a copy of
            # its own latest scans written where it believes it is
            tw = t - self.cfg.write_lag
            if tw >= L - 1 and t % self.cfg.svi_every == 0:
                self.elbo.num_steps_seen = tw + 1
                for _ in range(self.cfg.svi_steps):
                    st.losses.append(self._svi_step(0, tw - L + 1, tw - L + 1))
                # the map at the agent's cells learns fast enough to inform the filter while it
                # is still there, without larger steps on the older cells
                for _ in range(self.cfg.newest_svi_steps):
                    self.svi.step(ChunkBatch(torch.tensor([tw - L + 1]), L))
                    self._hold_anchor()
            st.t += 1
            bar.update(1)
            if self.checkpoint and st.t % self.cfg.checkpoint_every == 0:
                self.save(self.checkpoint)
        bar.close()
        self.elbo.num_steps_seen = self.T

    def _filter_pass(self, progress: bool, desc: str):
        """Filter the whole traversal under the map mean (refreshes the cache)."""
        M = self.map_mean()
        means, stds = [], []
        with torch.no_grad():
            for t in tqdm(range(self.T), desc=desc, disable=not progress, leave=False):
                self._filter_step(t, M)
                means.append(self.particles.mean().tolist())
                stds.append(self.particles.std().tolist())
        return means, stds

    def _cache_pass(self, progress: bool, desc: str):
        """Offline poses as the paper's Appendix B-I filters them: the traversal in consecutive
        chunks of ``chunk_length`` steps, each started from its first step's cached particles
        (categorical over the cache, plus 1e-3 noise) and filtered under the map mean; no
        particles cross a chunk boundary and the cache is left as it is."""
        M, L, K = self.map_mean(), self.cfg.chunk_length, self.cfg.filter_particles
        means, stds = [], []
        with torch.no_grad():
            for s in tqdm(range(0, self.T, L), desc=desc, disable=not progress, leave=False):
                for t in range(s, min(s + L, self.T)):
                    m = None if self.mask is None else self.mask[t]
                    if t == s:  # [K, 3] from the cache
                        ts = torch.tensor([s])
                        z0 = self.cache.propose(ts, K, "categorical", generator=self.gen)[0]
                        z0 = z0.to(self.obs.dtype)
                        self.particles, _ = self.pf.init(z0, M, self.obs[t], m, step=t)
                    else:
                        self.particles, _ = self.pf.step(
                            self.particles, M, self.obs[t], self.ctl[t - 1], m, step=t,
                            sigma=self._transition_sigma(M), heading=self._heading(t),
                        )  # fmt: skip
                    means.append(self.particles.mean().tolist())
                    stds.append(self.particles.std().tolist())
        return means, stds

    def _offline(self, progress: bool):
        st, L = self.state, self.cfg.chunk_length
        if st.phase == "online-init":
            if self.cfg.offline_init == "online":
                self._online(progress)
            else:
                self._filter_pass(progress, "odometry pass")
            st.phase, st.t = "offline-svi", 0
            if self.checkpoint:
                self.save(self.checkpoint)
        while st.round < self.cfg.offline_rounds:
            if st.phase == "offline-filter":
                # a whole filter pass refreshes the cache; with "cache" only the SVI chunks do
                if self.cfg.offline_estimate == "forward":
                    self._filter_pass(progress, f"filter pass {st.round + 1}")
                st.phase, st.t = "offline-svi", 0
            n = self.cfg.offline_svi_steps
            bar = tqdm(
                total=n, initial=st.t, desc=f"offline SVI {st.round + 1}", disable=not progress
            )
            while st.t < n:
                st.losses.append(self._svi_step(0, self.T - L, None))
                st.t += 1
                bar.update(1)
                if self.checkpoint and st.t % self.cfg.checkpoint_every == 0:
                    self.save(self.checkpoint)
            bar.close()
            st.round += 1
            st.phase, st.t = "offline-filter", 0
            if self.checkpoint:
                self.save(self.checkpoint)
        st.phase = "offline-final"
        final = self._cache_pass if self.cfg.offline_estimate == "cache" else self._filter_pass
        st.estimates, st.stds = final(progress, "final filter pass")

    def run(self, mode: str = "online", progress: bool = True) -> dict:
        """Run (or, after :meth:`resume`, continue) SLAM. Returns :meth:`result`."""
        if mode not in ("online", "offline"):
            raise ValueError(f"mode must be 'online' or 'offline', got {mode!r}")
        if self.state is None:
            self.state = SLAMState(mode, phase="online" if mode == "online" else "online-init")
        elif self.state.phase == "done":  # resumed from the final checkpoint: nothing to redo
            return self.result()
        if mode == "online":
            self._online(progress)
        else:
            self._offline(progress)
        self.state.phase = "done"
        if self.checkpoint:
            self.save(self.checkpoint)
        return self.result()

    def result(self) -> dict:
        st = self.state
        return {
            "mean": np.asarray(st.estimates, dtype=np.float64).reshape(-1, 3),
            "std": np.asarray(st.stds, dtype=np.float64).reshape(-1, 3),
            "losses": np.asarray(st.losses),
            "map_loc": self.guide.params()[0].detach().numpy(),
            "map_scale": self.guide.params()[1].detach().numpy(),
            # offline from an online sweep: the sweep's pose means [T, 3] ([0, 3] otherwise)
            "sweep_mean": np.asarray(st.sweep_estimates, dtype=np.float64).reshape(-1, 3),
        }

    def pin_cache(self, poses, noise: float = 1e-3, seed: int = 0) -> None:
        """Diagnostic: the particle cache holds ``poses [T, 3]`` (+ ``noise`` std) from now on.

        Every later store (the online filter's, the ELBO chunks' refreshes, the offline
        passes') writes the given poses with fresh noise instead of its particles, so the map is
        learned at those poses (e.g. the ground truth or path integration) while the filter
        still localises against it. This separates "the filter cannot use the map" from "pose
        errors written into the map feed back into the filter"
        (``benchmarks/slam_accuracy.py --map-poses``, ``benchmarks/slam_trace.py``). With
        ``ray_insert``, the scans are written at the given poses too. The pin is not part of
        checkpoints: call it again after :meth:`resume`.
        """
        cache = self.cache
        poses = torch.as_tensor(np.asarray(poses), dtype=cache.z.dtype)
        if poses.shape != (self.T, 3):
            shape = tuple(poses.shape)
            raise ValueError(f"pin_cache needs poses of shape ({self.T}, 3), got {shape}")
        gen = torch.Generator().manual_seed(seed)
        self.pinned_poses = poses  # [T, 3] (ray_insert writes its scans there)

        def store(t, p, generator=None):  # [C] steps; the particles p are ignored
            eps = torch.randn(len(t), cache.num_particles, 3, generator=gen, dtype=poses.dtype)
            cache.z[t] = poses[t].unsqueeze(-2) + noise * eps
            cache.filled[t] = True

        cache.store = store

    # --------------------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict:
        return {
            "config": self.cfg.to_dict(),
            "state": copy.deepcopy(self.state.__dict__),
            "params": pyro.get_param_store().get_state(),
            "optim": self.optim.get_state(),
            "model": self.model.state_dict(),
            "cache": self.cache.state_dict(),
            "particles": None if self.particles is None else self.particles.__dict__,
            "gen": self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "elbo_seen": self.elbo.num_steps_seen,
            "first_seen": self.first_seen.clone(),
            "inserted": self.inserted.clone(),
            "anchor": self.anchor.clone(),
            "freed": self.freed.clone(),
            "track": self.track.clone(),
        }

    def save(self, path) -> None:
        """Atomic checkpoint (temp file + rename)."""
        buf = io.BytesIO()
        torch.save(self.state_dict(), buf)
        atomic_write(Path(path), lambda f: f.write(buf.getvalue()))

    def resume(self, path) -> SLAM:
        """Load a checkpoint written by :meth:`save`; :meth:`run` then continues from it."""
        d = torch.load(path, weights_only=False)
        pyro.get_param_store().set_state(d["params"])
        self.model.load_state_dict(d["model"])
        if self.model.learn_emission:
            # the store now holds *loaded* tensors: make the emission network use (and SVI
            # update) those, as it did before the checkpoint, not its own parameter copies
            pyro.module("emission", self.model.emission, update_module_params=True)
        self.guide.params()
        # run one no-op step to create optimiser slots, then load their state
        self.optim.set_state(d["optim"])
        self.cache.load_state_dict(d["cache"])
        self.particles = None if d["particles"] is None else Particles(**d["particles"])
        self.gen.set_state(d["gen"])
        torch.set_rng_state(d["torch_rng"])
        self.elbo.num_steps_seen = d["elbo_seen"]
        self.first_seen.copy_(d["first_seen"])
        if "inserted" in d:  # (checkpoints before ray_insert have none)
            self.inserted.copy_(d["inserted"])
        if "anchor" in d:  # (checkpoints before ray_anchor have none)
            self.anchor.copy_(d["anchor"])
            self.freed.copy_(d["freed"])
        if "track" in d:  # (checkpoints before revisit_radius have none)
            self.track.copy_(d["track"])
        self.state = SLAMState(**d["state"])
        return self


def _scan_spread(tr: Traversal) -> float:
    """Std of the valid observed ranges: the scale of scan predictions under the map prior."""
    obs = np.asarray(tr.observations, dtype=np.float64)
    valid = obs if tr.obs_mask is None else obs[np.asarray(tr.obs_mask, dtype=bool)]
    return float(np.std(valid)) if valid.size > 1 else 1.0


def _scan_range(tr: Traversal) -> float:
    """Largest valid observed reading: the width of the filter's uniform outlier density."""
    obs = np.asarray(tr.observations, dtype=np.float64)
    valid = obs if tr.obs_mask is None else obs[np.asarray(tr.obs_mask, dtype=bool)]
    valid = valid[np.isfinite(valid)]
    return float(valid.max()) if valid.size and valid.max() > 0 else 1.0


def _batched(p: Particles) -> Particles:
    return Particles(
        p.z.unsqueeze(0), p.logw.unsqueeze(0), None if p.scan is None else p.scan.unsqueeze(0)
    )


def path_integration(traversal: Traversal, transition: Transition, emission_scan=True):
    """Dead reckoning with a transition's mean from the start pose: ``[T, 3]`` (heading wrapped).

    Transitions that need a scan get the *observed* scan (what a pretrained transition saw).
    """
    from .geometry import wrap_angle

    obs, ctl, _, z = _tensors(traversal)
    out = [z]
    with torch.no_grad():
        for t in range(ctl.shape[0]):
            z = transition.mean(z, ctl[t], obs[t] if transition.needs_scan else None)
            out.append(z)
    poses = torch.stack(out)
    poses[:, 2] = wrap_angle(poses[:, 2])
    return poses.numpy().astype(np.float64)


def pretrain_emission(
    traversals,
    config: SLAMConfig,
    *,
    steps: int = 2000,
    batch_size: int = 256,
    lr_map: float = 0.05,
    lr_emission: float = 1e-3,
    seed: int = 0,
    progress: bool = True,
) -> tuple[Emission | EmissionMLP, dict]:
    """Fit ``mu_E`` on traversals with ground-truth poses (one map belief per traversal).

    Maximises ``E_q(M)[log p(x_t | z_t, M)] - KL(q(M) || p(M)) / T`` with the true poses
    ``z_t``; the maps are discarded and the emission network is returned, to be reused (frozen or
    fine-tuned) for SLAM in new mazes.
    """
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    models, params, data = [], [], []
    emission = None
    for tr in traversals:
        m, _ = build_model(tr, config, emission=emission)
        emission = m.emission
        loc = torch.zeros(m.grid.shape, requires_grad=True)
        log_scale = torch.zeros(m.grid.shape, requires_grad=True)
        obs, _, mask, _ = _tensors(tr)
        models.append(m)
        params += [loc, log_scale]
        data.append((obs, mask, torch.as_tensor(tr.poses, dtype=obs.dtype), loc, log_scale))
    opt = torch.optim.Adam(
        [{"params": params, "lr": lr_map}, {"params": emission.parameters(), "lr": lr_emission}]
    )
    prior = torch.distributions.Normal(0.0, 1.0)
    bar = tqdm(range(steps), desc="pretrain emission", disable=not progress)
    for _ in bar:
        loss = 0.0
        for m, (obs, mask, poses, loc, log_scale) in zip(models, data):
            T = obs.shape[0]
            idx = torch.randint(T, (batch_size,), generator=gen)
            q = torch.distributions.Normal(loc, log_scale.exp())
            M = q.rsample()
            mean = m.emission_mean(M, poses[idx])
            ll = m.emission_log_prob(obs[idx], mean, None if mask is None else mask[idx])
            kl = torch.distributions.kl_divergence(q, prior).sum()
            loss = loss - ll.mean() + kl / T
        opt.zero_grad()
        loss.backward()
        opt.step()
        bar.set_postfix(loss=f"{loss.item():.2f}")
    with torch.no_grad():
        m, (obs, mask, poses, loc, _) = models[0], data[0]
        rmse = (m.emission_mean(loc, poses) - obs).pow(2).mean().sqrt().item()
    if isinstance(emission, LidarEmission):  # the network (what the LiDAR checkpoints hold)
        emission = emission.net
    return emission, {"final_loss": loss.item(), "rmse_first_traversal": rmse}


def fit_map(
    traversal: Traversal,
    model: DVBFLM,
    poses=None,
    steps: int = 1000,
    *,
    batch_size: int = 256,
    lr: float = 0.05,
    seed: int = 0,
    progress: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mapping with known poses: fit the mean-field ``q(M)`` with the emission frozen.

    Maximises ``E_q(M)[log p(x_t | z_t, M)] - KL(q(M) || p(M)) / T`` (the loss of
    :func:`pretrain_emission`) by Adam on minibatches of time steps, with the poses ``z_t``
    given (default: the traversal's ground truth; pass e.g. a SLAM posterior mean instead).
    Returns ``(loc, scale)`` of ``q(M)``, each ``[w, h, D_m]`` (detached).
    """
    if poses is None:
        if traversal.poses is None:
            raise ValueError("fit_map needs poses (the traversal has no ground truth)")
        poses = traversal.poses
    gen = torch.Generator().manual_seed(seed)
    obs, _, mask, _ = _tensors(traversal)
    z = torch.as_tensor(np.asarray(poses), dtype=obs.dtype)
    loc = torch.zeros(model.grid.shape, requires_grad=True)
    log_scale = torch.zeros(model.grid.shape, requires_grad=True)
    opt = torch.optim.Adam([loc, log_scale], lr=lr)
    prior = torch.distributions.Normal(0.0, 1.0)
    for p in model.emission.parameters():
        p.requires_grad_(False)
    T = obs.shape[0]
    try:
        for _ in tqdm(range(steps), desc="fit map", disable=not progress):
            idx = torch.randint(T, (min(batch_size, T),), generator=gen)
            q = torch.distributions.Normal(loc, log_scale.exp())
            mean = model.emission_mean(q.rsample(), z[idx])
            ll = model.emission_log_prob(obs[idx], mean, None if mask is None else mask[idx])
            loss = -ll.mean() + torch.distributions.kl_divergence(q, prior).sum() / T
            opt.zero_grad()
            loss.backward()
            opt.step()
    finally:
        for p in model.emission.parameters():
            p.requires_grad_(True)
    return loc.detach(), log_scale.detach().exp()
