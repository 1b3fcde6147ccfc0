"""PF-net: Particle Filter Networks (Karkus, Hsu & Lee, CoRL 2018).

A differentiable particle filter whose transition and observation models are neural network
components, trained end-to-end (backpropagation through time) on the pose loss of eq. (10).

Pieces, top to bottom:

* :data:`METRE` -- the length scale. Mazes have side 1.0 and ``6 x 6`` cells, so a corridor is
  ``1/6`` wide; we read one corridor as one metre, i.e. **1 m = 1/6 maze units** and 30 cm =
  0.05 units. All losses are computed in metres (positions divided by ``METRE``) and RMSEs are
  reported in centimetres.
* :func:`rasterize_floor_map` -- occupancy grid of the wall segments (the floor map ``M``).
* :func:`local_map_crops` -- spatial transformer (``affine_grid`` + ``grid_sample``) that cuts,
  for every particle, the floor-map window seen from the particle's pose.
* :class:`ObservationModel` -- ``Z(o | s, M)`` of Fig. 5: CNN on the map crop, CNN on the
  observation (1-D for a LiDAR scan, 2-D for a depth image), a locally connected layer on the
  concatenated feature maps and an FC head to a scalar log-likelihood.
* :class:`PFNet` -- the filter: reparameterised Gaussian transition from robot-frame odometry
  (eq. 11), log-space weight update (eq. 5), soft resampling (eqs. 8-9, through
  :func:`pyro_slam.resampling.soft`) every step, ESS-triggered or never, weighted-mean estimate
  (eq. 2) with a circular mean for the heading.
* :func:`pose_loss`, :func:`train` -- eq. (10) and an RMSProp BPTT loop with fixed seeds, a tqdm
  progress bar and resumable checkpoints; :func:`evaluate` computes the (x, y) RMSE.

Every estimator in this module and in :mod:`pyro_slam.pfnet.baselines` takes a *batch* dict
(see :func:`pyro_slam.pfnet.data.PFNetDataset.batch`)::

    maps      [B, 1, H, W]   floor-map rasters (walls only; distractors are never on the map)
    map_side  float          world extent of the rasters (maps cover [0, side]^2)
    obs       [B, T, ...]    LiDAR [B, T, n_beams] or depth [B, T, h, w]
    odom      [B, T-1, 3]    robot-frame odometry (dx, dy, dtheta) from step t to t+1
    init_mean [B, 3]         centre of the initial belief
    init_std  [3]            std of the initial belief (x, y, heading)
    poses     [B, T, 3]      true poses (targets only; never read by the estimators)

and returns ``{"estimates": [B, T, 3], ...}``.
"""

from __future__ import annotations

import math
import os
import random
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from tqdm.auto import tqdm, trange

from ..geometry import odometry_delta, wrap_angle
from ..inference import resampling

METRE = 1.0 / 6.0  # maze units per metre: a 1/6-wide corridor of a 6x6-cell maze ~ 1 m
INIT_STD = (0.3 * METRE, 0.3 * METRE, math.radians(30.0))  # initial belief, paper's 30cm/30deg


# --------------------------------------------------------------------------------------------
# Floor map and spatial transformer
# --------------------------------------------------------------------------------------------


