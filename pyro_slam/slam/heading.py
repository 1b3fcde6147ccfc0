"""The data side of the Manhattan-world heading factor (not the paper's model,
:class:`~pyro_slam.model.WallHeading`): the wall directions the scans show, their noise, and the
estimate of the walls' frame that sets its guide (:class:`~pyro_slam.model.FrameGuide`).

Where the walls run along two perpendicular axes, each scan's straight walls give the heading up
to a quarter turn: the walls' frame ``phi`` minus the scan's wall direction (from LiDAR ranges,
:func:`~pyro_slam.geometry.wall_direction`, or from a camera frame's wall edges,
:func:`~pyro_slam.geometry.image_wall_direction`). Nothing about the world is assumed beyond
that:

* **the frame** ``phi`` is a global latent of the model; its guide ``q(phi)`` is estimated
  from the data: from the first scans with a straight wall, each paired with the heading that
  odometry integrates from the known start, weighted by how little odometry has drifted by
  then; and refined online with the filter's posterior headings (the filter weighs with the
  evidence marginalised over ``q(phi)``, so its uncertainty widens the observation's std);
* **the tolerance** within which wall segments agree, and the observation's std, fit the
  sensor's noise, estimated from the scans themselves (:func:`~pyro_slam.geometry.range_noise`):
  a segment of length ``L`` has a direction error of about ``sqrt(2) sigma_r / L``;
* **odometry's heading drift** shows in the same wall directions: between two supported scans
  their heading change disagrees with odometry's by the drift in between plus the two scans'
  errors, so the disagreement's growth with the gap is the drift per step, which sets a real
  log's transition std on the heading (:func:`odometry_heading_noise`);
* the observation applies only where a scan **supports** it (a straight wall of at least three
  hits, and at least ``support`` agreeing segments), with an exact proposal
  (:class:`~pyro_slam.inference.HeadingProposal`);
* with a noise-free sensor a straight run of hits gives its wall's direction exactly and the
  observation is Gaussian; where the scans show range noise a segment may be a false wall
  (clutter, people, glass), and the observation is a mixture with an outlier component (the
  emission's ``outlier_prob``), so a scan whose walls disagree with the frame barely moves the
  particles.
"""

from __future__ import annotations

import math

import torch

from ..data import Traversal
from ..geometry import (
    image_background,
    image_wall_direction,
    range_noise,
    wall_direction,
    wrap_angle,
)
from ..io.common import odometry_poses
from ..model import FrameGuide, HeadingEvidence, WallHeading
from .build import prepare_traversal, traversal_tensors
from .config import HeadingConfig, SLAMConfig

QUARTER = math.pi / 2
FRAME_SCANS = 50  # at most this many early scans estimate the frame
NOISY = 1e-4  # range noise above this fraction of the median reading: outliers are possible
DRIFT_GAPS = 8  # odometry's heading drift: fitted over scan pairs 1 .. 8 steps apart
DRIFT_PAIRS = 20  # ... each gap with at least this many pairs of supported scans


