"""Baselines of PF-net's Table I (Karkus et al. 2018, Sec. V-B).

All take the batch dict of :mod:`pyro_slam.pfnet` and return ``{"estimates": [B, T, 3]}``:

* :func:`propagated_uncertainty` -- transition updates only (a :class:`~pyro_slam.pfnet.PFNet`
  without observation model).
* :class:`BeamModelPF` -- model-based particle filter with the beam model of Probabilistic
  Robotics / ROS AMCL: expected ranges ray-cast in the floor map (``simulators.raycast``), a
  mixture of hit / short / max / random per beam. :func:`tune_beam_model` grid-searches its
  parameters on (walls-only) training data.
* :class:`HistogramFilterNet` -- end-to-end histogram filter (Jonschkowski & Brock 2016): a
  discretised ``(heading, y, x)`` belief, translation by odometry + learned blur kernel as the
  convolutional transition, and a learned observation model producing a log-likelihood for every
  cell from map and observation features.
* :class:`LSTMNet` -- LSTM with map-localisation priors (paper's variant): each step crops the
  local map at the dead-reckoned pose, encodes map crop, observation and odometry, and outputs a
  robot-frame correction added to the pose.
"""

from __future__ import annotations

import itertools
import logging
import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from simulators import raycast

from ..geometry import odometry_delta, wrap_angle
from .model import (
    METRE,
    GaussianTransition,
    ImageEncoder,
    LidarEncoder,
    ObsModelConfig,
    PFNet,
    evaluate,
    local_map_crops,
)

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------
# Propagated uncertainty and the beam-model particle filter
# --------------------------------------------------------------------------------------------


def propagated_uncertainty(**kw) -> PFNet:
    """Transition-only filter: the error the initial uncertainty alone produces."""
    return PFNet(None, GaussianTransition(learn=False), **kw)


class _Identity(nn.Module):
    def encode_obs(self, obs):
        return obs


class BeamModelPF(PFNet):
    """Particle filter with the AMCL beam model on LiDAR scans (no learned parameters).

    ``log p(z | s) = sum_b log(z_hit N(z_b; r_b, sigma_hit) + z_short Exp_{<r_b}(z_b; lambda)
    + z_max [z_b >= max] + z_rand / max)`` with ``r_b`` ray-cast in the floor-map walls.
    """

    def __init__(
        self,
        z_hit=0.8,
        z_short=0.05,
        z_max=0.05,
        z_rand=0.1,
        sigma_hit=0.04,
        lambda_short=10.0,
        resample="ess",
    ):
        super().__init__(_Identity(), GaussianTransition(learn=False), resample=resample, alpha=1.0)
        self.params = dict(
            z_hit=z_hit,
            z_short=z_short,
            z_max=z_max,
            z_rand=z_rand,
            sigma_hit=sigma_hit,
            lambda_short=lambda_short,
        )

    def log_likelihood(self, batch, obs, particles, t):
        p = self.params
        B, K, _ = particles.shape
        rmax = batch["max_range"]
        angles = batch["beam_angles"].numpy()
        exp = np.empty((B, K, len(angles)))
        pn = particles.detach().numpy().astype(np.float64)
        for b in range(B):
            exp[b] = raycast(batch["walls"][b], pn[b, :, :2], pn[b, :, 2:3] + angles, rmax)
        r = torch.as_tensor(exp, dtype=obs.dtype)  # [B, K, n] expected ranges
        z = obs.unsqueeze(1)  # [B, 1, n]
        s = p["sigma_hit"]
        hit = torch.exp(-0.5 * ((z - r) / s) ** 2) / (s * math.sqrt(2 * math.pi))
        lam = p["lambda_short"]
        short = (z < r) * lam * torch.exp(-lam * z) / (1 - torch.exp(-lam * r)).clamp_min(1e-6)
        mx = (z >= rmax * 0.999).to(z.dtype)
        dens = p["z_hit"] * hit + p["z_short"] * short + p["z_max"] * mx + p["z_rand"] / rmax
        return torch.log(dens).sum(-1)  # [B, K]


def tune_beam_model(dataset, K=100, n_traj=40, progress=False):
    """Grid search of the beam model's mixture on ``dataset`` (LiDAR); returns the best params
    (lowest (x, y) RMSE) and the table of tried settings."""
    sub = dataset.subset(np.arange(min(n_traj, len(dataset)))).with_sensor("lidar")
    tried = []
    for sigma, z_hit in itertools.product((0.01, 0.02, 0.04), (0.5, 0.7, 0.9)):
        rest = 1 - z_hit
        prm = dict(sigma_hit=sigma, z_hit=z_hit, z_short=rest / 4, z_max=rest / 4, z_rand=rest / 2)
        tried.append((evaluate(BeamModelPF(**prm), sub, K=K), prm))
        if progress:
            log.info("beam model %s: %.1f cm", prm, tried[-1][0])
    return min(tried, key=lambda x: x[0])[1], tried


# --------------------------------------------------------------------------------------------
# Histogram filter network
# --------------------------------------------------------------------------------------------


