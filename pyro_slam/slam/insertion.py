"""Scan insertion: the part of the guide that updates ``q(M)`` with each online scan, for the
ray-cast LiDAR emission, as an approximate Bayesian update under the model's own map prior.

**The inverse sensor model.** A scan placed at the pose estimate reads the value of each grid
point it touches: a wall's grid point reads the emission's wall level ``occupancy`` (the logit
at which a ray stops within a grid spacing), a grid point the beam passed reads the free level
``-occupancy / 2`` (a logit that stops no ray), each with Gaussian noise of std ``noise``
(``emission.insert``). Readings at the sensor's range are misses and read no wall.

**The update.** Each grid point keeps its inverse-sensor-model reading as a Gaussian site (a
pseudo-observation ``y`` of precision ``lambda``). Inserting a reading replaces the point's site
and moves ``q(M)``'s natural parameters by the difference (an expectation-propagation site
update): with ``q`` at the prior ``N(mu_0, s_0^2)``, the first reading gives

    1 / s^2 = 1 / s_0^2 + lambda,    mu = s^2 (mu_0 / s_0^2 + lambda y),

the model's prior scaled by the reading; whatever SVI has learned since is kept, as the update
changes the belief only by the site's change. The prior's mean and variance are the model's
(:meth:`~pyro_slam.model.DVBFLM.map_prior`: a swapped prior changes what insertion writes; a
non-Gaussian prior enters through its first two moments). The belief is read and written
through the map guide's marginal (:class:`~pyro_slam.model.guide.MapLeaves`).

**The map's placement.** A reading is placed from the pose estimate, so where it lies in the
world is as uncertain as that pose: each grid point also keeps the position variance (per axis)
of the pose its reading was placed from, the map belief's *placement* variance. The filter's
cloud gives the pose relative to the map (its std:
:meth:`~pyro_slam.inference.Particles.posterior_std`); a pose's world-frame std adds the
placement variance of the walls its beams stop at (:meth:`ScanInserter.placement_at`), and the
scans it inserts are placed with that world-frame variance. Exploring hands the uncertainty on
from wall to wall, as drift accumulates; a revisit of walls placed earlier, with less, takes it
back.

Two kinds (``emission.insert.kind``):

``"occupancy"`` (:class:`OccupancyInserter`)
    the hits, joined into a polyline (hits of neighbouring beams closer than ``gap`` are one
    wall, sampled at half a grid spacing), give the grid points nearest to it that no earlier
    scan hit a wall reading; the grid points each beam crosses up to a grid spacing short of
    its return (up to the range for a miss) that no scan has read yet get a free reading:
    known free space, whose site a later hit replaces. A reading lies at the grid point
    nearest to where the scan puts it, up to half a spacing ``s`` away: besides its pose's
    placement, each wall carries its own rounding (variance ``s^2 / 12`` per axis, uniform),
    one shift along its length and independent between walls, of which a pose fitted to
    several walls gets a share (:meth:`OccupancyInserter.rounding_at`). Each grid point is read
    once (a wall
    once, its free reading before that at most once): the scans of one place are not
    independent readings of it, as the same pose error places them all. For walls without
    thickness (the simulated mazes).
``"fusion"`` (:class:`FusionInserter`)
    a truncated signed distance (TSDF; Curless and Levoy 1996) per grid point, in grid
    spacings, positive behind a surface:

    * near each **surface**, the grid points within ``band = ramp + SHIFT`` spacings of the
      scan's walls get
      their signed distance to them: the hits of neighbouring beams closer than ``gap`` are one
      wall (a segment, its normal pointing away from the sensor); an isolated hit is a wall
      across its beam, read along the beam;
    * along each beam, the grid points the beam **passed** before reaching ``band`` spacings of
      its hit (all of it for a reading at the range clip) are free: distance ``-band``;
    * each grid point keeps the running mean of what the scans said (at most ``MAX_WEIGHT``
      scans weigh, so that the map follows a changed pose estimate).

    A fused grid point's reading is a linear ramp in its distance
    (:class:`~pyro_slam.model.WallRamp`), from the free level at ``-ramp`` to ``occupancy`` at
    ``+ramp`` (``RAMP`` spacings), shifted (by at most ``SHIFT``) so that the emission's
    expected range at a wall seen head-on is the wall's distance (:func:`surface_offset`); an
    emission that reads the ramp itself (:class:`~pyro_slam.model.EndPointEmission`) states
    its own, and insertion writes that one. Bilinear interpolation reproduces a linear ramp
    exactly, so the ray stops at the wall to within a fraction of a grid spacing whatever the
    wall's position in its cell. Its precision is ``scans / noise^2`` (the fused scans'
    readings). For real walls, which have a back side no beam sees.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from ..geometry import interleave
from ..model.emissions import WallRamp
from ..model.model import MapGrid
from .config import ScanInsertionConfig

RAMP = 1.5  # half the width of a wall's ramp in q(M)'s mean (grid spacings), by default
SHIFT = 1.0  # the most the ramp may shift to put the expected range on the wall
MAX_WEIGHT = 10.0  # scans that weigh in a grid point's running mean


def ragged(counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For ``counts [n]`` items of each of ``n`` groups, laid end to end: each item's group and
    its place in the group, both ``[counts.sum()]``."""
    group = torch.repeat_interleave(torch.arange(len(counts)), counts)
    return group, torch.arange(len(group)) - (torch.cumsum(counts, 0) - counts)[group]


