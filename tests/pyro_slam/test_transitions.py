"""Engineered and learned transitions: semantics, pre-training, save/load round trip."""

import math

import pytest
import torch

from pyro_slam.model import KinematicTransition, LearnedTransition, pretrain_transition
from pyro_slam.slam import path_integration
from simulators import simulate_traversal


def test_kinematic_rotates_then_moves():
    t = KinematicTransition(1e-3)
    z = torch.tensor([0.5, 0.5, 0.0])
    out = t.mean(z, torch.tensor([math.pi / 2, 0.1]))
    torch.testing.assert_close(out, torch.tensor([0.5, 0.6, math.pi / 2]))


def test_kinematic_odometry_delta_is_robot_frame():
    t = KinematicTransition(1e-3, "odometry_delta")
    z = torch.tensor([1.0, 2.0, math.pi / 2])
    out = t.mean(z, torch.tensor([0.1, 0.0, 0.2]))  # 0.1 forward along +y
    torch.testing.assert_close(out, torch.tensor([1.0, 2.1, math.pi / 2 + 0.2]))


def test_kinematic_clip_stops_before_wall():
    t = KinematicTransition(1e-3, clip_margin=0.01)
    z = torch.tensor([0.0, 0.0, 0.0])
    scan = torch.full((20,), 0.5)
    scan[t.forward_beam] = 0.03
    out = t.mean(z, torch.tensor([0.0, 0.1]), scan)
    torch.testing.assert_close(out, torch.tensor([0.02, 0.0, 0.0]))


@pytest.fixture(scope="module")
def trained():
    torch.manual_seed(0)
    tr = simulate_traversal("moderate-medium", steps=1500, seed=5)
    return tr, pretrain_transition([tr], epochs=4, progress=False)


def test_pretrained_residual_transition_is_accurate(trained):
    tr, (lt, stats) = trained
    assert lt.base_control_model == "rotate_forward"
    # the learned noise is of the order of the simulator's actuation noise (6e-3 rad / step)
    assert 1e-3 < stats["sigma"][2] < 2e-2
    assert all(0 < s < 2e-3 for s in stats["sigma"][:2])
    # one-step predictions on the training traversal: position error well below a step length
    z = torch.as_tensor(tr.poses[:-1], dtype=torch.float32)
    u = torch.as_tensor(tr.controls, dtype=torch.float32)
    x = torch.as_tensor(tr.observations[:-1], dtype=torch.float32)
    pred = lt.mean(z, u, x)
    err = (pred[:, :2] - torch.as_tensor(tr.poses[1:, :2], dtype=torch.float32)).norm(dim=-1)
    assert err.mean() < 1e-3


def test_learned_transition_state_round_trip(trained):
    tr, (lt, _) = trained
    back = LearnedTransition.from_state(lt.to_state())
    z, u, x = torch.rand(5, 3), torch.rand(5, 2) * 0.01, torch.rand(5, 20) * 0.5
    torch.testing.assert_close(back.mean(z, u, x), lt.mean(z, u, x))
    torch.testing.assert_close(back.sigma, lt.sigma)
    pi = path_integration(tr, back)
    assert pi.shape == (tr.num_steps, 3)


def test_learned_transition_needs_scan(trained):
    _, (lt, _) = trained
    with pytest.raises(ValueError, match="predicted scan"):
        lt.mean(torch.zeros(3), torch.zeros(2), None)