class HistogramFilterNet(nn.Module):
    """End-to-end histogram filter over ``A`` headings x ``G x G`` positions.

    Args:
        obs_cfg: sensor description (an :class:`~pyro_slam.pfnet.ObsModelConfig`).
        grid: cells per side (the floor map is pooled to ``grid x grid``).
        headings: number of heading bins.
    """

    def __init__(self, obs_cfg: ObsModelConfig, grid: int = 16, headings: int = 16, ch=16):
        super().__init__()
        self.G, self.A, self.ch = grid, headings, ch
        self.map_cnn = nn.Sequential(
            nn.Conv2d(1, 16, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(16, 16, 3, padding=1),
            nn.ReLU(),
            nn.AdaptiveAvgPool2d(grid),
            nn.Conv2d(16, ch, 3, padding=1),
        )  # [B, ch, G, G]
        if obs_cfg.sensor == "lidar":
            n = len(obs_cfg.beam_angles)
            self.obs_enc = nn.Sequential(
                nn.Linear(n, 128), nn.ReLU(), nn.Linear(128, headings * ch)
            )
            self.obs_scale = obs_cfg.max_range
        else:
            h, w = obs_cfg.image_shape
            self.obs_enc = nn.Sequential(
                nn.Conv2d(1, 16, 3, padding=1),
                nn.ReLU(),
                nn.MaxPool2d(4),
                nn.Flatten(),
                nn.Linear(16 * (h // 4) * (w // 4), 128),
                nn.ReLU(),
                nn.Linear(128, headings * ch),
            )
            self.obs_scale = 1.0
        self.sensor = obs_cfg.sensor
        self.head = nn.Sequential(nn.ReLU(), nn.Conv2d(ch, 16, 1), nn.ReLU(), nn.Conv2d(16, 1, 1))
        # softmax -> transition noise kernels; start with 87 % (xy) / 96 % (heading) of the mass
        # on the centre, not uniform: a uniform 3x3 blur per step alone spreads the belief
        # wider than the propagated uncertainty (checked: 140 vs 86 cm without observations)
        self.blur_xy = nn.Parameter(torch.zeros(3, 3))
        self.blur_h = nn.Parameter(torch.zeros(3))
        with torch.no_grad():
            self.blur_xy[1, 1] = 4.0
            self.blur_h[1] = 4.0
        self.min_likelihood = 0.004

    def heading_centres(self):
        return -math.pi + (torch.arange(self.A) + 0.5) * 2 * math.pi / self.A  # [A]

    def initial_belief(self, mean, std, side):
        """Discretised Gaussian ``[B, A, G, G]`` (log probabilities)."""
        c = (torch.arange(self.G) + 0.5) * side / self.G
        lx = -0.5 * ((c[None] - mean[:, :1]) / std[0]) ** 2  # [B, G]
        ly = -0.5 * ((c[None] - mean[:, 1:2]) / std[1]) ** 2
        lh = -0.5 * (wrap_angle(self.heading_centres()[None] - mean[:, 2:]) / std[2]) ** 2
        logb = lh[:, :, None, None] + ly[:, None, :, None] + lx[:, None, None, :]
        return logb - torch.logsumexp(logb.flatten(1), -1)[:, None, None, None]

    def transition(self, logb, odom, side):
        """Shift every heading slice by the odometry, rotate headings, blur (learned)."""
        B = logb.shape[0]
        p = torch.exp(logb)  # [B, A, G, G]
        th = self.heading_centres()  # [A]
        c, s = torch.cos(th)[None], torch.sin(th)[None]
        dx = c * odom[:, :1] - s * odom[:, 1:2]  # [B, A] world units
        dy = s * odom[:, :1] + c * odom[:, 1:2]
        theta = torch.zeros(B * self.A, 2, 3)
        theta[:, 0, 0] = theta[:, 1, 1] = 1.0
        theta[:, 0, 2] = -(dx * 2 / side).reshape(-1)  # sample source = target - shift
        theta[:, 1, 2] = -(dy * 2 / side).reshape(-1)
        grid = F.affine_grid(theta, [B * self.A, 1, self.G, self.G], align_corners=False)
        p = F.grid_sample(p.reshape(B * self.A, 1, self.G, self.G), grid, align_corners=False)
        p = p.reshape(B, self.A, self.G, self.G)
        # heading rotation by dtheta: fractional circular shift along A
        shift = odom[:, 2] / (2 * math.pi / self.A)  # [B]
        lo = torch.floor(shift)
        frac = (shift - lo)[:, None, None, None]
        idx = (torch.arange(self.A)[None] - lo[:, None].long()) % self.A  # [B, A]
        p0 = torch.gather(p, 1, idx[:, :, None, None].expand_as(p))
        p1 = torch.gather(p, 1, ((idx - 1) % self.A)[:, :, None, None].expand_as(p))
        p = (1 - frac) * p0 + frac * p1
        # learned blur: 3x3 in xy, 3 in heading (circular)
        kxy = torch.softmax(self.blur_xy.flatten(), 0).reshape(1, 1, 3, 3)
        p = F.conv2d(p.reshape(B * self.A, 1, self.G, self.G), kxy, padding=1)
        p = p.reshape(B, self.A, self.G, self.G)
        kh = torch.softmax(self.blur_h, 0)
        p = kh[0] * p.roll(1, 1) + kh[1] * p + kh[2] * p.roll(-1, 1)
        return torch.log(p.clamp_min(1e-12))

    def log_likelihood(self, map_feat, obs):
        # map_feat [B, ch, G, G]; obs [B, ...] -> [B, A, G, G]
        B = obs.shape[0]
        x = obs / self.obs_scale
        if self.sensor != "lidar":
            x = x.unsqueeze(1)
        of = self.obs_enc(x).reshape(B, self.A, self.ch)  # [B, A, ch]
        h = map_feat[:, None] + of[..., None, None]  # [B, A, ch, G, G]
        logit = self.head(h.flatten(0, 1)).reshape(B, self.A, self.G, self.G)
        m = self.min_likelihood
        return torch.log(m + (1 - m) * torch.sigmoid(logit))

    def estimate(self, logb, side):
        p = torch.exp(logb)  # [B, A, G, G]
        c = (torch.arange(self.G) + 0.5) * side / self.G
        x = (p.sum((1, 2)) * c).sum(-1)
        y = (p.sum((1, 3)) * c).sum(-1)
        ph = p.sum((2, 3))  # [B, A]
        th = self.heading_centres()
        h = torch.atan2((ph * torch.sin(th)).sum(-1), (ph * torch.cos(th)).sum(-1))
        return torch.stack([x, y, h], -1)

    def forward(self, batch, K=None, generator=None):
        side = batch["map_side"]
        obs, odom = batch["obs"], batch["odom"]
        map_feat = self.map_cnn(batch["maps"])
        logb = self.initial_belief(batch["init_mean"], batch["init_std"], side)
        est = []
        for t in range(obs.shape[1]):
            if t > 0:
                logb = self.transition(logb, odom[:, t - 1], side)
            logb = logb + self.log_likelihood(map_feat, obs[:, t])
            logb = logb - torch.logsumexp(logb.flatten(1), -1)[:, None, None, None]
            est.append(self.estimate(logb, side))
        return {"estimates": torch.stack(est, 1)}


# --------------------------------------------------------------------------------------------
# LSTM network
# --------------------------------------------------------------------------------------------


class LSTMNet(nn.Module):
    """LSTM localiser with a local-map prior: pose ``s_t = (s_{t-1} (+) u_t) (+) delta_t``,
    ``delta_t`` = LSTM(map crop at ``s_{t-1} (+) u_t``, observation, odometry)."""

    def __init__(self, obs_cfg: ObsModelConfig, hidden: int = 128):
        super().__init__()
        self.cfg = obs_cfg
        crop = (obs_cfg.crop_size, obs_cfg.crop_half_extent, obs_cfg.crop_forward_offset)
        if obs_cfg.sensor == "lidar":
            self.obs_enc = LidarEncoder(obs_cfg.beam_angles, obs_cfg.max_range, crop)
        else:
            self.obs_enc = ImageEncoder(
                obs_cfg.image_shape,
                obs_cfg.column_angles,
                obs_cfg.depth_scale,
                obs_cfg.max_range,
                crop,
            )
        G = obs_cfg.crop_size // 4
        self.map_enc = nn.Sequential(
            nn.Conv2d(1, 8, 5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv2d(8, 16, 3, stride=2, padding=1),
            nn.ReLU(),
        )
        n_in = (16 + 16) * G * G + 3
        self.proj = nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU())
        self.lstm = nn.LSTMCell(hidden, hidden)
        self.out = nn.Linear(hidden, 3)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        self.register_buffer("scale", torch.tensor([0.3 * METRE, 0.3 * METRE, 0.3]))

    def forward(self, batch, K=None, generator=None):
        c = self.cfg
        obs, odom = batch["obs"], batch["odom"]
        B, T = obs.shape[:2]
        s = batch["init_mean"]
        h = torch.zeros(B, self.lstm.hidden_size)
        cell = torch.zeros_like(h)
        est = []
        for t in range(T):
            u = odom[:, t - 1] if t > 0 else torch.zeros(B, 3)
            s = odometry_delta(s, u)
            crop = local_map_crops(
                batch["maps"],
                s.detach()[:, None],
                batch["map_side"],
                c.crop_size,
                c.crop_half_extent,
                c.crop_forward_offset,
            )[:, 0]
            x = torch.cat(
                [
                    self.map_enc(crop.unsqueeze(1)).flatten(1),
                    self.obs_enc(obs[:, t]).flatten(1),
                    u / torch.tensor([0.1, 0.1, 1.0]),
                ],
                -1,
            )
            h, cell = self.lstm(self.proj(x), (h, cell))
            s = odometry_delta(s, torch.tanh(self.out(h)) * self.scale)
            est.append(s)
        return {"estimates": torch.stack(est, 1)}