def surface_offset(emission, ramp, spacing: float, phases: int = 8) -> float:
    """The shift ``delta`` (grid spacings) of the ramp ``ramp(d)`` (loc at signed distance
    ``d``) for which the emission's expected range at a wall seen head-on equals the wall's
    distance, averaged over the wall's position in its cell: ``ramp(d + delta)`` is written."""
    n = int(math.ceil(emission.max_range / spacing)) + 8
    grid = MapGrid((n, 3), 1, (-4 * spacing, -spacing), ((n - 1) * spacing, 2 * spacing))
    xs = grid.origin[0] + torch.arange(n, dtype=torch.float64) * spacing
    ang = emission.beam_angles.double()
    dist = 0.5 * emission.max_range + spacing * (torch.arange(phases) + 0.5) / phases  # walls
    z = torch.stack([torch.zeros_like(dist), torch.zeros_like(dist), -ang[0].expand_as(dist)], -1)

    def bias(delta: float) -> float:
        d = (xs[None, :] - dist[:, None]) / spacing + delta  # [P, n] signed distances
        M = ramp(d)[:, :, None, None].expand(-1, -1, 3, 1)  # [P, n, 3, 1] a map per wall
        with torch.no_grad():
            r = emission.read(grid, M.float(), z.float())[:, 0]  # [P] beam 0
        return float((r.double() - dist).mean()) / spacing

    lo, hi = -SHIFT, SHIFT  # the bias falls as delta grows: bisect for zero
    for _ in range(20):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if bias(mid) > 0 else (lo, mid)
    return 0.5 * (lo + hi)


def wall_ramp(
    config: ScanInsertionConfig, emission, spacing: float, half_width: float = RAMP
) -> WallRamp:
    """The ramp that fusion insertion writes across a wall for ``emission``: from the free level
    ``-occupancy / 2`` to ``occupancy`` over ``2 half_width`` spacings, shifted by
    :func:`surface_offset` (for a grid of ``spacing``)."""
    base = WallRamp(config.occupancy, -0.5 * config.occupancy, half_width)
    return replace(base, shift=surface_offset(emission, base.loc, spacing))


