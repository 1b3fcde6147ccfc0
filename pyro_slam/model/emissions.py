"""Emissions: the observation mean ``mu_E`` of DVBF-LM as a function of the map and the pose.

An :class:`Emission` maps chart ``m_t`` and pose ``z_t`` to a predicted observation, flattened
to ``[..., N]`` (``event_shape`` gives its structure):

* :class:`LidarEmission` -- the paper's: :class:`~pyro_slam.model.networks.EmissionMLP`, then
  :func:`rotate_scan` (the "rotational shift of the beam outputs w.r.t. heading") to the beams;
* :class:`ImageEmission` -- the paper's visual one: chart ``[k angular bins x l rows]`` rotated
  with the heading and cropped to the camera's field of view, then row-wise MLPs (Appendix B-D).

Geometric alternatives (not the paper's) read the map along rays instead of at the pose:
:class:`RayEmission` (LiDAR ranges volume-rendered through an occupancy map) and
:class:`RayImageEmission` (a pinhole camera drawing the walls those rays hit).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from ..geometry import interleave
from .networks import EmissionMLP


def rotate_scan(
    world_scan: torch.Tensor, heading: torch.Tensor, beam_angles: torch.Tensor
) -> torch.Tensor:
    """Read a world-frame profile at body-frame beam directions.

    Args:
        world_scan: ``[..., n]`` values at world angles ``2 pi j / n``.
        heading: ``[...]`` agent headings (rad, any range).
        beam_angles: ``[B]`` beam directions relative to the heading (rad).
    Returns:
        ``[..., B]``: beam ``i`` reads the profile at world angle ``heading + beam_angles[i]``,
        linearly interpolated between the two nearest world directions (wrapping around).
    """
    n = world_scan.shape[-1]
    f = torch.remainder(heading.unsqueeze(-1) + beam_angles, 2 * math.pi) * (n / (2 * math.pi))
    i0 = torch.floor(f)
    a = f - i0  # [..., B]
    i0 = i0.long().remainder(n)
    i1 = (i0 + 1).remainder(n)
    batch = torch.broadcast_shapes(world_scan.shape[:-1], i0.shape[:-1])
    ws = world_scan.expand(*batch, n)
    i0 = i0.expand(*batch, i0.shape[-1])
    i1 = i1.expand(*batch, i1.shape[-1])
    return torch.lerp(ws.gather(-1, i0), ws.gather(-1, i1), a.expand_as(i0).to(ws.dtype))


class Emission(nn.Module):
    """The observation mean ``mu_E`` of DVBF-LM as a function of the chart and the pose.

    Subclasses set ``map_dim`` (``D_m``, the features per map cell the chart carries) and
    ``event_shape`` (the structure of one observation) and implement :meth:`mean`. Observations
    are handled flattened, ``[..., N]`` with ``N = prod(event_shape)``, so that the model, the
    particle filter and the ELBO treat every sensor alike (a diagonal Gaussian over ``N``).
    """

    map_dim: int
    event_shape: tuple[int, ...]
    # how unknown a reading is (read_moments) is the variance of the first trust_features
    # features of the chart at the pose (None: all of them)
    trust_features: int | None = None
    # the width of the interval a reading lies in (a range finder's range, a pixel's [0, 1]):
    # a reading the map does not determine is taken as uniform over it (read_moments)
    reading_range: float = 1.0
    # whether the reading's mean depends on the reading itself (an end-point model): the model
    # then passes the observation to read / read_moments where there is one
    reads_observation: bool = False

    @property
    def event_size(self) -> int:
        return math.prod(self.event_shape)

    def mean(self, m: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Chart ``m [..., D_m]``, pose ``z [..., 3]`` -> predicted observation ``[..., N]``."""
        raise NotImplementedError

    def read(self, grid, M: torch.Tensor, z: torch.Tensor, x=None) -> torch.Tensor:
        """Predicted observation at poses ``z [..., 3]`` from the map ``M [w, h, D_m]`` on
        ``grid`` (a :class:`~pyro_slam.model.MapGrid`): ``[..., N]``. The paper's read-out, the
        default: the chart ``f_m(z_t, M)`` (bilinear attention at the position), then
        :meth:`mean`. An emission that reads the map elsewhere (:class:`RayEmission`)
        overrides this. ``x [..., N]``: the observation, read only where
        :attr:`reads_observation` (:class:`EndPointEmission`)."""
        return self.mean(grid.attend(M, z[..., :2]), z)

    def read_moments(
        self, grid, loc: torch.Tensor, scale: torch.Tensor, z: torch.Tensor, variance=None, x=None
    ):
        """The reading at poses ``z [..., 3]`` under a Gaussian map belief, mean ``loc`` and
        std ``scale`` relative to the prior's (``[w, h, D_m]``; ``variance``: ``scale ** 2``
        where the caller keeps it, or None; ``x``: the observation, as :meth:`read`):
        ``(mean [..., N], v)`` with ``v`` how unknown the
        reading is, in ``[0, 1]``: the chart's variance relative to the prior's (``[..., 1]``,
        the same for every entry), which :meth:`~pyro_slam.model.DVBFLM.marginal_emission`
        turns into a variance."""
        n = self.trust_features
        var = grid.relative_variance(scale if n is None else scale[..., :n], z[..., :2])
        return self.read(grid, loc, z), var