def rasterize_floor_map(
    walls: np.ndarray, side: float = 1.0, resolution: int = 64, thickness: float = 1.5
) -> np.ndarray:
    """Occupancy grid of wall segments, anti-aliased.

    Args:
        walls: ``[W, 4]`` segments ``(x1, y1, x2, y2)`` in ``[0, side]^2``.
        side: world extent; the raster covers ``[0, side]^2``.
        resolution: pixels per side.
        thickness: wall thickness in pixels.
    Returns:
        ``[resolution, resolution]`` float32 in [0, 1]; ``grid[i, j]`` is the cell at
        ``y = (i + 0.5) * side / resolution``, ``x = (j + 0.5) * side / resolution`` (row = y).
    """
    px = side / resolution
    c = (np.arange(resolution) + 0.5) * px
    X, Y = np.meshgrid(c, c)  # [R, R]; X varies along columns
    P = np.stack([X.ravel(), Y.ravel()], -1)  # [R*R, 2]
    walls = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
    if len(walls) == 0:
        return np.zeros((resolution, resolution), np.float32)
    a, b = walls[:, :2], walls[:, 2:]  # [W, 2]
    ab = b - a
    t = ((P[:, None, :] - a[None]) * ab[None]).sum(-1) / np.maximum((ab**2).sum(-1), 1e-12)
    t = np.clip(t, 0.0, 1.0)  # [R*R, W]
    closest = a[None] + t[..., None] * ab[None]  # [R*R, W, 2]
    d = np.sqrt(((P[:, None, :] - closest) ** 2).sum(-1)).min(-1) / px  # [R*R] in pixels
    occ = np.clip(thickness / 2 + 0.5 - d, 0.0, 1.0)
    return occ.reshape(resolution, resolution).astype(np.float32)


def crop_affine(
    poses: torch.Tensor, map_side: float, half_extent: float, forward_offset: float = 0.0
) -> torch.Tensor:
    """Affine matrices ``[N, 2, 3]`` for :func:`torch.nn.functional.affine_grid`.

    The output crop has normalised coordinates ``(u, v)`` in ``[-1, 1]^2``: column ``u`` runs
    along the robot's forward axis (``forward = forward_offset + half_extent * u``), row ``v``
    along its left axis (``left = half_extent * v``). The input normalised coordinates are
    ``2 * world / map_side - 1`` (map column = world x, map row = world y).
    """
    x, y, th = poses[..., 0], poses[..., 1], poses[..., 2]  # [N]
    c, s = torch.cos(th), torch.sin(th)
    k = 2.0 / map_side
    row0 = torch.stack(
        [k * half_extent * c, -k * half_extent * s, k * (x + c * forward_offset) - 1], -1
    )
    row1 = torch.stack(
        [k * half_extent * s, k * half_extent * c, k * (y + s * forward_offset) - 1], -1
    )
    return torch.stack([row0, row1], -2)  # [N, 2, 3]