class ScanInserter:
    """Updates a map guide's ``q(M)`` with scans (module doc); :func:`make_inserter` builds the
    configured kind.

    Args:
        config: the :class:`~pyro_slam.slam.config.ScanInsertionConfig`.
        model: the :class:`~pyro_slam.model.DVBFLM` (its grid, ray-cast emission and prior).
        leaves: the guide's marginal, :class:`~pyro_slam.model.guide.MapLeaves`.
    """

    def __init__(self, config: ScanInsertionConfig, model, leaves):
        self.cfg, self.model, self.leaves = config, model, leaves
        g = model.grid
        w, h, _ = g.shape
        self.spacing = min(g.size[0] / (w - 1), g.size[1] / (h - 1))
        self.free = -0.5 * config.occupancy  # the free level
        self.precision = 1.0 / config.noise**2  # one reading's
        self.site_y = torch.zeros((w, h), dtype=torch.float64)  # [w, h] each point's reading
        self.site_prec = torch.zeros((w, h), dtype=torch.float64)  # [w, h] and its precision
        self.placement = torch.zeros((w, h), dtype=torch.float64)  # [w, h] its placement var
        self._field = None  # [w, h, 2] the placement and whether a site is set, as read

    @property
    def inserted(self) -> torch.Tensor:
        """``[w, h]`` bool: grid points some scan wrote a wall or a distance into."""
        raise NotImplementedError

    def insert(
        self, x: torch.Tensor, valid: torch.Tensor, z: torch.Tensor, var=0.0, scale=1.0
    ) -> None:
        """Update ``q(M)`` with scan ``x [B]`` (``valid [B]`` bool) placed from pose ``z [3]``,
        whose world-frame position variance (per axis) is ``var``; ``scale``: the scale of the
        scan's site in the model (a handler's ``poutine.scale``), which scales each reading's
        precision as it scales the likelihood."""
        raise NotImplementedError

    def placement_at(self, z: torch.Tensor) -> float:
        """The placement variance (per axis) of the map where the beams of pose ``z [3]`` stop
        under ``q(M)``'s mean: the stop-weighted mean of the placements of the readings that
        hit inserted grid points (shared by them, as nearby poses placed them), plus the share
        of the readings' own rounding that reaches the pose (:meth:`rounding_at`); 0 where no
        beam stops on an inserted point."""
        em, grid = self.model.emission, self.model.grid
        with torch.no_grad():
            loc = self.leaves.loc.detach()
            pts, stop, _ = em.stops(grid, loc, z.to(loc.dtype))  # [B, S, 2], [B, S]
            read = grid.attend(self._placement_field(loc.dtype), pts)  # [B, S, 2]
            on = stop * read[..., 1]  # [B, S] stopping on an inserted point
            seen = on.sum()
            if seen <= 1e-6:
                return 0.0
            shared = float((stop * read[..., 0]).sum() / seen)
            return shared + self.rounding_at(z.to(loc.dtype), pts, on)

    def _placement_field(self, dtype) -> torch.Tensor:
        """``[w, h, 2]``: each grid point's placement variance and whether a site is set, kept
        between scans (:meth:`_observe` updates the points it writes)."""
        if self._field is None or self._field.dtype != dtype:
            self._field = interleave(self.placement, self.site_prec > 0, dtype)
        return self._field

    def rounding_at(self, z: torch.Tensor, pts: torch.Tensor, on: torch.Tensor) -> float:
        """The variance (per axis) that the readings' own rounding gives pose ``z [3]`` whose
        beams stop at ``pts [B, S, 2]`` on inserted points with probability ``on [B, S]``:
        none here (a kind that places readings exactly)."""
        return 0.0

    def _to_grid(self, p: torch.Tensor) -> torch.Tensor:
        """Positions ``[..., 2]`` in grid coordinates (spacings from the origin)."""
        g = self.model.grid
        w, h, _ = g.shape
        scale = p.new_tensor([(w - 1) / g.size[0], (h - 1) / g.size[1]])
        return (p - p.new_tensor(g.origin)) * scale

    def _nearest(self, p: torch.Tensor):
        """The grid points ``(i [P], j [P])`` nearest to positions ``p [P, 2]`` (clamped)."""
        w, h = self.model.grid.cells
        c = self._to_grid(p).round().long()
        return c[:, 0].clamp(0, w - 1), c[:, 1].clamp(0, h - 1)

    def _observe(self, i, j, y, precision, placement) -> None:
        """Replace the sites of grid points ``(i [P], j [P])`` by readings ``y`` of precision
        ``precision`` placed with variance ``placement`` (numbers or ``[P]``), moving ``q(M)``'s
        natural parameters by the sites' change (module doc)."""
        if not len(i):
            return
        loc, std = self.leaves.read(i, j)  # [P]
        lam = std.double() ** -2
        eta = loc.double() * lam
        y = torch.as_tensor(y, dtype=torch.float64).expand(len(i))
        prec = torch.as_tensor(precision, dtype=torch.float64).expand(len(i))
        old_prec, old_y = self.site_prec[i, j], self.site_y[i, j]
        lam_new = (lam - old_prec + prec).maximum(prec)  # (SVI may have widened the belief)
        eta_new = eta - old_prec * old_y + prec * y
        self.site_y[i, j], self.site_prec[i, j] = y, prec
        self.placement[i, j] = torch.as_tensor(placement, dtype=torch.float64)
        if self._field is not None:
            fresh = interleave(self.placement[i, j], self.site_prec[i, j] > 0, self._field.dtype)
            self._field[i, j] = fresh
        self.leaves.write(i, j, eta_new / lam_new, lam_new.rsqrt())

    def state_dict(self) -> dict:
        sites = ("site_y", "site_prec", "placement")
        return {k: getattr(self, k).clone() for k in sites}

    def load_state_dict(self, d: dict) -> None:
        for k in ("site_y", "site_prec", "placement"):
            getattr(self, k).copy_(d[k])
        self._field = None


