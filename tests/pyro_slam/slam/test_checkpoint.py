"""Checkpoints: a resume is refused under another map prior or emission noise, named or
passed in as an object."""

from __future__ import annotations

import functools

import pyro.distributions as dist
import pytest
import torch
from small_slam import SMALL

from pyro_slam.slam import SLAM, with_overrides
from pyro_slam.slam.checkpoint import CheckpointError
from simulators import simulate_traversal

STEPS = 6


@pytest.fixture(scope="module")
def traversal():
    return simulate_traversal("simple-small", steps=STEPS, seed=0)


def _wide():
    return dist.Normal(torch.zeros(1), torch.full((1,), 2.0)).to_event(1)


def _checkpoint(tr, path, config=SMALL, **kw):
    """Run ``config`` on ``tr`` to its end, writing its final checkpoint to ``path``."""
    SLAM(tr, config, checkpoint=path, checkpoint_every=100, **kw).run("online", progress=False)
    return path


def test_resume_refuses_another_prior(traversal, tmp_path):
    ckpt = _checkpoint(traversal, tmp_path / "wide.pt", prior=_wide())
    with pytest.raises(CheckpointError, match=r"prior \(.*scale=\[2\.0\].* in the checkpoint"):
        SLAM(traversal, SMALL).resume(ckpt)
    SLAM(traversal, SMALL, prior=_wide()).resume(ckpt)  # an equal prior resumes
    named = with_overrides(SMALL, {"emission": {"prior": "wide"}})
    with pytest.raises(CheckpointError, match=r"config emission\.prior \('wide' in the"):
        SLAM(traversal, SMALL).resume(_checkpoint(traversal, tmp_path / "named.pt", named))


def test_resume_refuses_another_noise(traversal, tmp_path):
    student = functools.partial(dist.StudentT, 3.0)
    ckpt = _checkpoint(traversal, tmp_path / "t.pt", noise=student)
    with pytest.raises(CheckpointError, match=r"noise \('StudentT\(3\.0\)' in the checkpoint"):
        SLAM(traversal, SMALL).resume(ckpt)
    named = with_overrides(SMALL, {"emission": {"noise": "student-t"}})
    with pytest.raises(CheckpointError, match=r"config emission\.noise"):
        SLAM(traversal, named).resume(ckpt)


def test_named_priors_and_noises_build_the_models_factors(traversal):
    default = SLAM(traversal, SMALL)
    assert default.model.prior is None and default.model.noise is dist.Normal
    cfg = with_overrides(SMALL, {"emission": {"prior": "wide", "noise": "student-t"}})
    slam = SLAM(traversal, cfg)
    torch.testing.assert_close(slam.model.prior_std(), torch.full((1,), 2.0))
    d = slam.model.noise_dist(torch.zeros(3))
    assert isinstance(d, dist.StudentT) and bool((d.df == 3.0).all())
    student = SLAM(traversal, with_overrides(SMALL, {"emission": {"prior": "student-t"}}))
    torch.testing.assert_close(student.model.prior_std(), torch.full((1,), 2.0).sqrt())