def local_map_crops(
    maps: torch.Tensor,
    poses: torch.Tensor,
    map_side: float,
    size: int = 32,
    half_extent: float = 0.3,
    forward_offset: float = 0.1,
) -> torch.Tensor:
    """Local floor-map windows aligned with each particle's pose (spatial transformer).

    Args:
        maps: ``[B, 1, H, W]`` rasters covering ``[0, map_side]^2``.
        poses: ``[B, K, 3]`` particle poses.
        size: crop side in pixels.
        half_extent: half the crop side in world units.
        forward_offset: crop centre ahead of the robot (world units).
    Returns:
        ``[B, K, size, size]``; column index = forward, row index = left. Outside the map is 0.
    """
    B, K, _ = poses.shape
    theta = crop_affine(poses.reshape(B * K, 3), map_side, half_extent, forward_offset)
    grid = F.affine_grid(theta, [B * K, 1, size, size], align_corners=False)  # [BK, S, S, 2]
    grid = grid.reshape(B, K * size, size, 2)
    crops = F.grid_sample(maps, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return crops.reshape(B, K, size, size)  # [B, K, S, S]


# --------------------------------------------------------------------------------------------
# Observation encoders and the observation model
# --------------------------------------------------------------------------------------------


def crop_cell_polar(size: int, half_extent: float, forward_offset: float):
    """Robot-frame polar coordinates ``(rho, phi)`` ``[S, S]`` of the local-map crop's cells.

    Same layout as :func:`local_map_crops`: column = forward, row = left.
    """
    c = (2 * torch.arange(size, dtype=torch.float32) + 1) / size - 1  # cell centres in [-1, 1]
    fwd = forward_offset + half_extent * c[None, :]  # [1, S]
    left = half_extent * c[:, None]  # [S, 1]
    fwd, left = torch.broadcast_tensors(fwd, left)
    return torch.hypot(fwd, left), torch.atan2(left, fwd)


class ScanTopDown(nn.Module):
    """Parameter-free projection of a range scan into the local-map crop frame.

    Each crop cell looks up the beam whose direction is nearest to the cell's bearing and gets
    three channels: *hit* (Gaussian in ``rho - range``, only for returns below ``max_range``),
    *free* (``rho`` before the return) and *seen* (the bearing lies within a beam's sector).
    This is the geometric prior that lets the observation model compare the scan with the
    map crop cell by cell; everything downstream is learned.

    Args:
        beam_angles: beam directions relative to the heading ``[n_beams]`` (rad).
        max_range: readings ``>= max_range`` are "no return".
    """

    def __init__(self, beam_angles, max_range, size, half_extent, forward_offset):
        super().__init__()
        a = torch.as_tensor(np.asarray(beam_angles), dtype=torch.float32)  # [n]
        rho, phi = crop_cell_polar(size, half_extent, forward_offset)  # [S, S]
        diff = wrap_angle(phi.reshape(-1, 1) - a.reshape(1, -1)).abs()  # [S*S, n]
        d, idx = diff.min(-1)
        spacing = wrap_angle(torch.diff(a, append=a[:1] + 2 * math.pi)).abs().min()
        self.register_buffer("idx", idx)  # [S*S] nearest beam per cell
        self.register_buffer("seen", (d <= spacing / 2 + 1e-6).float())  # [S*S]
        self.register_buffer("rho", rho.reshape(-1))  # [S*S]
        self.max_range, self.size = float(max_range), size
        self.sigma = 2 * half_extent / size  # one cell

    def forward(self, ranges: torch.Tensor) -> torch.Tensor:
        r = ranges[:, self.idx]  # [N, S*S]
        valid = (r < self.max_range * 0.999).float()
        hit = torch.exp(-0.5 * ((self.rho - r) / self.sigma) ** 2) * valid * self.seen
        free = torch.sigmoid((r - self.rho) / self.sigma) * self.seen
        out = torch.stack([hit, free, self.seen.expand_as(hit)], 1)  # [N, 3, S*S]
        return out.reshape(-1, 3, self.size, self.size)


def _crop_cnn(c_in: int, channels: int) -> nn.Sequential:
    """``[N, c_in, S, S] -> [N, channels, S/4, S/4]``."""
    return nn.Sequential(
        nn.Conv2d(c_in, 8, 5, stride=2, padding=2),
        nn.ReLU(),
        nn.Conv2d(8, channels, 3, stride=2, padding=1),
        nn.ReLU(),
    )


class LidarEncoder(nn.Module):
    """LiDAR scan ``[N, n_beams]`` -> ``[N, C, G, G]``: top-down projection + 2-D CNN, plus a
    1-D CNN branch (circular padding) on the raw scan mapped to the grid by an FC layer."""

    def __init__(self, beam_angles, max_range, crop, channels: int = 8):
        super().__init__()
        size, half, off = crop
        n = len(beam_angles)
        self.grid, self.channels, self.max_range = size // 4, channels, max_range
        self.topdown = ScanTopDown(beam_angles, max_range, size, half, off)
        self.cnn = _crop_cnn(3, channels)
        self.conv1d = nn.Sequential(
            nn.Conv1d(1, 8, 5, padding=2, padding_mode="circular"),
            nn.ReLU(),
        )
        self.fc = nn.Linear(8 * n, channels * self.grid**2)

    def forward(self, scan: torch.Tensor) -> torch.Tensor:
        g = self.grid
        h1 = self.cnn(self.topdown(scan))  # [N, C, G, G]
        h2 = self.fc(self.conv1d((scan / self.max_range).unsqueeze(1)).flatten(1))
        return torch.cat([h1, F.relu(h2).reshape(-1, self.channels, g, g)], 1)  # [N, 2C, G, G]


class ImageEncoder(nn.Module):
    """Depth image ``[N, h, w]`` (values = z-depth / ``depth_scale``) -> ``[N, 2C, G, G]``.

    Branch 1: the horizon rows give a virtual laser scan over the camera's field of view
    (``range = z / cos(column angle)``), projected top-down (:class:`ScanTopDown`) + 2-D CNN.
    Branch 2: a 2-D CNN over the whole image, mapped to the grid by an FC layer.
    """

    def __init__(self, image_shape, column_angles, depth_scale, max_range, crop, channels=8):
        super().__init__()
        size, half, off = crop
        self.grid, self.channels = size // 4, channels
        self.depth_scale, self.max_range = depth_scale, max_range
        self.register_buffer("cos", torch.cos(torch.as_tensor(column_angles, dtype=torch.float32)))
        self.topdown = ScanTopDown(column_angles, max_range, size, half, off)
        self.cnn = _crop_cnn(3, channels)
        self.conv = nn.Sequential(
            nn.Conv2d(1, 16, 3, padding=1),
            nn.ReLU(),
            nn.MaxPool2d(2),
            nn.Conv2d(16, 16, 3, padding=1),
            nn.ReLU(),
            nn.MaxPool2d(2),
        )
        h, w = image_shape
        self.fc = nn.Linear(16 * (h // 4) * (w // 4), channels * self.grid**2)

    def virtual_scan(self, img: torch.Tensor) -> torch.Tensor:
        h = img.shape[-2]
        z = img[:, h // 2 - 1 : h // 2 + 1].mean(1) * self.depth_scale  # [N, w]
        return torch.clamp(z / self.cos, max=self.max_range)

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        g = self.grid
        h1 = self.cnn(self.topdown(self.virtual_scan(img)))
        h2 = F.relu(self.fc(self.conv(img.unsqueeze(1)).flatten(1)))
        return torch.cat([h1, h2.reshape(-1, self.channels, g, g)], 1)


class MapEncoder(nn.Module):
    """CNN over local map crops ``[N, S, S]`` -> ``[N, C, S/4, S/4]``."""

    def __init__(self, channels: int = 16):
        super().__init__()
        self.net = _crop_cnn(1, channels)

    def forward(self, crops: torch.Tensor) -> torch.Tensor:
        return self.net(crops.unsqueeze(1))


class LocallyConnected(nn.Module):
    """Per-location linear map ("locally fully connected", LFC) of ``[N, C_in, G, G]``.

    Split into a map part and an observation part (the layer is linear in the concatenation),
    so the observation half is computed once per sequence and broadcast over particles.
    """

    def __init__(self, c_map: int, c_obs: int, c_out: int, grid: int):
        super().__init__()
        P = grid * grid
        self.w_map = nn.Parameter(torch.randn(P, c_out, c_map) / math.sqrt(c_map + c_obs))
        self.w_obs = nn.Parameter(torch.randn(P, c_out, c_obs) / math.sqrt(c_map + c_obs))
        self.bias = nn.Parameter(torch.zeros(P, c_out))

    def forward(self, map_feat: torch.Tensor, obs_feat: torch.Tensor) -> torch.Tensor:
        # map_feat [B, K, Cm, G, G], obs_feat [B, Co, G, G] -> [B, K, G*G*c_out]
        hm = torch.einsum("bkmp,pcm->bkpc", map_feat.flatten(-2), self.w_map)  # [B, K, P, c]
        ho = torch.einsum("bop,pco->bpc", obs_feat.flatten(-2), self.w_obs)  # [B, P, c]
        return F.relu(hm + ho.unsqueeze(1) + self.bias).flatten(-2)


@dataclass
class ObsModelConfig:
    sensor: str = "lidar"  # "lidar" | "depth"
    beam_angles: tuple = tuple(2 * math.pi * i / 20 for i in range(20))  # LiDAR, rel. heading
    max_range: float = 0.53  # LiDAR range; also caps the depth camera's virtual scan
    image_shape: tuple = (24, 32)
    column_angles: tuple = tuple(math.pi / 4 - (c + 0.5) * math.pi / 2 / 32 for c in range(32))
    depth_scale: float = 0.53  # depth image value 1 = this z-depth (world units)
    crop_size: int = 32
    crop_half_extent: float = 0.3  # world units (~1.8 m)
    crop_forward_offset: float = 0.1
    map_channels: int = 16
    obs_channels: int = 8
    lfc_channels: int = 8
    min_likelihood: float = 0.004  # f = min + (1 - min) * sigmoid(.): bounded log-likelihood


class ObservationModel(nn.Module):
    """Learned ``log Z(o | s, M)`` for a batch of particles (Fig. 5 of the paper)."""

    def __init__(self, cfg: ObsModelConfig | None = None, **kw):
        super().__init__()
        cfg = cfg or ObsModelConfig(**kw)
        self.cfg = cfg
        G = cfg.crop_size // 4
        crop = (cfg.crop_size, cfg.crop_half_extent, cfg.crop_forward_offset)
        if cfg.sensor == "lidar":
            self.obs_enc = LidarEncoder(cfg.beam_angles, cfg.max_range, crop, cfg.obs_channels)
        elif cfg.sensor == "depth":
            self.obs_enc = ImageEncoder(
                cfg.image_shape,
                cfg.column_angles,
                cfg.depth_scale,
                cfg.max_range,
                crop,
                cfg.obs_channels,
            )
        else:
            raise ValueError(f"unknown sensor {cfg.sensor!r}")
        self.map_enc = MapEncoder(cfg.map_channels)
        self.lfc = LocallyConnected(cfg.map_channels, 2 * cfg.obs_channels, cfg.lfc_channels, G)
        self.head = nn.Sequential(
            nn.Linear(G * G * cfg.lfc_channels, 32), nn.ReLU(), nn.Linear(32, 1)
        )

    def crops(self, maps, particles, map_side):
        c = self.cfg
        return local_map_crops(
            maps, particles, map_side, c.crop_size, c.crop_half_extent, c.crop_forward_offset
        )

    def encode_obs(self, obs: torch.Tensor) -> torch.Tensor:
        """Observation features ``[B, C, G, G]``, computed once per step for all particles."""
        return self.obs_enc(obs)

    def forward(self, obs_feat, maps, particles, map_side) -> torch.Tensor:
        """Log-likelihoods ``[B, K]`` of observation features ``obs_feat`` at ``particles``."""
        B, K, _ = particles.shape
        crops = self.crops(maps, particles, map_side)  # [B, K, S, S]
        mf = self.map_enc(crops.reshape(B * K, *crops.shape[-2:]))  # [BK, Cm, G, G]
        h = self.lfc(mf.reshape(B, K, *mf.shape[1:]), obs_feat)  # [B, K, G*G*c]
        logit = self.head(h).squeeze(-1)  # [B, K]
        m = self.cfg.min_likelihood
        return torch.log(m + (1 - m) * torch.sigmoid(logit))


# --------------------------------------------------------------------------------------------
# The particle filter network
# --------------------------------------------------------------------------------------------


def sample_initial_particles(
    mean: torch.Tensor, std, K: int, generator: torch.Generator | None = None
) -> torch.Tensor:
    """``K`` particles ``~ N(mean, diag(std^2))`` per row: mean ``[B, 3]`` -> ``[B, K, 3]``."""
    std = torch.as_tensor(std, dtype=mean.dtype)
    eps = torch.randn(mean.shape[0], K, 3, generator=generator, dtype=mean.dtype)
    p = mean.unsqueeze(1) + eps * std
    return torch.cat([p[..., :2], wrap_angle(p[..., 2:])], -1)


def weighted_pose_mean(particles: torch.Tensor, log_weights: torch.Tensor) -> torch.Tensor:
    """Eq. (2) with a circular mean for the heading: ``[B, K, 3], [B, K] -> [B, 3]``."""
    w = torch.exp(resampling.normalize(log_weights)).unsqueeze(-1)  # [B, K, 1]
    xy = (w * particles[..., :2]).sum(-2)  # [B, 2]
    h = torch.atan2(
        (w[..., 0] * torch.sin(particles[..., 2])).sum(-1),
        (w[..., 0] * torch.cos(particles[..., 2])).sum(-1),
    )
    return torch.cat([xy, h.unsqueeze(-1)], -1)


class GaussianTransition(nn.Module):
    """Eq. (11): ``s' ~ N(s (+) u, diag(sigma_t, sigma_t, sigma_r)^2)`` (reparameterised).

    ``u`` is the robot-frame odometry ``(dx, dy, dtheta)``, turned into the global frame of each
    particle by :func:`pyro_slam.geometry.odometry_delta`. The standard deviations are
    learnable when ``learn=True`` (the paper set them by hand).
    """

    def __init__(self, sigma_t: float = 0.1 * METRE, sigma_r: float = math.radians(5), learn=True):
        super().__init__()
        raw = torch.log(torch.expm1(torch.tensor([sigma_t, sigma_r])))  # softplus^-1
        self.raw_sigma = nn.Parameter(raw, requires_grad=learn)

    @property
    def sigma(self) -> torch.Tensor:
        return F.softplus(self.raw_sigma)  # [2]: (translation, rotation)

    def forward(self, particles, odom, generator=None):
        # particles [B, K, 3], odom [B, 3] -> [B, K, 3]
        mean = odometry_delta(particles, odom.unsqueeze(1).expand_as(particles))
        s = self.sigma
        std = torch.stack([s[0], s[0], s[1]])
        eps = torch.randn(particles.shape, generator=generator, dtype=particles.dtype)
        p = mean + eps * std
        return torch.cat([p[..., :2], wrap_angle(p[..., 2:])], -1)


class PFNet(nn.Module):
    """Differentiable particle filter with learned observation model (PF-net).

    Args:
        obs_model: an :class:`ObservationModel` (or any module with ``encode_obs`` and
            ``forward(obs_feat, maps, particles, map_side) -> [B, K]`` log-likelihoods); ``None``
            runs transition-only filtering ("propagated uncertainty").
        transition: a :class:`GaussianTransition` (default: learnable, 10 cm / 5 deg).
        resample: ``"never"`` (the paper's training setting), ``"always"`` or ``"ess"``.
        alpha: soft-resampling trade-off of eq. (8); ``1`` = ordinary multinomial resampling.
        ess_threshold: resample a sequence when ``ESS < ess_threshold * K`` (``"ess"`` mode).
    """

    def __init__(
        self,
        obs_model: nn.Module | None,
        transition: GaussianTransition | None = None,
        resample: str = "ess",
        alpha: float = 0.5,
        ess_threshold: float = 0.5,
    ):
        super().__init__()
        if resample not in ("never", "always", "ess"):
            raise ValueError(f"resample must be never/always/ess, got {resample!r}")
        self.obs_model = obs_model
        self.transition = transition or GaussianTransition()
        self.resample, self.alpha, self.ess_threshold = resample, alpha, ess_threshold

    def log_likelihood(self, batch, obs_feat, particles, t):
        return self.obs_model(obs_feat, batch["maps"], particles, batch["map_side"])

    def resample_step(self, particles, log_weights, generator=None):
        """Soft resampling (eqs. 8-9) of all, or of low-ESS, rows: -> (particles, log_weights)."""
        if self.resample == "never":
            return particles, log_weights
        idx, new_lw = resampling.soft(log_weights, self.alpha, generator)
        new_p = resampling.gather_particles(particles, idx)  # [B, K, 3]
        if self.resample == "always":
            return new_p, new_lw
        K = log_weights.shape[-1]
        do = (resampling.ess(log_weights) < self.ess_threshold * K).unsqueeze(-1)  # [B, 1]
        return torch.where(do.unsqueeze(-1), new_p, particles), torch.where(do, new_lw, log_weights)

    def forward(self, batch: dict, K: int = 30, generator: torch.Generator | None = None) -> dict:
        """Filter a batch of sequences.

        Returns ``{"estimates": [B, T, 3], "particles": [B, K, 3], "log_weights": [B, K]}``
        (the last two at the final step).
        """
        obs, odom = batch["obs"], batch["odom"]  # [B, T, ...], [B, T-1, 3]
        T = obs.shape[1]
        particles = sample_initial_particles(batch["init_mean"], batch["init_std"], K, generator)
        log_w = torch.full(particles.shape[:2], -math.log(K), dtype=particles.dtype)  # [B, K]
        estimates = []
        for t in range(T):
            if t > 0:
                particles = self.transition(particles, odom[:, t - 1], generator)
            if self.obs_model is not None:
                feat = self.obs_model.encode_obs(obs[:, t])
                log_w = resampling.normalize(log_w + self.log_likelihood(batch, feat, particles, t))
                resampling.check_weights(log_w, t)
            estimates.append(weighted_pose_mean(particles, log_w))
            if t < T - 1:
                particles, log_w = self.resample_step(particles, log_w, generator)
        return {
            "estimates": torch.stack(estimates, 1),
            "particles": particles,
            "log_weights": log_w,
        }


# --------------------------------------------------------------------------------------------
# Loss, training, evaluation
# --------------------------------------------------------------------------------------------


def pose_loss(estimates: torch.Tensor, poses: torch.Tensor, beta: float = 0.1) -> torch.Tensor:
    """Eq. (10), averaged over batch and time: position MSE in m^2 + ``beta`` * heading^2."""
    dxy = (estimates[..., :2] - poses[..., :2]) / METRE
    dh = wrap_angle(estimates[..., 2] - poses[..., 2])
    return ((dxy**2).sum(-1) + beta * dh**2).mean()


def rmse_cm(estimates: torch.Tensor, poses: torch.Tensor) -> float:
    """RMSE of the (x, y) components over all sequences and steps, in centimetres."""
    d = (estimates.detach()[..., :2] - poses[..., :2]) / METRE * 100.0
    return float(torch.sqrt((d**2).sum(-1).mean()))


@dataclass
class TrainConfig:
    epochs: int = 10
    batch_size: int = 8
    lr: float = 1e-3
    K: int = 30  # particles during training
    beta: float = 0.1
    seed: int = 0
    grad_clip: float = 10.0
    max_seconds: float | None = None  # stop (after the current epoch's step) past this budget
    progress: bool = True
    history: list = field(default_factory=list)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)  # noqa: NPY002 (legacy global RNG, for third-party code)
    torch.manual_seed(seed)


def _epoch_generator(seed: int, epoch: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed * 100_003 + epoch)


def save_checkpoint(path, model, optimizer, epoch: int, cfg: TrainConfig, extra=None) -> None:
    """Atomically write model / optimizer state, the number of finished epochs and the config."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "epoch": epoch,
        "config": asdict(cfg),
        "extra": extra or {},
    }
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def train(
    model: nn.Module,
    dataset,
    cfg: TrainConfig,
    checkpoint: str | os.PathLike | None = None,
    resume: bool = True,
    desc: str = "train",
) -> TrainConfig:
    """End-to-end BPTT training with RMSProp on the pose loss (eq. 10).

    ``dataset`` must provide ``len()`` and ``batch(indices, init_generator)`` (see
    :class:`pyro_slam.pfnet.data.PFNetDataset`). Each epoch shuffles with a generator seeded
    by ``(seed, epoch)``, which also draws the initial beliefs, the particle noise and the
    resampling, so a run resumed from the checkpoint of epoch ``e`` repeats the uninterrupted
    run exactly. The checkpoint is written after every epoch. Returns ``cfg`` with
    ``cfg.history`` (mean loss per epoch) filled in.
    """
    optimizer = torch.optim.RMSprop([p for p in model.parameters() if p.requires_grad], lr=cfg.lr)
    start = 0
    if checkpoint is not None and resume and Path(checkpoint).exists():
        try:  # tensors and plain data only: a file can never run code
            state = torch.load(checkpoint, weights_only=True)
        except Exception as e:
            raise ValueError(f"{checkpoint}: not a PF-net training checkpoint ({e})") from None
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        start = state["epoch"]
        cfg.history = list(state["config"].get("history", []))
    t0 = time.monotonic()
    n = len(dataset)
    steps = math.ceil(n / cfg.batch_size)
    bar = tqdm(total=(cfg.epochs - start) * steps, desc=desc, disable=not cfg.progress, leave=False)
    for epoch in range(start, cfg.epochs):
        g = _epoch_generator(cfg.seed, epoch)
        order = torch.randperm(n, generator=g)
        model.train()
        total = 0.0
        for i in range(steps):
            batch = dataset.batch(order[i * cfg.batch_size : (i + 1) * cfg.batch_size], g)
            out = model(batch, K=cfg.K, generator=g)
            loss = pose_loss(out["estimates"], batch["poses"], cfg.beta)
            optimizer.zero_grad()
            loss.backward()
            if cfg.grad_clip:
                nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            optimizer.step()
            total += loss.item()
            bar.update(1)
            bar.set_postfix(epoch=epoch, loss=f"{loss.item():.3f}")
        cfg.history.append(total / steps)
        if checkpoint is not None:
            save_checkpoint(checkpoint, model, optimizer, epoch + 1, cfg)
        if cfg.max_seconds is not None and time.monotonic() - t0 > cfg.max_seconds:
            break
    bar.close()
    return cfg


def pretrain_observation_model(
    obs_model: nn.Module,
    dataset,
    steps: int = 300,
    batch_size: int = 32,
    candidates: int = 16,
    lr: float = 1e-3,
    seed: int = 0,
    progress: bool = False,
) -> list:
    """Warm start for ``obs_model`` before end-to-end training (optional, not in the paper).

    Per step: pick ``batch_size`` random (trajectory, time) pairs, draw ``candidates - 1``
    poses from the initial-belief Gaussian around the true pose, and minimise the softmax
    cross-entropy of the true pose among the candidates' log-likelihoods -- i.e. a one-step
    particle-filter weight update that should put its mass on the truth. Returns the losses.
    """
    g = torch.Generator().manual_seed(seed)
    opt = torch.optim.RMSprop(obs_model.parameters(), lr=lr)
    losses = []
    for _ in trange(steps, desc="pretrain obs", disable=not progress, leave=False):
        idx = torch.randint(len(dataset), (batch_size,), generator=g)
        b = dataset.batch(idx, g)
        T = b["poses"].shape[1]
        t = torch.randint(T, (batch_size,), generator=g)
        rows = torch.arange(batch_size)
        pose, obs = b["poses"][rows, t], b["obs"][rows, t]  # [N, 3], [N, ...]
        cand = sample_initial_particles(pose, b["init_std"], candidates, g)  # [N, C, 3]
        cand[:, 0] = pose
        ll = obs_model(obs_model.encode_obs(obs), b["maps"], cand, b["map_side"])  # [N, C]
        loss = -torch.log_softmax(ll, -1)[:, 0].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return losses


@torch.no_grad()
def evaluate(model: nn.Module, dataset, K: int = 300, batch_size: int = 25, seed: int = 1234):
    """(x, y) RMSE in cm of ``model`` on ``dataset`` with ``K`` particles (fixed seed)."""
    model.eval()
    g = torch.Generator().manual_seed(seed)
    est, true = [], []
    idx = torch.arange(len(dataset))
    for i in range(0, len(dataset), batch_size):
        batch = dataset.batch(idx[i : i + batch_size], None)
        est.append(model(batch, K=K, generator=g)["estimates"])
        true.append(batch["poses"])
    return rmse_cm(torch.cat(est), torch.cat(true))
