"""The geometric camera read-out :class:`~pyro_slam.model.RayImageEmission`."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pyro
import pytest
import torch

from pyro_slam.geometry import wrap_angle
from pyro_slam.inference import ChunkBatch
from pyro_slam.model import MapBelief, MapGrid, RayEmission, RayImageEmission
from pyro_slam.slam import (
    SLAM,
    ConfigError,
    EmissionConfig,
    FilterConfig,
    HeadingConfig,
    OfflineConfig,
    TrainingConfig,
    TransitionConfig,
    build_model,
    loop,
    prepare_traversal,
    presets,
)
from pyro_slam.slam import (
    image_traversal as prepare_images,
)
from simulators import simulate_traversal
from simulators.camera import CEILING_ALBEDO, FLOOR_ALBEDO, Camera, CameraConfig

CFG = replace(
    presets.get("visual-raycast").config,
    emission=EmissionConfig("ray_camera", resolution=1 / 63),
    transition=TransitionConfig("kinematic"),
    filter=FilterConfig(proposal="transition"),
)
# a small SLAM run of the ray camera
SMALL = replace(
    CFG,
    filter=FilterConfig(particles=16, proposal="transition"),
    training=TrainingConfig(particles=4, chunks=2, every=1),
    offline=OfflineConfig(rounds=1, svi_steps=4),
)


def ray_camera(tr, samples: int = 48, bins: int = 8) -> RayImageEmission:
    """The ray camera for ``tr``'s frames: ``samples`` points per ray, ``bins`` albedo
    directions per cell."""
    prep = prepare_images(tr)
    rows, cols = prep.metadata["image_shape"]
    return RayImageEmission(prep.beam_angles[:cols], rows, prep.max_range, samples, bins)


@pytest.fixture(scope="module")
def image_traversal():
    return simulate_traversal("moderate-medium", steps=60, seed=3, images=True)


def oracle(tr, albedo: float = 0.6):
    """The model with the simulator camera's constants, a wall map of uniform ``albedo`` and the
    same scene rendered by the simulator with every wall face at that albedo."""
    prep = prepare_traversal(tr, CFG)
    model, _ = build_model(prep, CFG)
    em = model.emission
    cam_cfg, w = CameraConfig(), tr.metadata["maze"]["corridor_width"]
    cam = Camera(tr.walls, w, None, cam_cfg)
    cam.albedo[:] = albedo
    occ = RayEmission.wall_map(model.grid, tr.walls)  # [w, h, 1]
    logit = math.log(albedo / (1 - albedo))
    M = torch.cat([occ, torch.full((*occ.shape[:2], em.bins), logit)], -1)
    y = torch.arange(em.rows) + 0.5 - em.rows / 2  # pixel offset from the horizon
    above, below = (cam_cfg.wall_height - cam_cfg.eye_height) * w, cam_cfg.eye_height * w
    plane = torch.where(y < 0, above, below) * em.focal / y.abs()
    fog = cam_cfg.fog * w
    with torch.no_grad():
        em.log_height.copy_(torch.tensor([above, below]).log())
        em.log_fog.fill_(math.log(fog))
        em.background.copy_(torch.where(y < 0, CEILING_ALBEDO, FLOOR_ALBEDO) / (1 + plane / fog))
    return model, M, cam


def test_shapes_and_config_wiring(image_traversal):
    prep = prepare_traversal(image_traversal, CFG)
    assert CFG.emission.observation == "image" and prep.metadata["image_shape"] == [24, 32]
    model, _ = build_model(prep, CFG)
    assert isinstance(model.emission, RayImageEmission) and model.emission.map_dim == 9
    model, guide = build_model(prep, CFG, emission=ray_camera(image_traversal, bins=4))
    em = model.emission
    assert isinstance(em, RayImageEmission)
    assert em.map_dim == 5 and guide.shape == (*model.grid.cells, 5)
    assert em.event_shape == (24, 32) and em.max_range == 1.0
    # the simulator's 90 degree camera: f = 16 / tan(45 deg) = 16 pixels
    assert em.focal == pytest.approx(16.0, rel=1e-6)
    z = torch.as_tensor(image_traversal.poses[:6], dtype=torch.float32).reshape(2, 3, 3)
    assert model.emission_mean(torch.zeros(guide.shape), z).shape == (2, 3, 24 * 32)
    with pytest.raises(ConfigError, match="emission.kind must be one of"):
        EmissionConfig("nerf")


def test_oracle_map_reproduces_simulated_images(image_traversal):
    tr = image_traversal
    model, M, cam = oracle(tr)
    z = torch.as_tensor(tr.poses, dtype=torch.float32)
    with torch.no_grad():
        pred = model.emission_mean(M, z).reshape(len(z), 24, 32)
    true = torch.as_tensor(cam.render(tr.poses))
    err = (pred - true).abs()
    # the geometry (wall rows, fog, floor and ceiling) is right; the mean is the blur at wall
    # edges, where a column's expected depth mixes two walls (images' own std: 0.085)
    assert float(true.std()) > 0.07
    assert err.median() < 0.01 and err.mean() < 0.04
    # the prior map (free space) draws no near walls: far worse
    with torch.no_grad():
        free = model.emission_mean(torch.zeros_like(M), z).reshape(pred.shape)
    assert (free - true).abs().mean() > 3 * err.mean()


def test_turning_by_one_column_shifts_the_rays_by_one_column(image_traversal):
    model, M, _ = oracle(image_traversal)
    em, grid = model.emission, model.grid
    z = torch.as_tensor(image_traversal.poses[10:14], dtype=torch.float32)
    step = math.pi / 2 / 32
    r0 = em.expected_range(grid, M, z)  # [4, 32] left to right
    r1 = em.expected_range(grid, M, z + torch.tensor([0.0, 0.0, step]))  # turned left
    torch.testing.assert_close(r1[:, 1:], r0[:, :-1], atol=2e-4, rtol=0)


def test_albedo_is_read_at_the_ray_direction():
    # one wall cell seen from the west (ray heading east, bin 0) and from the east (bin 4)
    grid = MapGrid((41, 41), 1 + 8, (0.0, 0.0), (1.0, 1.0))
    occ = RayEmission.wall_map(grid, torch.tensor([[0.5, 0.0, 0.5, 1.0]]))
    alb = torch.zeros(41, 41, 8)
    alb[..., 0], alb[..., 4] = 3.0, -3.0  # bright seen heading east, dark heading west
    M = torch.cat([occ, alb], -1)
    em = RayImageEmission(torch.tensor([0.1, 0.0, -0.1]), rows=24, max_range=1.0, samples=100)
    with torch.no_grad():
        img = em.read(grid, M, torch.tensor([[0.3, 0.5, 0.0], [0.7, 0.5, math.pi]]))
    centre = img.reshape(2, 24, 3)[:, 12, 1]  # the middle column's horizon row: on the wall
    dim = 1 + 0.2 / math.exp(em.log_fog.item())  # the wall is 0.2 away
    s = 1 / (1 + math.exp(-3.0))
    assert centre.tolist() == pytest.approx([s / dim, (1 - s) / dim], abs=0.02)


def test_gradients_reach_occupancy_albedo_and_camera_constants(image_traversal):
    torch.manual_seed(0)
    slam = SLAM(image_traversal, SMALL)
    loop.filter_pass(slam.components, slam.state, slam.data, False, "fill cache")
    with slam.scope():
        loss = slam.elbo.differentiable_loss(
            slam.model.model, slam.guide, ChunkBatch(torch.tensor([0, 20]), 4)
        )
        assert torch.isfinite(loss)
        loss.backward()
        g = pyro.get_param_store()["map_loc"].grad
    assert g is not None and torch.isfinite(g).all()
    assert g[..., 0].abs().sum() > 0 and g[..., 1:].abs().sum() > 0
    em = slam.model.emission
    for p in (em.log_height, em.log_fog, em.background):
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    res = slam.run("offline", progress=False)
    assert res["mean"].shape == (60, 3) and np.isfinite(res["mean"]).all()
    assert res["map_loc"].shape[-1] == 9
    assert len(res["losses"]) == 60 - 4 + 1 + 4  # the online sweep's SVI steps, then 4 offline


def test_unknownness_reads_the_occupancy_where_rays_stop_not_the_wall_albedo(image_traversal):
    prep = prepare_traversal(image_traversal, CFG)
    model, guide = build_model(prep, CFG)
    # occupancy mapped everywhere (std 0.1), albedo only where rays stop: still the prior's std
    scale = torch.ones(guide.shape)
    scale[..., 0] = 0.1
    belief = MapBelief(torch.zeros(guide.shape), scale)
    z = torch.as_tensor(image_traversal.poses[:5], dtype=torch.float32)
    mean, v = model.emission.read_moments(model.grid, belief.loc, belief.scale, z)
    rows, cols = model.emission.rows, model.emission.cols
    assert mean.shape == v.shape == (5, rows * cols)
    torch.testing.assert_close(v, torch.full((5, rows * cols), 0.01))
    # each pixel is as unknown as its column's ray: unmapped occupancy makes it unknown
    belief.scale[..., 0] = 1.0
    v = model.emission.read_moments(model.grid, belief.loc, belief.scale, z)[1]
    torch.testing.assert_close(v, torch.ones(5, rows * cols))


def test_heading_observation_from_images(image_traversal):
    """The heading observation on camera frames: the walls' edges give each frame's heading modulo
    pi / 2 (``geometry.image_wall_direction``), and the online filter's heading stays at the
    truth where the same run without it drifts."""
    tr = image_traversal
    # the run the measured numbers below come from keeps 4 particles per step in the cache
    training = TrainingConfig(particles=4, cache_particles=4, every=1)
    base = replace(CFG, filter=FilterConfig(particles=32, proposal="transition"), training=training)
    on = replace(base, heading=HeadingConfig(sigma=1e-3))
    slam = SLAM(tr, on, emission=ray_camera(tr, samples=24), learn_emission=True)
    e = slam.heading.evidence()  # wall directions [T], nan: no walls agree
    value = torch.remainder(e.frame - e.direction, math.pi / 2)  # the heading mod pi / 2
    seen = ~value.isnan()
    assert float(seen.double().mean()) > 0.8
    r = torch.remainder(torch.as_tensor(tr.poses[:, 2]) - value + math.pi / 4, math.pi / 2)
    # relative to the walls' frame estimated from the frames (off by 0.0014 rad here)
    assert float((r[seen] - math.pi / 4).abs().max()) < 2e-3
    err = {}
    for name, cfg in (("off", base), ("on", on)):
        slam = SLAM(tr, cfg, emission=ray_camera(tr, samples=24), learn_emission=True)
        res = slam.run("online", progress=False)
        err[name] = wrap_angle(torch.as_tensor(res["mean"][:, 2] - tr.poses[:, 2])).abs()  # [T]
    assert float(err["on"][seen].max()) < 0.005  # measured 0.0022
    # where the walls are seen, the run without the factor drifts from the truth
    assert float(err["off"][seen].max()) > 3 * float(err["on"][seen].max())