class OccupancyInserter(ScanInserter):
    """Walls and free space read once per grid point (module doc, ``"occupancy"``)."""

    def __init__(self, config: ScanInsertionConfig, model, leaves):
        super().__init__(config, model, leaves)
        w, h = model.grid.cells
        self.rounding = self.spacing**2 / 12  # a reading's variance (per axis) from its rounding
        self.walls = torch.zeros((w, h), dtype=torch.bool)  # [w, h] hit by a scan
        self.freed = torch.zeros((w, h), dtype=torch.bool)  # [w, h] crossed by a beam

    @property
    def inserted(self) -> torch.Tensor:
        return self.walls

    def hit_cells(self, x: torch.Tensor, valid: torch.Tensor, z: torch.Tensor):
        """Grid points ``(i [P], j [P])`` nearest to the polyline of the hits of scan
        ``x [B]`` (``valid [B]`` bool) placed from pose ``z [3]``."""
        em = self.model.emission
        hit = (x < em.max_range * (1 - 1e-3)) & valid  # [B]
        ang = z[2] + em.beam_angles.to(x.dtype)  # [B]
        pts = z[:2] + x[:, None] * torch.stack([ang.cos(), ang.sin()], -1)  # [B, 2]
        nxt = torch.roll(torch.arange(x.shape[0]), -1)  # [B] the neighbouring beam
        seg = hit & hit[nxt] & ((pts[nxt] - pts).norm(dim=-1) < self.cfg.gap)  # [B]
        n = int(math.ceil(self.cfg.gap / (0.5 * self.spacing))) + 1
        f = torch.linspace(0, 1, n, dtype=x.dtype)[:, None, None]  # [n, 1, 1]
        on = pts[seg] + f * (pts[nxt][seg] - pts[seg])  # [n, S, 2] along joined pairs
        return self._nearest(torch.cat([pts[hit], on.reshape(-1, 2)]))

    def rounding_at(self, z: torch.Tensor, pts: torch.Tensor, on: torch.Tensor) -> float:
        """The share of the walls' rounding that reaches pose ``z [3]`` (per axis): each wall
        the beams stop on (neighbouring beams' stops closer than ``gap`` are one wall, as
        inserted) is shifted along its normal ``n_k`` by its own rounding (variance ``r``,
        independent between walls); a pose fitted to the ``w_k`` beams on each wall moves by
        the weighted mean of the shifts, covariance ``r A^+ C A^+`` with ``A = sum w_k n_k
        n_k^T`` and ``C = sum w_k^2 n_k n_k^T``; its mean over the axes, at most ``r``."""
        mass = on.sum(-1)  # [B]
        hit = mass > 0.5
        if not bool(hit.any()):
            return 0.0
        p = (on[..., None] * pts).sum(-2) / mass.clamp_min(1e-12)[:, None]  # [B, 2] its stop
        B = p.shape[0]
        nxt, prv = torch.roll(torch.arange(B), -1), torch.roll(torch.arange(B), 1)
        join = hit & hit[nxt] & ((p[nxt] - p).norm(dim=-1) < self.cfg.gap)  # [B]
        first = hit & ~join[prv]  # [B] a wall's first beam
        if not bool(first.any()):  # one wall all round
            first = hit & (torch.arange(B) == int(torch.nonzero(hit)[0]))
        label = torch.cumsum(first.long(), 0)  # beams before the first start: the last wall
        label = torch.where(label == 0, label.max(), label)
        A, C = p.new_zeros(2, 2), p.new_zeros(2, 2)
        for k in range(1, int(label.max()) + 1):
            beams = torch.nonzero(hit & (label == k)).flatten()
            a, b = p[beams[0]], p[beams[-1]]
            if len(beams) > 1 and float((b - a).norm()) > 0:
                n = torch.stack([a[1] - b[1], b[0] - a[0]]) / (b - a).norm()
            else:
                n = (a - z[:2]) / (a - z[:2]).norm().clamp_min(1e-12)
            nn_ = torch.outer(n, n)
            A, C = A + len(beams) * nn_, C + len(beams) ** 2 * nn_
        Ai = torch.linalg.pinv(A)
        return min(self.rounding * float(torch.trace(Ai @ C @ Ai)) / 2, self.rounding)

    def free_cells(self, x: torch.Tensor, valid: torch.Tensor, z: torch.Tensor):
        """Grid points ``(i [P], j [P])`` the beams of scan ``x [B]`` (``valid [B]``) cross from
        pose ``z [3]`` up to a grid spacing short of their returns (up to the range where they
        miss), sampled at half a spacing."""
        em = self.model.emission
        hit = x < em.max_range * (1 - 1e-3)
        reach = torch.where(hit, x - self.spacing, x.new_tensor(em.max_range)).clamp_min(0)
        ang = z[2] + em.beam_angles.to(x.dtype)[valid]  # [V]
        n = int(math.ceil(em.max_range / (0.5 * self.spacing))) + 1
        d = torch.linspace(0, 1, n, dtype=x.dtype)[:, None] * reach[valid]  # [n, V]
        p = z[:2] + d[..., None] * torch.stack([ang.cos(), ang.sin()], -1)  # [n, V, 2]
        return self._nearest(p.reshape(-1, 2))

    def insert(self, x, valid, z, var=0.0, scale=1.0) -> None:
        """Read scan ``x [B]`` (``valid [B]``) placed from pose ``z [3]`` (position variance
        ``var``; ``scale``: :meth:`ScanInserter.insert`): its walls where no scan hit yet, then
        its free space where nothing was read yet."""
        precision = self.precision * scale
        i, j = self.hit_cells(x, valid, z)
        new = ~self.walls[i, j]  # [P]
        self._observe(i[new], j[new], self.cfg.occupancy, precision, var)
        self.walls[i[new], j[new]] = True
        i, j = self.free_cells(x, valid, z)
        new = ~(self.walls[i, j] | self.freed[i, j])
        self._observe(i[new], j[new], self.free, precision, var)
        self.freed[i[new], j[new]] = True

    def state_dict(self) -> dict:
        return {**super().state_dict(), "walls": self.walls.clone(), "freed": self.freed.clone()}

    def load_state_dict(self, d: dict) -> None:
        super().load_state_dict(d)
        self.walls.copy_(d["walls"])
        self.freed.copy_(d["freed"])


