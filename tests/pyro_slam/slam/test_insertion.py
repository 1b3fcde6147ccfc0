"""Scan insertion (:mod:`pyro_slam.slam.insertion`): the guide's Gaussian update of ``q(M)``
from a stated inverse sensor model and the model's own map prior, through any guide's marginal,
with the map's placement variance."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pyro.distributions as dist
import pytest
import torch
from pyro.infer.autoguide import AutoDelta, AutoLowRankMultivariateNormal
from small_slam import SMALL

from pyro_slam.metrics import CALIBRATION_START, calibration
from pyro_slam.model import autoguide, map_marginals
from pyro_slam.planning.envs import run_env
from pyro_slam.slam import SLAM, ConfigError, EmissionConfig, ScanInsertionConfig
from pyro_slam.slam.insertion import FusionInserter, OccupancyInserter, make_inserter
from pyro_slam.slam.loop import world_std
from simulators import simulate_traversal
from simulators.maze import make_maze

INSERT = ScanInsertionConfig()
WALL, FREE, NOISE = INSERT.occupancy, -INSERT.occupancy / 2, INSERT.noise


@pytest.fixture(scope="module")
def small_traversal():
    return simulate_traversal("moderate-medium", steps=100, seed=1)


def insertion_slam(tr, kind: str = "occupancy", **kw) -> SLAM:
    """SLAM on a 1/63 grid with scan insertion of ``kind`` (``kw``: ``SLAM``'s, e.g. prior)."""
    insert = replace(INSERT, kind=kind)
    return SLAM(tr, replace(SMALL, emission=EmissionConfig("raycast", 1 / 63, insert=insert)), **kw)


def first_scan(slam, tr, var: float = 0.0):
    """Insert scan 0 at the true start pose (position variance ``var``); returns the pose."""
    z = torch.as_tensor(tr.poses[0], dtype=slam.obs.dtype)
    slam.inserter.insert(slam.obs[0], torch.ones_like(slam.obs[0], dtype=torch.bool), z, var)
    return z


def updated(y, prior_mean, prior_var, noise=NOISE):
    """The Gaussian update of ``N(prior_mean, prior_var)`` with one reading ``y``: (mean, std)."""
    lam = 1 / prior_var + 1 / noise**2
    return (prior_mean / prior_var + y / noise**2) / lam, lam**-0.5


def test_insertion_follows_the_prior(small_traversal):
    """A first scan updates each wall and free grid point from the model's map prior by the
    inverse sensor model's reading (wall level, free level, noise): under N(0, 1) the belief is
    at the emission's wall level 2 with std 0.3; under a wider prior, N(0, 2^2) or a Student-t
    (variance 3), the same reading weighs more against it, so walls come out higher and free
    space lower, each exactly as the Gaussian update says; untouched grid points keep the
    prior's std."""
    tr = small_traversal
    wide = dist.Normal(torch.zeros(1), 2.0 * torch.ones(1)).to_event(1)
    heavy = dist.StudentT(3.0, torch.zeros(1), torch.ones(1)).to_event(1)
    walls = {}
    for name, prior, var in (("default", None, 1.0), ("wide", wide, 4.0), ("t", heavy, 3.0)):
        slam = insertion_slam(tr, prior=prior)
        first_scan(slam, tr)
        b, ins = slam.map_belief(), slam.inserter
        for cells, y in ((ins.walls, WALL), (ins.freed, FREE)):
            mean, std = updated(y, 0.0, var)
            assert torch.allclose(b.loc[cells][:, 0], torch.tensor(mean), atol=1e-5)
            assert torch.allclose(b.scale[cells][:, 0], torch.tensor(std), atol=1e-5)
        untouched = ~(ins.walls | ins.freed)
        assert torch.allclose(b.scale[untouched][:, 0], torch.tensor(var**0.5))
        walls[name] = float(b.loc[ins.walls][:, 0].mean())
    assert walls["default"] == pytest.approx(2.0, abs=2e-3)  # the emission's wall level
    assert walls["wide"] > walls["t"] > walls["default"] + 0.1


def test_low_rank_guide_insertion_writes_the_marginal(small_traversal):
    """With Pyro's low-rank multivariate normal as the map guide, insertion reads and writes
    its marginal (``scale * sqrt(1 + |cov_factor row|^2)``), not its diagonal ``scale``: the
    guide's own marginal after insertion is the Gaussian update of its marginal before; a guide
    with no marginal to update (a point estimate) switches insertion off with a warning."""
    tr = small_traversal
    slam = insertion_slam(tr, guide=autoguide(AutoLowRankMultivariateNormal, rank=3))
    with slam.scope():
        loc0, std0 = (v.detach().clone() for v in map_marginals(slam.map_guide))
    first_scan(slam, tr)
    with slam.scope():
        loc, std = (v.detach() for v in map_marginals(slam.map_guide))
    walls = slam.inserter.walls
    mean, sd = updated(WALL, loc0[walls][:, 0].double(), std0[walls][:, 0].double() ** 2)
    assert torch.allclose(loc[walls][:, 0].double(), mean, atol=1e-4)
    assert torch.allclose(std[walls][:, 0].double(), sd, atol=1e-4)
    diagonal = slam.inserter.leaves.transform(slam.inserter.leaves.raw[walls][:, 0]).detach()
    assert not torch.allclose(diagonal.double(), sd, atol=1e-2)  # the marginal, not the scale
    with pytest.warns(UserWarning, match="scan insertion is off"):
        point = insertion_slam(tr, guide=autoguide(AutoDelta))
    assert point.inserter is None


def test_the_kept_map_belief_follows_insertion_and_svi(small_traversal):
    """The map belief the filter reads each step is kept between steps by the guide's leaves:
    after a scan's insertion and after an SVI step it equals the guide's own marginal, exactly
    (the points insertion wrote, and every point an SVI step moved), its variance the square of
    its std."""
    tr = small_traversal
    slam = insertion_slam(tr, "fusion")

    def agrees():
        kept = slam.map_belief()
        with slam.scope():
            loc, std = (v.detach() for v in map_marginals(slam.map_guide))
        same = torch.equal(kept.loc, loc) and torch.equal(kept.scale, std)
        return same and torch.equal(kept.variance, std**2)

    assert agrees()
    first_scan(slam, tr)
    assert agrees()
    before = slam.map_belief().scale.clone()
    with slam.scope():
        leaves = slam.inserter.leaves
        with torch.no_grad():
            leaves.raw.add_(0.1)  # as an optimiser's step moves it, in place
    assert agrees() and not torch.equal(slam.map_belief().scale, before)


def test_scan_insertion_fuses_scans_into_the_map(small_traversal):
    """Fusion: a scan placed from a pose is fused into a signed distance per grid point and
    read into q(M); the map then reproduces that scan at that pose. The same scan again, after
    SVI has moved every grid point, adds its reading to what SVI learned instead of writing
    over it: the belief's natural parameters move by the site's change."""
    tr = small_traversal
    slam = insertion_slam(tr, "fusion")
    inserter = slam.inserter
    assert isinstance(inserter, FusionInserter) and not inserter.inserted.any()
    z = first_scan(slam, tr)
    valid = torch.ones_like(slam.obs[0], dtype=torch.bool)
    M = slam.map_belief().loc
    written = inserter.inserted.clone()
    wall, _ = updated(WALL, 0.0, 1.0)
    assert int(written.sum()) > 20 and float(M.max()) <= wall + 1e-5
    assert float(M.min()) == pytest.approx(updated(FREE, 0.0, 1.0)[0], abs=1e-5)
    scale = slam.map_belief().scale[..., 0]  # [w, h]: updated where read, else the prior
    assert torch.allclose(scale[written], torch.tensor(updated(0, 0.0, 1.0)[1]), atol=1e-5)
    assert scale.max() == 1.0
    em, grid = slam.model.emission, slam.model.grid
    hit = slam.obs[0] < em.max_range * 0.999
    err = (em.read(grid, M, z) - slam.obs[0])[hit].abs()
    assert err.median() < 0.005
    y = inserter.site_y[written].clone()  # the fused readings
    with torch.no_grad():
        inserter.leaves.loc.fill_(0.5)  # as if SVI had moved every grid point
    inserter.insert(slam.obs[0], valid, z)
    lam1 = 1 + 1 / NOISE**2  # the belief's precision after one reading
    expect = (0.5 * lam1 + y / NOISE**2) / (lam1 + 1 / NOISE**2)  # one more reading of y
    assert torch.allclose(slam.map_belief().loc[written][:, 0].double(), expect, atol=1e-4)
    inserter.weight.zero_()  # masked readings read nothing
    inserter.insert(slam.obs[0], torch.zeros_like(valid), z)
    assert not inserter.inserted.any()
    with pytest.raises(ConfigError, match="emission.insert .* needs a ray-cast LiDAR emission"):
        EmissionConfig("mlp", insert=ScanInsertionConfig())  # the MLP's map has no occupancy
    with pytest.raises(ConfigError, match="emission.insert.noise"):
        ScanInsertionConfig(noise=0.0)
    with pytest.raises(ConfigError, match="emission.insert.kind must be one of"):
        ScanInsertionConfig(kind="tsdf")


def test_occupancy_insertion_reads_walls_once_and_free_space_a_hit_replaces(small_traversal):
    """Occupancy: a scan's hits, joined where neighbouring beams hit close together, are read
    as walls from the given pose, the grid points its beams cross short of their returns as
    free space, never a wall point; the map then reproduces the scan to within a grid spacing;
    a grid point is read once (what SVI learned since stays), and a later hit replaces a free
    reading by a wall's."""
    tr = small_traversal
    slam = insertion_slam(tr)
    inserter = slam.inserter
    assert isinstance(inserter, OccupancyInserter) and not inserter.inserted.any()
    z = first_scan(slam, tr)
    valid = torch.ones_like(slam.obs[0], dtype=torch.bool)
    b = slam.map_belief()
    walls, free = inserter.inserted.clone(), inserter.freed.clone()
    assert int(walls.sum()) > 20 and free.sum() > 3 * walls.sum() and not (walls & free).any()
    em, grid = slam.model.emission, slam.model.grid
    hit = slam.obs[0] < em.max_range * 0.999
    err = (em.read(grid, b.loc, z) - slam.obs[0])[hit].abs()
    assert err.median() < grid.size[0] / (grid.cells[0] - 1)  # within a grid spacing
    i, j = inserter.free_cells(slam.obs[0], valid, z)  # the sensor's own cell is free
    assert bool(free[i, j].all())
    with torch.no_grad():
        inserter.leaves.loc.fill_(0.5)  # as if SVI had moved every grid point
    inserter.insert(slam.obs[0], valid, z)
    assert float(slam.map_belief().loc.max()) == 0.5  # read once only
    # a hit where an earlier scan saw free space: beam 0 of a scan from a pose a tenth of the
    # range short of a free grid point, looking at it; the free reading is replaced by a wall's
    k, m = map(int, torch.nonzero(free)[len(torch.nonzero(free)) // 2])
    spacing = grid.size[0] / (grid.cells[0] - 1)
    point = torch.tensor([grid.origin[0] + k * spacing, grid.origin[1] + m * spacing])
    d = 0.1 * em.max_range
    z2 = torch.cat([point - torch.tensor([d, 0.0]), -em.beam_angles[:1]])  # beam 0 along +x
    x = torch.full_like(slam.obs[0], em.max_range)  # every other beam: no return
    x[0] = d
    inserter.insert(x, valid, z2)
    lam = 1 + 1 / NOISE**2
    expect = (0.5 * lam - FREE / NOISE**2 + WALL / NOISE**2) / lam  # free site out, wall in
    assert bool(inserter.inserted[k, m])
    assert float(slam.map_belief().loc[k, m, 0]) == pytest.approx(expect, abs=1e-4)


def test_placement_variance_is_handed_on_from_wall_to_pose(small_traversal):
    """Each grid point keeps the position variance of the pose its reading was placed from; a
    pose whose beams stop on those walls gets that variance, plus its share of the walls' own
    rounding, added to its world-frame std on x and y (not on the heading), and a pose looking
    at no inserted wall gets none."""
    tr = small_traversal
    slam = insertion_slam(tr)
    z = first_scan(slam, tr, var=4e-6)
    ins = slam.inserter
    assert torch.allclose(ins.placement[ins.walls], torch.tensor(4e-6, dtype=torch.float64))
    share = ins.placement_at(z) - 4e-6  # the rounding's share: several walls, less than one's
    assert ins.rounding / 6 < share < ins.rounding
    std = torch.tensor([1e-3, 1e-3, 1e-3])
    out, var = world_std(slam.inserter, z, std)
    assert var == pytest.approx(4e-6 + share, rel=1e-6)
    assert out[:2].tolist() == pytest.approx([math.sqrt(1e-6 + 4e-6 + share)] * 2, rel=1e-3)
    assert float(out[2]) == float(std[2])
    fresh = insertion_slam(tr)
    assert fresh.inserter.placement_at(z) == 0.0


def wall_stops(*walls):
    """Stops ``[B, 1, 2]`` (each beam certain, ``on [B, 1]``) of beams running along straight
    walls in order: each wall ``(a [2], b [2], beams)`` gets ``beams`` stops evenly from a to b,
    closer together than the inserter's ``gap``."""
    pts = [torch.stack([torch.linspace(a[i], b[i], n) for i in (0, 1)], -1) for a, b, n in walls]
    pts = torch.cat(pts).double()[:, None]
    return pts, torch.ones(pts.shape[:2], dtype=torch.float64)


def test_rounding_share_follows_the_walls_a_pose_is_fitted_to(small_traversal):
    """A wall's rounding (variance ``r = s^2 / 12`` per axis for spacing ``s``) shifts the wall
    along its normal; a pose fitted to one wall per axis moves with each (``r``), a second wall
    on one axis halves that axis's share (``0.75 r`` over the axes), and beams on one wall
    share its rounding (splitting a wall's beams into walls of their own would halve it)."""
    ins = insertion_slam(small_traversal).inserter
    r, z = ins.rounding, torch.zeros(3, dtype=torch.float64)
    assert r == pytest.approx(ins.spacing**2 / 12) and ins.spacing == pytest.approx(
        1 / 63, rel=0.02
    )
    east, north, west = (
        ((1, -0.03), (1, 0.03), 4),
        ((0.03, 1), (-0.03, 1), 4),
        ((-1, 0.03), (-1, -0.03), 4),
    )
    assert ins.rounding_at(z, *wall_stops(east, north)) == pytest.approx(r)
    assert ins.rounding_at(z, *wall_stops(east, north, west)) == pytest.approx(0.75 * r)
    apart = ((1, -0.3), (1, 0.3), 4)  # the same wall's stops, too far apart to be joined
    # about 0.625 r (x: four walls of one beam, y: one of four); the lone stops' normals are
    # their beams', a little turned
    assert 0.55 * r < ins.rounding_at(z, *wall_stops(apart, north)) < 0.7 * r
    pts, on = wall_stops(east, north)
    assert ins.rounding_at(z, pts, on * 0) == 0.0  # no beam stops on an inserted point


@pytest.mark.parametrize("kind", ["occupancy", "fusion"])
def test_online_slam_inserts_each_scan_from_its_steps_estimate(small_traversal, kind):
    """In the online sweep, scan ``t`` is inserted from the pose estimated at step ``t`` with
    that step's world-frame position variance: the inserter's sites are those of a replay of
    every scan placed at its step's estimate."""
    tr = small_traversal
    slam = insertion_slam(tr, kind)
    leaves = slam.inserter.leaves
    replay = make_inserter(
        slam.cfg.emission.insert,
        slam.model,
        type(leaves)(
            leaves.loc.detach().clone(), leaves.raw.detach().clone(), dist.constraints.positive
        ),
    )
    res = slam.run("online", progress=False)
    est = torch.as_tensor(res["filtered_mean"], dtype=slam.obs.dtype)  # the step's own estimate
    var = (res["filtered_std"][:, :2] ** 2).mean(1)  # its world-frame position variance
    valid = torch.ones_like(slam.obs[0], dtype=torch.bool)
    for t in range(est.shape[0]):
        replay.insert(slam.obs[t], valid, est[t], float(var[t]))
    for key in ("walls", "freed") if kind == "occupancy" else ("sdf", "weight", "placed"):
        assert torch.allclose(
            slam.inserter.state_dict()[key].double(), getattr(replay, key).double()
        )
        assert torch.equal(
            slam.state_dict()["components"]["inserter"][key], slam.inserter.state_dict()[key]
        )
    assert torch.allclose(slam.inserter.placement, replay.placement)
    assert replay.inserted.any()


@pytest.mark.slow
def test_prior_swap_reaches_map_and_planner():
    """A map prior N(0, 2^2) instead of N(0, 1), through the default preset's online SLAM: the
    inserted walls' belief moves towards the inverse sensor model's reading (a higher mean
    wall logit, as the wider prior weighs less against the same readings), and the planner,
    which counts a place as explored by its std relative to the prior's, finds the walls better
    known; each by more than the spread between two seeds of the same prior."""
    maze = make_maze("moderate-medium", 1)
    tr = simulate_traversal(maze, steps=300, seed=1)
    wide = dist.Normal(torch.zeros(1), 2.0 * torch.ones(1)).to_event(1)
    wall_mean, explored = {}, {}
    for name, prior in (("std", None), ("wide", wide)):
        for seed in (0, 1):
            slam = SLAM(tr, "manhattan", seed=seed, prior=prior)
            r = slam.run("online", progress=False)
            walls = slam.inserter.walls
            wall_mean[name, seed] = float(torch.as_tensor(r["map_loc"])[walls].mean())
            env = run_env(maze, tr, slam.cfg, r["map_loc"], r["map_scale"], r["mean"], prior=prior)
            i, j = torch.nonzero(walls).T
            g = slam.model.grid
            xy = np.stack(
                [
                    g.origin[0] + i * g.size[0] / (g.cells[0] - 1),
                    g.origin[1] + j * g.size[1] / (g.cells[1] - 1),
                ],
                -1,
            )
            explored[name, seed] = float(env.std(xy).mean())  # relative std at the walls
    for d, sign in ((wall_mean, 1), (explored, -1)):
        spread = max(abs(d["std", 0] - d["std", 1]), abs(d["wide", 0] - d["wide", 1]))
        moved = min(sign * (d["wide", s] - d["std", s]) for s in (0, 1))
        assert moved > spread, (d, moved, spread)


@pytest.mark.slow
def test_posterior_coverage():
    """The default preset's reported pose posterior covers the truth: over three runs of 1500
    steps in mazes that neither the tuning nor the test runs use (noise-free LiDAR), the
    fraction of steps (from step 100) whose true position lies in the reported 2-sigma ellipse
    is 0.6-0.98 (0.865 for a calibrated Gaussian). The cloud's own std, or the map's placement
    without the walls' rounding, covers well under half of them."""
    covered = []
    for maze_seed in (988, 989, 990):
        tr = simulate_traversal(make_maze("moderate-medium", maze_seed), steps=1500, seed=1)
        res = SLAM(tr, "manhattan", seed=1).run("online", progress=False)
        cal = calibration(res["std"], res["mean"], tr.poses, CALIBRATION_START)
        covered.append(cal["coverage_2sigma"])
    assert 0.6 <= np.mean(covered) <= 0.98, covered


def test_surface_points_are_every_grid_point_in_the_band_of_its_nearest_wall(small_traversal):
    """The walls' grid points, sampled along each wall, are those a brute force over the whole
    grid finds: every grid point within the band of a wall (``|d| <= band``, at most half a
    spacing past its ends), with the signed distance to its nearest such wall."""
    inserter = insertion_slam(small_traversal, "fusion").inserter
    w, h = inserter.model.grid.cells
    gen = torch.Generator().manual_seed(3)
    a = torch.rand(12, 2, generator=gen, dtype=torch.float64) * (w - 1)
    b = a + (torch.rand(12, 2, generator=gen, dtype=torch.float64) - 0.5) * 14  # up to ~10 long
    b[-3:] = a[-3:]  # isolated hits
    t = b - a
    n = torch.stack([t[:, 1], -t[:, 0]], -1) / t.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    n[-3:] = torch.tensor([0.6, 0.8], dtype=torch.float64)
    idx, d = inserter.surface_points(a, b, n)
    g = torch.stack(torch.meshgrid(torch.arange(w), torch.arange(h), indexing="ij"), -1)
    g = g.reshape(-1, 1, 2).double()  # [w h, 1, 2]
    ab = (b - a)[None]
    s = (((g - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-9)).clamp(0, 1)
    e = g - (a + s[..., None] * ab)  # [w h, W, 2]
    dist_n = (e * n).sum(-1)
    lateral = (e - dist_n[..., None] * n).norm(dim=-1)
    near = (dist_n.abs() <= inserter.band) & (lateral <= 0.5)  # [w h, W]
    best = torch.where(near, dist_n.abs(), math.inf).argmin(-1)  # [w h]
    want = near.any(-1).nonzero()[:, 0]
    assert len(want) > 200
    assert torch.equal(idx, want)
    assert torch.allclose(d, dist_n[want, best[want]])


def test_free_points_are_the_grid_points_along_each_beam_up_to_its_reach(small_traversal):
    """The free grid points of a scan are the grid points nearest to the points every half
    spacing along each valid beam, up to ``band + 0.5`` spacings before its hit (the whole
    range for a reading at the range), each once."""
    slam = insertion_slam(small_traversal, "fusion")
    inserter = slam.inserter
    em, (w, h) = inserter.model.emission, inserter.model.grid.cells
    x = slam.obs[5].clone()
    x[:3] = em.max_range  # readings at the range
    valid = torch.ones_like(x, dtype=torch.bool)
    valid[7] = False
    z = torch.as_tensor(small_traversal.poses[5], dtype=x.dtype)
    got = inserter.free_points(x, valid, z)
    want = set()
    step = 0.5 * inserter.spacing
    for b in range(len(x)):
        if not valid[b]:
            continue
        hit = float(x[b]) < em.max_range * (1 - 1e-3)
        reach = float(x[b]) - (inserter.band + 0.5) * inserter.spacing if hit else float(x[b])
        ang = z[2] + em.beam_angles[b].to(x.dtype)
        u = torch.stack([ang.cos(), ang.sin()])
        for k in range(int(em.max_range / step) + 2):
            if k * step > reach:
                break
            p = z[:2] + torch.tensor(k * step, dtype=x.dtype) * u
            i, j = inserter._to_grid(p).round().long().tolist()
            if 0 <= i < w and 0 <= j < h:
                want.add(i * h + j)
    assert len(want) > 50
    assert got.tolist() == sorted(want)
