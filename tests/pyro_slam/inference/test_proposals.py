"""Pose proposals as SMC guides (:mod:`pyro_slam.inference.proposals`): their densities are
the distributions they sample, and the scan-matching proposal puts the particles where the scan
and the map agree, its importance weights keeping the model's posterior."""

from __future__ import annotations

import math

import torch
from torch.distributions import MultivariateNormal, Normal

from pyro_slam.inference import ParticleFilter, Particles, TransitionProposal
from pyro_slam.inference.proposals import MatchedProposal, PoseProposal, ScanMatchProposal
from pyro_slam.model import (
    DVBFLM,
    HeadingEvidence,
    KinematicTransition,
    MapBelief,
    MapGrid,
    RayEmission,
    WallHeading,
)


def test_the_proposals_densities_are_the_mixtures_they_sample():
    g = torch.Generator().manual_seed(0)
    loc, scale = torch.tensor([[0.1, 0.2, 0.3]]), torch.tensor([[0.01, 0.02, 0.05]])
    mu = torch.tensor([[0.12, 0.19, 0.25]])
    cov = torch.tensor([[[1e-4, 2e-5, 0.0], [2e-5, 4e-5, 1e-5], [0.0, 1e-5, 4e-4]]])
    q = MatchedProposal(loc, scale, mu, cov, defensive=0.2)
    z = q.sample((20000,), generator=g)[:, 0]  # [N, 3]
    expect = torch.logaddexp(
        math.log(0.2) + Normal(loc[0], scale[0]).log_prob(z).sum(-1),
        math.log(0.8) + MultivariateNormal(mu[0], cov[0]).log_prob(z),
    )
    torch.testing.assert_close(q.log_prob(z[:, None])[:, 0], expect, rtol=1e-5, atol=1e-4)
    mean = 0.2 * loc[0] + 0.8 * mu[0]
    assert torch.allclose(z.mean(0), mean, atol=2e-3)
    # the heading mixture of PoseProposal: weight w on the alternative component
    p = PoseProposal(loc, scale, torch.tensor([0.5]), torch.tensor([0.01]), torch.tensor([0.7]))
    h = p.sample((20000,), generator=g)[:, 0, 2]
    assert abs(float((h > 0.45).float().mean()) - 0.7) < 0.02
    x = torch.tensor([[0.1, 0.2, 0.5]])
    want = Normal(loc[0, :2], scale[0, :2]).log_prob(x[0, :2]).sum() + torch.logaddexp(
        math.log(0.7) + Normal(0.5, 0.01).log_prob(torch.tensor(0.5)),
        math.log(0.3) + Normal(0.3, 0.05).log_prob(torch.tensor(0.5)),
    )
    torch.testing.assert_close(p.log_prob(x)[0], want)


def _room():
    """A 1 x 1 room with walls on all four sides and one across at x = 0.6, on a 64 x 64 grid;
    a ray-cast LiDAR of 24 beams and a kinematic odometry transition."""
    walls = [[0, 0, 1, 0], [1, 0, 1, 1], [1, 1, 0, 1], [0, 1, 0, 0], [0.6, 0.2, 0.6, 0.8]]
    grid = MapGrid((64, 64), 1, (0.0, 0.0), (1.0, 1.0))
    em = RayEmission(2 * math.pi * torch.arange(24) / 24, max_range=0.8, samples=160)
    trans = KinematicTransition((0.02, 0.02, 0.05), "odometry_delta")
    model = DVBFLM(grid, em, trans, sigma_emission=0.02, outlier_prob=0.05, outlier_range=0.8)
    M = RayEmission.wall_map(grid, torch.tensor(walls, dtype=torch.float32))
    return model, MapBelief(M, torch.full_like(M, 0.05))


def test_scan_matching_puts_few_particles_where_the_scan_fits():
    """From particles whose odometry is off by (0.03, -0.02, 0.04), the scan-matching proposal
    lands the cloud near the pose the scan was taken at (its particles within 1 cm), which the
    transition (bootstrap) proposal with the same 16 particles does not; the weighted estimate
    targets the model's posterior either way, so the gain is in accuracy, not in the target."""
    model, belief = _room()
    truth = torch.tensor([0.35, 0.45, 0.3])
    x = model.emission_mean(belief.loc, truth)  # [24] the scan at the true pose
    prev = truth - torch.tensor([0.03, -0.02, 0.04])  # the odometry's error
    K = 16
    err = {"match": [], "transition": []}
    for seed in range(6):
        g = torch.Generator().manual_seed(seed)
        start = prev + torch.tensor([0.005, 0.005, 0.01]) * torch.randn(K, 3, generator=g)
        p = Particles(start, torch.full((K,), -math.log(K)))
        for name, proposal in (
            ("match", ScanMatchProposal()),
            ("transition", TransitionProposal()),
        ):
            pf = ParticleFilter(model, proposal, torch.Generator().manual_seed(seed))
            new, _ = pf.step(p, belief, x, torch.zeros(3), step=1)
            err[name].append(float((new.mean()[:2] - truth[:2]).norm()))
            if name == "match":  # the particles themselves sit at the pose
                assert float((new.z[:, :2] - truth[:2]).norm(dim=-1).median()) < 0.01
    assert max(err["match"]) < 0.008, err  # measured <= 0.0051
    assert sum(err["match"]) < 0.5 * sum(err["transition"]), err


def test_scan_matching_pulls_a_far_heading_to_the_wall_direction():
    """With a heading factor of no outliers and a direction seen with std 0.001 rad, a single
    path (a Pyro guide's) whose heading is 0.02 rad (20 std) off is matched to the heading the
    direction says (the factor's weight is a whole 1 / sigma^2, not a 0 / 0 where its Gaussian
    underflows), not handed back to the transition, where nothing would bring it back; a
    cloud that far off is proposed by the transition, whose spread its weights choose from."""
    model, belief = _room()
    model.heading = WallHeading(period=math.pi / 2, outlier_prob=0.0)
    truth = torch.tensor([0.35, 0.45, 0.3])
    x = model.emission_mean(belief.loc, truth)
    seen = HeadingEvidence(torch.tensor(0.0), 0.001, frame=0.3)  # frame - direction = 0.3
    prev = truth - torch.tensor([0.0, 0.0, 0.02])
    scan = model.emission_mean(belief.loc, prev)
    q = ScanMatchProposal().dist(model, prev, scan, torch.zeros(3), x=x, M=belief, heading=seen)
    assert isinstance(q, MatchedProposal)
    assert abs(float(q.mu[2]) - 0.3) < 0.002, q.mu
    cloud = prev + torch.zeros(8, 3)
    scans = model.emission_mean(belief.loc, cloud)
    q = ScanMatchProposal().dist(
        model, cloud, scans, torch.zeros(3), x=x, M=belief, heading=seen.per_particle()
    )
    assert isinstance(q, PoseProposal)
