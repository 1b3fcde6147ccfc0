"""The visual DVBF-LM emission (paper Appendix B-D): shapes, rotation, row sharing, SLAM."""

import math
from dataclasses import replace

import numpy as np
import pyro
import pytest
import torch

from pyro_slam.inference import ChunkBatch
from pyro_slam.model import DVBFLM, ImageEmission, KinematicTransition, MapGrid
from pyro_slam.slam import (
    SLAM,
    EmissionConfig,
    FilterConfig,
    OfflineConfig,
    SLAMConfig,
    TrainingConfig,
    loop,
    prepare_traversal,
    presets,
)
from pyro_slam.slam import (
    image_traversal as prepare_images,
)

ROWS, COLS, BINS = 6, 8, 16


def small(**kw):
    torch.manual_seed(0)
    return ImageEmission(BINS, ROWS, COLS, hidden=kw.pop("hidden", 16), **kw)


def test_shapes_and_model_wiring():
    em = small(layers=2)
    assert em.map_dim == BINS * ROWS and em.event_shape == (ROWS, COLS)
    m = torch.randn(5, 4, em.map_dim)
    z = torch.randn(5, 4, 3)
    assert em.view(m, z[..., 2]).shape == (5, 4, ROWS, COLS)
    assert em(m, z[..., 2]).shape == (5, 4, ROWS, COLS)
    assert em.mean(m, z).shape == (5, 4, ROWS * COLS)
    grid = MapGrid((5, 5), em.map_dim)
    model = DVBFLM(grid, em, KinematicTransition(0.01))
    M = torch.randn(grid.shape)
    zz = torch.rand(7, 3)
    assert model.emission_mean(M, zz).shape == (7, ROWS * COLS)
    assert model.beam_angles is None
    with pytest.raises(ValueError, match="D_m"):
        DVBFLM(MapGrid((5, 5), 10), em, KinematicTransition(0.01))


def test_turning_by_one_column_shifts_the_image_by_one_column():
    fov = math.pi / 2
    em = small(layers=0, fov=fov)  # one linear layer per row: set it to the identity
    with torch.no_grad():
        em.weights[0].copy_(torch.eye(COLS).expand(em.num_nets, COLS, COLS))
        em.biases[0].zero_()
    m = torch.randn(3, em.map_dim)
    h = torch.tensor([0.3, -2.0, 3.1])
    step = fov / COLS  # the angle between neighbouring image columns
    img = em(m, h)
    left = em(m, h + step)  # turning left moves the scene to the right
    torch.testing.assert_close(left[..., 1:], img[..., :-1])
    # a full angular bin of the map: the view moves by bins -> columns of the same bin width
    em2 = small(layers=2, fov=fov)
    v0 = em2.view(m, h)
    v1 = em2.view(m, h + step)
    torch.testing.assert_close(v1[..., 1:], v0[..., :-1])
    # with the columns spaced like the map's bins, a bin turn is exactly a column shift, and the
    # view at a bin-aligned heading reads the map's bins themselves
    em3 = ImageEmission(BINS, ROWS, 4, column_angles=2 * math.pi / BINS * torch.arange(4.0))
    bins = m.unflatten(-1, (BINS, ROWS)).transpose(-1, -2)  # [3, rows, bins]
    torch.testing.assert_close(em3.view(m, torch.zeros(3)), bins[..., :4])
    torch.testing.assert_close(em3.view(m, torch.full((3,), 2 * math.pi / BINS)), bins[..., 1:5])


def test_rows_share_networks_top_bottom_mirrored():
    em = small(layers=2)
    assert em.num_nets == ROWS // 2 and len(em.weights) == 3
    assert em.net_of_row.tolist() == [0, 1, 2, 2, 1, 0]
    # rows of the view that mirror each other give mirrored image rows
    v = torch.randn(4, ROWS // 2, COLS)
    v = torch.cat([v, v.flip(-2)], -2)
    out = em.rows_mlp(v)
    torch.testing.assert_close(out, out.flip(-2))
    # changing network 0 changes the top and the bottom row only
    v = torch.randn(4, ROWS, COLS)
    with torch.no_grad():
        before = em.rows_mlp(v)
        em.biases[-1][0] += 1.0
        diff = (em.rows_mlp(v) - before).abs().amax((0, 2))
    assert diff[0] > 0.5 and diff[-1] > 0.5 and float(diff[1:-1].max()) == 0.0


def image_traversal(steps=40):
    from simulators import simulate_traversal

    return simulate_traversal("moderate-medium", steps=steps, seed=3, images=True)


CFG = replace(
    presets.get("visual").config,
    emission=EmissionConfig("image_mlp", resolution=1 / 6),
    filter=FilterConfig(particles=16, proposal="transition"),
    training=TrainingConfig(particles=4, chunks=2, every=1),
    offline=OfflineConfig(rounds=1, svi_steps=4),
)


def small_slam(tr) -> SLAM:
    """SLAM with the test configuration and a small visual emission (8 angular bins, 2 x 16
    row networks, initial weights from seed 0) that it learns."""
    prep = prepare_images(tr)
    torch.manual_seed(0)
    rows, cols = prep.metadata["image_shape"]
    em = ImageEmission(8, rows, cols, hidden=16, layers=2, column_angles=prep.beam_angles[:cols])
    return SLAM(tr, CFG, emission=em, learn_emission=True)


def test_prepared_image_traversal():
    tr = image_traversal(5)
    image = SLAMConfig(emission=EmissionConfig("image_mlp"))
    prep = prepare_traversal(tr, image)
    assert prep.observations.shape == (5, 24 * 32)
    np.testing.assert_array_equal(prep.observations[2].reshape(24, 32), tr.images[2])
    assert prep.metadata["image_shape"] == [24, 32]
    assert prepare_traversal(prep, image) is prep


def test_gradients_reach_map_and_emission_through_particle_elbo():
    slam = small_slam(image_traversal())
    assert isinstance(slam.model.emission, ImageEmission)
    loop.filter_pass(slam.components, slam.state, slam.data, False, "fill cache")
    with slam.scope():
        loss = slam.elbo.differentiable_loss(
            slam.model.model, slam.guide, ChunkBatch(torch.tensor([0, 20]), 4)
        )
        assert torch.isfinite(loss)
        loss.backward()
        g_map = pyro.get_param_store()["map_loc"].grad
    assert g_map is not None and torch.isfinite(g_map).all() and g_map.abs().sum() > 0
    for p in slam.model.emission.parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all()
    assert slam.model.emission.weights[0].grad.abs().sum() > 0


def test_tiny_visual_slam_run_is_finite():
    slam = small_slam(image_traversal())
    assert slam.model.learn_emission
    res = slam.run("offline", progress=False)
    assert res["mean"].shape == (40, 3) and np.isfinite(res["mean"]).all()
    # the online sweep's SVI steps (from step chunk_length - 1 on), then 4 offline ones
    assert np.isfinite(res["losses"]).all() and len(res["losses"]) == 40 - 4 + 1 + 4
    assert res["map_loc"].shape[-1] == 8 * 24