class LidarEmission(Emission):
    """LiDAR read-out: world-frame range profile ``net(m)`` read at ``heading + beam_angles``.

    ``forward(m)`` is the world-frame profile (``[..., n_world]``); :meth:`mean` the body-frame
    scan ``[..., B]``.
    """

    def __init__(self, net: EmissionMLP, beam_angles):
        super().__init__()
        self.net = net
        self.map_dim = net.map_dim
        angles = torch.as_tensor(beam_angles, dtype=torch.get_default_dtype())
        self.register_buffer("beam_angles", angles, persistent=False)
        self.event_shape = (int(angles.shape[0]),)

    @property
    def n_world(self) -> int:
        return self.net.n_world

    @property
    def scale(self) -> float:
        return self.net.scale

    @property
    def reading_range(self) -> float:
        return float(self.net.scale)

    def forward(self, m: torch.Tensor) -> torch.Tensor:
        return self.net(m)

    def mean(self, m, z):
        return rotate_scan(self.net(m), z[..., 2], self.beam_angles)


class RayEmission(Emission):
    """Geometric LiDAR read-out: each beam's expected range through a density map.

    Not the paper's emission, an alternative with the same interface: the map holds
    ``D_m = 1`` feature per cell, an occupancy logit ``o = gain * M + offset`` (so that the prior
    mean ``M = 0`` is nearly free space and ``M ~ 1-2`` a wall). Along each beam, ``samples``
    points at ``d_s = (s + 1/2) * max_range / samples`` read ``o`` bilinearly; the density
    ``density * softplus(o)`` (per unit length) gives the probability that the ray stops in each
    segment (volume rendering), and the expected range is ``sum_s P(stop in s) d_s`` plus
    ``max_range`` times the probability that it passes. Differentiable in ``M``; a scan then
    constrains every cell its beams cross, not only the charts at the pose, so a new position is
    localised against walls mapped from earlier ones.

    Args:
        beam_angles: ``[B]`` beam directions relative to the heading (rad).
        max_range: the sensor's range (a ray that stops nowhere reads this).
        samples: points per beam.
        density, gain, offset: density per unit length ``density * softplus(gain * M + offset)``.
        tolerance: the transmittance below which :meth:`read_moments` stops marching a beam on
            a single map (the rest of the march moves its range by less than ``tolerance *
            max_range``); 0: every beam is marched over the full range.
    """

    map_dim = 1
    block = 32  # points per block of the march that stops beams early

    def __init__(
        self,
        beam_angles,
        max_range: float,
        samples: int = 48,
        density: float = 100.0,
        gain: float = 8.0,
        offset: float = -8.0,
        tolerance: float = 0.0,
    ):
        super().__init__()
        self.tolerance = float(tolerance)
        angles = torch.as_tensor(beam_angles, dtype=torch.get_default_dtype())
        self.register_buffer("beam_angles", angles, persistent=False)
        self.event_shape = (int(angles.shape[0]),)
        self.max_range, self.samples = float(max_range), int(samples)
        self.density, self.gain, self.offset = float(density), float(gain), float(offset)
        step = self.max_range / self.samples
        self.register_buffer("dist", (torch.arange(self.samples) + 0.5) * step, persistent=False)

    def mean(self, m, z):
        raise TypeError("RayEmission reads the map along its beams: use read(grid, M, z)")

    @staticmethod
    def wall_map(grid, walls, wall: float = 2.0, free: float = -1.0, width: float = 0.5):
        """A map ``[w, h, 1]`` of known walls (an oracle map, for tests and diagnostics): ``wall``
        at grid points within ``width`` grid spacings of a segment of ``walls [W, 4]`` (x0, y0,
        x1, y1), ``free`` elsewhere."""
        w, h = grid.cells
        xs = grid.origin[0] + torch.arange(w, dtype=torch.float64) * (grid.size[0] / (w - 1))
        ys = grid.origin[1] + torch.arange(h, dtype=torch.float64) * (grid.size[1] / (h - 1))
        p = torch.stack(torch.meshgrid(xs, ys, indexing="ij"), -1)  # [w, h, 2]
        seg = torch.as_tensor(walls, dtype=torch.float64).reshape(-1, 1, 1, 4)  # [W, 1, 1, 4]
        a, ab = seg[..., :2], seg[..., 2:] - seg[..., :2]
        t = (((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-12)).clamp(0, 1)
        d = (p - a - t.unsqueeze(-1) * ab).norm(dim=-1).amin(0)  # [w, h] distance to a wall
        near = d < width * grid.size[0] / (w - 1)
        out = torch.where(near, torch.tensor(wall), torch.tensor(free))
        return out.to(torch.get_default_dtype()).unsqueeze(-1)

    def stops(self, grid, M: torch.Tensor, z: torch.Tensor):
        """Points ``[..., B, S, 2]`` along the beams at poses ``z [..., 3]``, the probability
        that each beam stops in each segment ``[..., B, S]`` and that it passes ``[..., B]``.
        Only feature 0 of ``M`` (the occupancy logit) is read."""
        (x, y), stop, passes = self._march(grid, M, z)
        return interleave(x, y), stop, passes

    def _march(self, grid, M: torch.Tensor, z: torch.Tensor):
        """:meth:`stops` with the points as their coordinates ``(x, y)``, each ``[..., B, S]``."""
        d = self.dist.to(z.dtype)  # [S]
        ang = z[..., 2:3] + self.beam_angles.to(z.dtype)  # [..., B]
        x = (d * torch.cos(ang).unsqueeze(-1)).add_(z[..., 0:1, None])  # [..., B, S]
        y = (d * torch.sin(ang).unsqueeze(-1)).add_(z[..., 1:2, None])
        o = grid.read(M[..., :1], x, y)[..., 0]  # [..., B, S] occupancy logit
        step = self.max_range / self.samples
        tau = nn.functional.softplus(o.mul_(self.gain).add_(self.offset)).mul_(self.density * step)
        cum = tau.cumsum(-1)  # optical depth up to the end of each segment
        # transmittance before s x absorbed in s
        stop = (torch.exp(tau - cum) * torch.expm1(tau.neg())).neg_()
        return (x, y), stop, torch.exp(-cum[..., -1])

    def _range(self, grid, M: torch.Tensor, z: torch.Tensor):
        """Each beam's expected range and the probability that it passes, both ``[..., B]``."""
        _, stop, passes = self._march(grid, M, z)
        return (stop * self.dist.to(z.dtype)).sum(-1) + passes * self.max_range, passes

    def expected_range(self, grid, M: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Each beam's expected range ``[..., B]`` (the LiDAR reading)."""
        return self._range(grid, M, z)[0]

    def read(self, grid, M, z, x=None):
        return self.expected_range(grid, M, z)

    @property
    def reading_range(self) -> float:
        return self.max_range

    def read_moments(self, grid, loc, scale, z, variance=None, x=None):
        """Each beam's expected range under ``loc`` and how unknown it is, both ``[..., B]``,
        from one march along the beams: the occupancy's variance relative to the prior's
        (``scale``) where the ray stops under ``loc``, averaged over the stopping point
        (passing rays: the last point). A beam that ends on a mapped wall is known even where
        the pose is new; one that runs into unmapped space is not."""
        if self.tolerance > 0 and loc.dim() == 3:
            var = scale[..., :1] ** 2 if variance is None else variance[..., :1]
            return self._early_moments(grid, loc, var, z)
        pts, stop, passes = self._march(grid, loc, z)  # ([..., B, S] x 2), [..., B, S], [..., B]
        var = grid.read_variance(scale[..., :1], *pts)[..., 0]  # [..., B, S] occupancy's
        rng = (stop * self.dist.to(z.dtype)).sum(-1) + passes * self.max_range
        return rng, (stop * var).sum(-1) + passes * var[..., -1]

    def _early_moments(self, grid, loc, var, z):
        """:meth:`read_moments` on one map ``loc [w, h, D]`` (relative variance ``var [w, h,
        1]``), marched in blocks of :attr:`block` points, each beam dropped once its
        transmittance is below :attr:`tolerance`: the same sums over the points before that (a
        dropped beam's passing term is its transmittance there, read at its last point)."""
        ang = z[..., 2:3] + self.beam_angles.to(z.dtype)  # [..., B]
        shape = ang.shape
        xy = z[..., :2].unsqueeze(-2).expand(*shape, 2).reshape(-1, 2)
        ray = torch.cat([xy, torch.cos(ang).reshape(-1, 1), torch.sin(ang).reshape(-1, 1)], -1)
        # each live beam's optical depth so far and its sums of P(stop) d and P(stop) v so far
        acc = z.new_zeros(ray.shape[0], 3)  # [A, 3]
        live = torch.arange(ray.shape[0])
        out = z.new_zeros(ray.shape[0], 2)  # each beam's range and variance, once dropped
        dist, scale = self.dist.to(z.dtype), self.density * self.max_range / self.samples
        for s0 in range(0, self.samples, self.block):
            s1 = min(s0 + self.block, self.samples)
            d = dist[s0:s1]  # [L]
            x = torch.addcmul(ray[:, 0:1], ray[:, 2:3], d)  # [A, L]
            y = torch.addcmul(ray[:, 1:2], ray[:, 3:4], d)
            o = grid.read(loc[..., :1], x, y)[..., 0]
            tau = nn.functional.softplus(o.mul_(self.gain).add_(self.offset))
            cum = tau.mul_(scale).cumsum(-1).add_(acc[:, :1])
            stop = (torch.exp(tau - cum) * torch.expm1(tau.neg())).neg_()  # as in _march
            v = grid.read_variance(var, x, y, squared=True)[..., 0]  # [A, L]
            sums = torch.stack([(stop * d).sum(-1), (stop * v).sum(-1)], -1)
            acc = torch.cat([cum[:, -1:], acc[:, 1:] + sums], -1)
            t_end = torch.exp(-acc[:, 0])  # [A] transmittance past the block
            last = s1 == self.samples
            drop = torch.ones_like(t_end, dtype=torch.bool) if last else t_end < self.tolerance
            if bool(drop.any()):
                gone = drop.nonzero()[:, 0]
                ends = torch.stack([t_end[gone] * self.max_range, t_end[gone] * v[gone, -1]], -1)
                out[live[gone]] = acc[gone, 1:] + ends
                kept = (~drop).nonzero()[:, 0]
                live, ray, acc = live[kept], ray[kept], acc[kept]
                if not len(live):
                    break
        return out[:, 0].reshape(shape), out[:, 1].reshape(shape)


@dataclass(frozen=True)
class WallRamp:
    """How a ray-cast map's occupancy logit varies across a wall: linear in the signed distance
    ``d`` to it (grid spacings, positive behind it), from the free level ``free`` at ``d =
    -half_width - shift`` to the wall level ``wall`` at ``d = half_width - shift``, constant
    beyond (``shift``: puts the volume-rendered range of a wall seen head-on on the wall). What
    fusion insertion writes (:mod:`pyro_slam.slam.insertion`) and what
    :class:`EndPointEmission` reads a distance from."""

    wall: float
    free: float
    half_width: float
    shift: float = 0.0

    def loc(self, d: torch.Tensor) -> torch.Tensor:
        """The logit at signed distance ``d [...]`` (grid spacings): ``[...]``."""
        f = ((d + self.shift + self.half_width) / (2 * self.half_width)).clamp(0, 1)
        return self.free + f * (self.wall - self.free)

    def distance(self, m: torch.Tensor) -> torch.Tensor:
        """The signed distance (grid spacings) that the logit ``m [...]`` says, clamped to the
        ramp: ``[...]``, the inverse of :meth:`loc` on it."""
        f = ((m - self.free) / (self.wall - self.free)).clamp(0, 1)
        return f * (2 * self.half_width) - self.half_width - self.shift


class EndPointEmission(RayEmission):
    """Likelihood-field LiDAR emission (Thrun, Burgard and Fox, *Probabilistic Robotics*, 6.4:
    the end-point model), a second, stated model of the ranges beside :class:`RayEmission`.

    It reads the same occupancy map, as a signed distance through its :class:`WallRamp`
    ``ramp``: a reading ``x_b`` of beam ``b`` places its end point ``e_b = p + x_b u_b`` (the
    pose's position ``p``, the beam's world direction ``u_b``), and the map's distance there,
    ``d_b = s * ramp.distance(M(e_b))`` (grid spacing ``s``), is the reading's error: the
    emission's mean given the reading is ``x_b - d_b``, so that the model's Gaussian noise
    scores ``N(d_b; 0, sigma_E)``, Thrun's likelihood field (with the model's beam mixture). A
    reading at the sensor's range (a miss) is uninformative. Unlike the ray march, the mean
    depends on the reading itself (:attr:`reads_observation`), and a beam costs two bilinear
    reads (mean and variance at its end point) instead of a march along it. Without a reading
    (prediction, sampling) the emission is the ray march's expected range, the mode of the
    end-point model at a wall seen head-on; the two differ where a beam meets a wall at a
    grazing angle (the field's distance is the nearest wall's, not the range along the beam).

    Args:
        as :class:`RayEmission`, and ``ramp``: the map's :class:`WallRamp` (set before use).
    """

    reads_observation = True

    def __init__(self, beam_angles, max_range: float, ramp: WallRamp | None = None, **rays):
        super().__init__(beam_angles, max_range, **rays)
        self.ramp = ramp

    def _end_points(self, z: torch.Tensor, x: torch.Tensor):
        """The end points' coordinates ``(x, y)``, each ``[..., B]``, and which readings hit."""
        ang = z[..., 2:3] + self.beam_angles.to(z.dtype)  # [..., B]
        r = x.to(z.dtype).expand_as(ang)
        ex = torch.addcmul(z[..., 0:1], r, torch.cos(ang))
        ey = torch.addcmul(z[..., 1:2], r, torch.sin(ang))
        return ex, ey, r < self.max_range * (1 - 1e-3)

    def _mean_given(self, grid, M, z, x):
        """The mean given the reading ``x`` and the end points: ``x - d [..., B]``, ``(ex, ey)``
        and the hits ``[..., B]``."""
        if self.ramp is None:
            raise ValueError("EndPointEmission reads distances through its ramp: set .ramp")
        ex, ey, hit = self._end_points(z, x)
        w, h = grid.cells
        spacing = min(grid.size[0] / (w - 1), grid.size[1] / (h - 1))
        d = self.ramp.distance(grid.read(M[..., :1], ex, ey)[..., 0]) * spacing
        r = x.to(z.dtype).expand_as(ex)
        return torch.where(hit, r - d, r), (ex, ey), hit

    def read(self, grid, M, z, x=None):
        """The mean given the reading ``x [..., B]`` (class doc), or without one the ray
        march's expected range: ``[..., B]``."""
        if x is None:
            return self.expected_range(grid, M, z)
        return self._mean_given(grid, M, z, x)[0]

    def read_moments(self, grid, loc, scale, z, variance=None, x=None):
        """Given the reading ``x``: the mean under ``loc`` and how unknown each reading is, the
        occupancy's variance relative to the prior's at its end point (1 for a miss), both
        ``[..., B]``; without one, :meth:`RayEmission.read_moments`."""
        if x is None:
            return super().read_moments(grid, loc, scale, z, variance)
        mean, (ex, ey), hit = self._mean_given(grid, loc, z, x)
        var = scale[..., :1] ** 2 if variance is None else variance[..., :1]
        v = grid.read_variance(var, ex, ey, squared=True)[..., 0]
        return mean, torch.where(hit, v, torch.ones_like(v))


class ImageEmission(Emission):
    """First-person image read-out (paper Appendix B-D..F, the VizDoom emission).

    Each map cell holds ``bins x rows`` features (``M`` is ``w x h x k x l``, flattened to
    ``D_m = k * l`` with the angular axis major): ``bins`` equally spaced world directions
    (``2 pi j / bins``) times ``rows`` image rows. The chart is rotated with the agent's heading
    and cropped to the camera's field of view by reading every row at the world angles
    ``heading + column_angles`` (circular linear interpolation, :func:`rotate_scan`), giving a
    ``rows x cols`` view; row ``r`` of the view is mapped to row ``r`` of the image by MLP
    ``min(r, rows - 1 - r)``: the top half of the rows uses networks ``0 .. ceil(rows/2) - 1``,
    the bottom half the same networks in reverse order (the image is symmetric about the
    horizon up to texture). ``layers`` hidden layers of ``hidden`` ReLU units per network.

    Args:
        bins: ``k``, angular bins of the map (paper 32).
        rows, cols: image size (paper / simulator 24 x 32).
        fov: horizontal field of view, rad (90 deg); ignored if ``column_angles`` is given.
        column_angles: ``[cols]`` ray angle of each image column relative to the heading, left
            to right (default: the pinhole camera's evenly spread ``fov/2 - (j + 1/2) fov/cols``).
    """

    def __init__(
        self,
        bins: int = 32,
        rows: int = 24,
        cols: int = 32,
        fov: float = math.pi / 2,
        hidden: int = 256,
        layers: int = 4,
        column_angles=None,
    ):
        super().__init__()
        self.bins, self.rows, self.cols = int(bins), int(rows), int(cols)
        self.map_dim = self.bins * self.rows
        self.event_shape = (self.rows, self.cols)
        if column_angles is None:
            column_angles = fov / 2 - (torch.arange(cols) + 0.5) * (fov / cols)
        angles = torch.as_tensor(column_angles, dtype=torch.get_default_dtype())
        self.register_buffer("column_angles", angles, persistent=False)
        self.num_nets = (self.rows + 1) // 2
        net_of_row = [min(r, self.rows - 1 - r) for r in range(self.rows)]
        self.register_buffer("net_of_row", torch.tensor(net_of_row), persistent=False)
        dims = [self.cols] + [hidden] * layers + [self.cols]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for d_in, d_out in zip(dims[:-1], dims[1:]):
            bound = 1.0 / math.sqrt(d_in)  # nn.Linear's default initialisation
            self.weights.append(nn.Parameter(torch.empty(self.num_nets, d_in, d_out)))
            self.biases.append(nn.Parameter(torch.empty(self.num_nets, d_out)))
            nn.init.uniform_(self.weights[-1], -bound, bound)
            nn.init.uniform_(self.biases[-1], -bound, bound)

    def view(self, m: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
        """Rotated, cropped chart: ``m [..., k * l]``, ``heading [...]`` -> ``[..., l, cols]``."""
        chart = m.unflatten(-1, (self.bins, self.rows)).transpose(-1, -2)  # [..., l, k]
        return rotate_scan(chart, heading.unsqueeze(-1), self.column_angles)

    def rows_mlp(self, v: torch.Tensor) -> torch.Tensor:
        """Row-wise MLPs: ``[..., rows, cols]`` -> ``[..., rows, cols]``."""
        idx = self.net_of_row
        n = len(self.weights)
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            v = torch.einsum("...ri,rio->...ro", v, w[idx]) + b[idx]
            if i < n - 1:
                v = torch.relu(v)
        return v

    def forward(self, m: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
        """Predicted image ``[..., rows, cols]``."""
        return self.rows_mlp(self.view(m, heading))

    def mean(self, m, z):
        return self(m, z[..., 2]).flatten(-2)


class RayImageEmission(RayEmission):
    """Geometric first-person camera: one ray per image column through an occupancy map.

    Not the paper's image emission (:class:`ImageEmission`), an alternative with the same
    interface, as :class:`RayEmission` is for LiDAR: the map holds ``D_m = 1 + bins`` features
    per cell, an occupancy logit (feature 0, read as by :class:`RayEmission`) and an albedo
    logit at ``bins`` world directions ``2 pi j / bins`` (features ``1..bins``; the albedo a ray
    sees is ``sigmoid`` of them, circularly interpolated at the ray's world direction, so a wall's
    faces can differ). Column ``c`` casts a ray at ``heading + column_angles[c]``; its expected
    range ``r_c`` gives the perpendicular depth ``d_c = r_c cos(column_angles[c])`` and the
    albedo ``a_c`` is read at the point ``r_c`` along the ray (rays that stop nowhere see a
    learned far albedo); a pinhole camera (focal length from the field of view) draws the wall
    between rows ``rows/2 - f h_up / d_c`` and ``rows/2 + f h_down / d_c`` with brightness
    ``a_c / (1 + d_c / fog)``; rows not covered show a per-row background
    (floor or ceiling). Pixels blend by fractional row coverage.

    The scene constants ``h_up, h_down, fog`` (world units), the ``[rows]`` background and the
    albedo of rays that stop nowhere are this emission's parameters, pretrained like the other
    emissions (:func:`~pyro_slam.slam.pretrain_emission`); everything about the maze is in ``M``.
    A view then constrains every cell its rays cross, so a new pose is localised against walls
    mapped from earlier poses (the chart emission copies the view of the cell it stands on).

    Args:
        column_angles: ``[cols]`` ray angle of each image column relative to the heading, left
            to right (the simulator camera's ``fov/2 - (j + 1/2) fov/cols``).
        rows: image rows.
        max_range: rays are marched this far (world units).
        samples, density, gain, offset: as :class:`RayEmission`.
        bins: albedo directions per cell.
    """

    def __init__(
        self,
        column_angles,
        rows: int,
        max_range: float = 1.0,
        samples: int = 48,
        bins: int = 8,
        density: float = 100.0,
        gain: float = 8.0,
        offset: float = -8.0,
    ):
        super().__init__(column_angles, max_range, samples, density, gain, offset)
        cols = int(self.beam_angles.shape[0])
        self.rows, self.cols, self.bins = int(rows), cols, int(bins)
        self.map_dim = 1 + self.bins
        self.event_shape = (self.rows, cols)
        # trust: the occupancy where the agent stands (the albedo features are only learned
        # where rays stop, i.e. on walls, so at a free pose they keep the prior's variance)
        self.trust_features = 1
        a = self.beam_angles.double()
        spacing = float((a[0] - a[-1]).abs()) / max(cols - 1, 1) if cols > 1 else 1.0
        self.focal = (cols / 2) / math.tan(cols * spacing / 2)  # pixels
        self.log_height = nn.Parameter(torch.full((2,), math.log(0.05)))  # up, down
        self.log_fog = nn.Parameter(torch.tensor(math.log(0.25)))
        self.background = nn.Parameter(torch.full((self.rows,), 0.5))
        self.far_albedo = nn.Parameter(torch.tensor(0.0))

    reading_range = 1.0  # pixel intensities

    def read_moments(self, grid, loc, scale, z, variance=None, x=None):
        """The predicted image under ``loc`` ``[..., rows * cols]`` and how unknown each pixel
        is: its column's ray's (:meth:`RayEmission.read_moments`), ``[..., rows * cols]``."""
        var = RayEmission.read_moments(self, grid, loc, scale, z, variance)[1]  # [..., C]
        var = var.unsqueeze(-2).expand(*var.shape[:-1], self.rows, self.cols)
        return self.read(grid, loc, z), var.flatten(-2)

    def read(self, grid, M, z, x=None):
        """Predicted image at poses ``z [..., 3]``, flattened row-major: ``[..., rows * cols]``."""
        dt = z.dtype
        rng, passes = self._range(grid, M, z)  # [..., C] each
        ang = z[..., 2:3] + self.beam_angles.to(dt)  # [..., C] world direction of each ray
        # albedo where the ray is expected to stop (one read per ray, not per sample)
        u = torch.stack([torch.cos(ang), torch.sin(ang)], -1)  # [..., C, 2]
        hit = z[..., None, :2] + rng.unsqueeze(-1) * u  # [..., C, 2]
        albedo = rotate_scan(grid.attend(M[..., 1:], hit), ang, torch.zeros(1, dtype=dt))
        a = (1 - passes) * torch.sigmoid(albedo[..., 0]) + passes * torch.sigmoid(self.far_albedo)
        depth = (rng * torch.cos(self.beam_angles.to(dt))).clamp_min(1e-3)  # [..., C]
        up, down = self.log_height.exp()
        h0 = self.rows / 2
        top = (h0 - self.focal * up / depth).unsqueeze(-2)  # [..., 1, C]
        bottom = (h0 + self.focal * down / depth).unsqueeze(-2)
        r = torch.arange(self.rows, dtype=dt).unsqueeze(-1)  # [rows, 1]
        cover = (torch.minimum(r + 1, bottom) - torch.maximum(r, top)).clamp(0.0, 1.0)
        wall = (a / (1.0 + depth / self.log_fog.exp())).unsqueeze(-2)  # [..., 1, C]
        img = cover * wall + (1.0 - cover) * self.background.unsqueeze(-1)  # [..., rows, C]
        return img.flatten(-2)