class ManhattanHeading:
    """The wall directions of a prepared traversal's scans (``obs [T, N]``, ``mask``) and the
    guide of the walls' frame (``self.frame``, a :class:`~pyro_slam.model.FrameGuide`).

    Args:
        config: the :class:`~pyro_slam.slam.config.HeadingConfig` (``sigma``: the std floor;
            ``support``: agreeing segments needed).
        image: camera frames (the walls' edges) instead of LiDAR ranges.
        outlier_prob: the outlier component's weight where the scans show range noise (the
            filter's); a noise-free sensor's observation is Gaussian.
    """

    def __init__(
        self,
        traversal: Traversal,
        obs,
        mask,
        config: HeadingConfig,
        image: bool,
        outlier_prob: float = 0.0,
    ):
        angles = torch.as_tensor(traversal.beam_angles, dtype=obs.dtype)
        self.noise, self.outlier_prob = 0.0, 0.0
        if image:  # the walls' edges in each frame
            frames = obs.reshape(obs.shape[0], *traversal.metadata["image_shape"])  # [T, H, W]
            columns = angles.reshape(frames.shape[1:])[0]  # [W] column bearings
            direction, support = image_wall_direction(
                frames, columns, image_background(frames), config.sigma
            )
            std = torch.zeros_like(direction)
        else:
            wall = self._lidar(traversal, obs, mask, angles, config)
            direction, support = wall.direction, wall.support
            # the sensor's noise through the agreeing segments' lengths, or their own scatter
            std = torch.maximum(
                math.sqrt(2) * self.noise / wall.length2.clamp_min(1e-30).sqrt(), wall.scatter
            )
        if not image and self.noise > NOISY * float(obs[mask].median()):  # false walls possible
            self.outlier_prob = float(outlier_prob)
        self.direction = direction  # [T] in [0, pi / 2)
        self.ok = support >= config.support  # [T]
        self.sigma = std.clamp_min(config.sigma)  # [T] the observation's std
        self.frame = FrameGuide()  # (:meth:`estimate_frame`)

    def estimate_frame(self, traversal: Traversal, drift: float) -> None:
        """Set the frame guide from the first supported scans (:meth:`_initial_frame`), with
        ``drift`` the transition's heading std per step (rad), which weighs the early scans."""
        self.frame = FrameGuide(*self._initial_frame(traversal, drift))

    def _lidar(self, traversal, obs, mask, angles, config: HeadingConfig):
        """Wall directions of the scans, with the agreement tolerance fitted to the noise."""
        max_range = float(traversal.max_range)
        self.noise = range_noise(obs, angles, max_range, mask)
        tol = config.sigma
        if self.noise > 0:  # 2 stds of a segment as long as the beams' spacing at mid range
            spacing = float((angles[1:] - angles[:-1]).abs().median()) if len(angles) > 1 else 1.0
            typical = 0.5 * max_range * spacing
            tol = max(tol, 2 * math.sqrt(2) * self.noise / typical)
        return wall_direction(obs, angles, max_range, mask, min(tol, QUARTER / 4))

    def _initial_frame(self, traversal: Traversal, drift: float) -> tuple[float, float]:
        """The walls' frame from the first supported scans: each gives ``y_t`` = odometry
        heading plus wall direction (modulo a quarter turn) = ``phi + w_t + e_t``, with
        odometry's drift ``w_t`` a random walk (step std ``drift``) from the known start
        (``w_0 = 0``) and ``e_t`` the scan's error (std ``sigma_t``). A Kalman filter run
        backwards in time, from the last of those scans to the first step, ends at ``phi``
        (mean and variance)."""
        steps = torch.nonzero(self.ok).flatten()[:FRAME_SCANS]
        if not len(steps):
            return float("nan"), float("inf")
        odometry = odometry_poses(traversal, traversal.start_pose)  # [T, 3] in SLAM's frame
        heading = torch.as_tensor(odometry[:, 2], dtype=self.direction.dtype)
        y = heading[steps] + self.direction[steps]  # [n] phi + drift, modulo a quarter turn
        y = y[0] + wrap_angle(y - y[0], QUARTER)  # unwrapped about the first
        sigma2 = self.sigma[steps] ** 2
        mean, var, t = float(y[-1]), float(sigma2[-1]), int(steps[-1])
        for k in range(len(steps) - 2, -1, -1):
            var += (t - int(steps[k])) * drift**2  # back to step steps[k]
            gain = var / (var + float(sigma2[k]))
            mean, var, t = mean + gain * (float(y[k]) - mean), (1 - gain) * var, int(steps[k])
        var += t * drift**2  # the drift at step 0 is zero: the level there is the frame
        return float(torch.remainder(torch.tensor(mean), QUARTER)), var

    def odometry_drift(self, odometry_heading, max_gap: int = DRIFT_GAPS) -> float | None:
        """The odometry's heading noise per step (rad), read from the scans' wall directions.

        Between supported scans ``k`` steps apart, the change of the heading the walls give
        minus the change of odometry's heading (``odometry_heading [T]``, rad), modulo a quarter
        turn, has mean 0 and variance ``2 sigma_obs^2 + k sigma_drift^2`` when odometry's heading
        error is a random walk, as the transition says: a line fitted to the robust second
        moments about 0 (``(1.4826 median |v|)^2``) over ``k = 1 .. max_gap`` has slope
        ``sigma_drift^2`` whatever the wall directions' own noise, which sets the intercept. A
        heading bias in the odometry, which the transition does not model, grows the moments as
        ``k^2`` and so widens the std that covers it. None where some gap has fewer than
        ``DRIFT_PAIRS`` pairs or the slope is not positive (no drift the scans can see)."""
        d, ok = self.direction.double(), self.ok
        heading = torch.as_tensor(odometry_heading, dtype=torch.float64)  # [T]
        var = []
        for k in range(1, max_gap + 1):
            a = torch.nonzero(ok[:-k] & ok[k:]).flatten()
            if len(a) < DRIFT_PAIRS:
                return None
            v = wrap_angle(d[a] - d[a + k] - (heading[a + k] - heading[a]), QUARTER)
            var.append((1.4826 * v.abs().median()) ** 2)  # about 0: a bias counts as drift
        y = torch.stack(var)  # [max_gap]
        k = torch.arange(1, max_gap + 1, dtype=torch.float64)
        slope = ((k - k.mean()) * (y - y.mean())).sum() / ((k - k.mean()) ** 2).sum()
        return math.sqrt(float(slope)) if slope > 0 else None

    def factor(self) -> WallHeading:
        """The model's heading factor for these scans (outliers only where they show noise)."""
        return WallHeading(QUARTER, self.outlier_prob)

    def evidence(self) -> HeadingEvidence:
        """The wall directions ``direction [T]`` (nan where a scan supports none), their std
        ``[T]`` and the frame guide's mean and variance."""
        d = torch.where(self.ok, self.direction, torch.full_like(self.direction, math.nan))
        return HeadingEvidence(d, self.sigma, self.frame.mean, self.frame.var)

    def refine(self, t: int, heading: float, heading_std: float) -> None:
        """Refine ``q(phi)`` with step ``t``'s posterior heading (mean and std): ``heading +
        direction`` (modulo a quarter turn) observes the frame with variance ``sigma_t^2 +
        heading_std^2``; one scalar Kalman update of the frame's mean and variance."""
        f = self.frame
        if not bool(self.ok[t]) or math.isnan(f.mean):
            return
        v = float(self.sigma[t]) ** 2 + heading_std**2
        r = float(wrap_angle(heading + float(self.direction[t]) - f.mean, QUARTER))
        gain = f.var / (f.var + v)
        f.mean = float(torch.remainder(torch.tensor(f.mean + gain * r), QUARTER))
        f.var *= 1 - gain

    def state_dict(self) -> dict:
        return self.frame.state_dict()

    def load_state_dict(self, d: dict) -> None:
        self.frame.load_state_dict(d)


def odometry_heading_noise(traversal: Traversal, config: SLAMConfig) -> float | None:
    """The odometry's heading noise per step (rad) of a LiDAR log, from its scans' wall
    directions as ``config`` reads them (beam stride, range clip, the heading factor's
    settings; :meth:`ManhattanHeading.odometry_drift`); None without the heading factor, for
    camera frames, or where the scans show too few straight walls to tell."""
    if config.heading is None or config.emission.observation == "image":
        return None
    tr = prepare_traversal(traversal, config)
    obs, _, mask, _ = traversal_tensors(tr)
    outliers = config.emission.outlier_prob
    walls = ManhattanHeading(tr, obs, mask, config.heading, image=False, outlier_prob=outliers)
    return walls.odometry_drift(odometry_poses(tr, tr.start_pose)[:, 2])