class FusionInserter(ScanInserter):
    """A truncated signed distance fused over scans (module doc, ``"fusion"``)."""

    def __init__(self, config: ScanInsertionConfig, model, leaves):
        super().__init__(config, model, leaves)
        w, h = model.grid.cells
        self.sdf = torch.zeros((w, h), dtype=torch.float64)  # weighted sum of distances
        self.weight = torch.zeros((w, h), dtype=torch.float64)  # scans fused
        self.placed = torch.zeros((w, h), dtype=torch.float64)  # weighted sum of placement vars
        own = getattr(model.emission, "ramp", None)  # an emission that reads one states it
        self.ramp = own if own is not None else wall_ramp(config, model.emission, self.spacing)
        # grid spacings either side of a surface that carry its signed distance
        self.band = self.ramp.half_width + SHIFT

    @property
    def inserted(self) -> torch.Tensor:
        return self.weight > 0

    def surfaces(self, x: torch.Tensor, valid: torch.Tensor, z: torch.Tensor):
        """The scan's walls: ``a, b [W, 2]`` (grid coordinates) and their unit normals ``n [W,
        2]`` pointing away from the sensor; an isolated hit is ``a == b`` with ``n`` its beam."""
        em = self.model.emission
        hit = (x < em.max_range * (1 - 1e-3)) & valid  # [B]
        ang = z[2] + em.beam_angles.to(x.dtype)  # [B]
        u = torch.stack([ang.cos(), ang.sin()], -1)  # [B, 2]
        pts = self._to_grid(z[:2] + x[:, None] * u)  # [B, 2]
        nxt = torch.roll(torch.arange(x.shape[0]), -1)
        gap = self.cfg.gap / self.spacing
        seg = hit & hit[nxt] & ((pts[nxt] - pts).norm(dim=-1) < gap)  # [B]
        lone = hit & ~seg & ~torch.roll(seg, 1)  # [B] a hit on no segment
        a = torch.cat([pts[seg], pts[lone]])
        b = torch.cat([pts[nxt][seg], pts[lone]])
        t = b[: int(seg.sum())] - a[: int(seg.sum())]
        n = torch.stack([t[:, 1], -t[:, 0]], -1) / t.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        mid = 0.5 * (a[: len(t)] + b[: len(t)]) - self._to_grid(z[:2])
        n = torch.where((n * mid).sum(-1, keepdim=True) < 0, -n, n)
        return a, b, torch.cat([n, u[lone]])

    def surface_points(self, a, b, n):
        """Grid points near the walls and their signed distances: ``(flat index [P], d [P])``,
        one per grid point (the nearest wall's). A wall's candidates are the grid points of its
        bounding box widened by ``sqrt(band^2 + 1/4)``: a grid point within ``band`` of a wall
        and at most half a spacing past its ends is no farther than that from it."""
        w, h = self.model.grid.cells
        reach = math.sqrt(self.band**2 + 0.25) + 1e-6
        lo = (torch.minimum(a, b) - reach).ceil()  # [W, 2] the box's first grid point
        size = ((torch.maximum(a, b) + reach).floor() - lo + 1).long()  # [W, 2] its points
        counts = size[:, 0] * size[:, 1]  # [W]
        wall, k = ragged(counts)  # [N] each one's wall and place in its box
        ny = size[wall, 1]
        g = lo[wall] + torch.stack([k // ny, k % ny], -1).to(a.dtype)  # [N, 2]
        ab = b - a  # [W, 2]
        a, ab, n = a[wall], ab[wall], n[wall]  # [N, 2]
        t = (((g - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-9)).clamp(0, 1)
        e = g - (a + t[..., None] * ab)  # [N, 2] from the wall
        d = (e * n).sum(-1)  # signed distance along the normal
        lateral = (e - d[..., None] * n).norm(dim=-1)
        keep = (d.abs() <= self.band) & (lateral <= 0.5)
        inside = (g[..., 0] >= 0) & (g[..., 0] <= w - 1) & (g[..., 1] >= 0) & (g[..., 1] <= h - 1)
        keep &= inside
        idx = (g[..., 0] * h + g[..., 1]).long()[keep]
        d = d[keep]
        order = torch.argsort(d.abs(), stable=True)  # nearest first, then by grid point
        idx, d = idx[order], d[order]
        order = torch.argsort(idx, stable=True)
        idx, d = idx[order], d[order]
        uniq = torch.ones_like(idx, dtype=torch.bool)
        uniq[1:] = idx[1:] != idx[:-1]
        return idx[uniq], d[uniq]

    def free_points(self, x, valid, z) -> torch.Tensor:
        """Flat indices of the grid points the beams passed (up to ``band`` spacings before a
        hit; the whole clip for a reading at it), without repeats: each beam sampled every half
        spacing up to its reach."""
        em = self.model.emission
        w, h = self.model.grid.cells
        ang = z[2] + em.beam_angles.to(x.dtype)
        u = torch.stack([ang.cos(), ang.sin()], -1)  # [B, 2]
        hit = x < em.max_range * (1 - 1e-3)
        reach = torch.where(hit, x - (self.band + 0.5) * self.spacing, x)  # [B]
        step = 0.5 * self.spacing
        n = int(math.ceil(em.max_range / step)) + 1
        counts = (reach / step).floor().long().add(2).clamp(0, n) * valid  # [B] (one spare)
        beam, k = ragged(counts)  # [P] each sample's beam and place along it
        s = k.to(x.dtype) * step  # [P]
        on = s <= reach[beam]
        g = self._to_grid(z[:2] + s[:, None] * u[beam]).round()[on]  # [P, 2]
        ok = (g[:, 0] >= 0) & (g[:, 0] <= w - 1) & (g[:, 1] >= 0) & (g[:, 1] <= h - 1)
        return torch.unique((g[ok, 0] * h + g[ok, 1]).long())

    def insert(self, x, valid, z, var=0.0, scale=1.0) -> None:
        """Fuse scan ``x [B]`` (``valid [B]``) placed from pose ``z [3]`` (position variance
        ``var``; ``scale``: :meth:`ScanInserter.insert`) and update ``q(M)`` at the fused grid
        points."""
        idx, d = self.surface_points(*self.surfaces(x, valid, z))
        free = self.free_points(x, valid, z)
        free = free[~torch.isin(free, idx)]
        idx = torch.cat([idx, free])
        d = torch.cat([d.double(), torch.full((len(free),), -self.band, dtype=torch.float64)])
        sdf, weight = self.sdf.view(-1), self.weight.view(-1)
        keep = ((MAX_WEIGHT - 1) / weight[idx].clamp_min(1e-9)).clamp(max=1)  # cap the weight
        sdf[idx] = sdf[idx] * keep + d
        placed = self.placed.view(-1)
        placed[idx] = placed[idx] * keep + var
        weight[idx] = weight[idx] * keep + 1
        y = self.ramp.loc(sdf[idx] / weight[idx])
        h = self.model.grid.cells[1]
        prec, var = weight[idx] * (self.precision * scale), placed[idx] / weight[idx]
        self._observe(idx // h, idx % h, y, prec, var)

    def state_dict(self) -> dict:
        own = {k: getattr(self, k).clone() for k in ("sdf", "weight", "placed")}
        return {**super().state_dict(), **own}

    def load_state_dict(self, d: dict) -> None:
        super().load_state_dict(d)
        self.placed.copy_(d["placed"])
        self.sdf.copy_(d["sdf"])
        self.weight.copy_(d["weight"])


INSERTERS = {"occupancy": OccupancyInserter, "fusion": FusionInserter}


def make_inserter(config: ScanInsertionConfig, model, leaves) -> ScanInserter:
    """The scan inserter of ``config.kind`` (module doc) for a map guide's marginal
    ``leaves`` (:class:`~pyro_slam.model.guide.MapLeaves`)."""
    return INSERTERS[config.kind](config, model, leaves)
