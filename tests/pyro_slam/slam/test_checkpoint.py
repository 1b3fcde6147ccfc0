"""Checkpoints (:mod:`pyro_slam.slam.checkpoint`): a resumed run reproduces the uninterrupted
one, also after SIGKILL; writes are atomic; a resume is refused under another map prior or
emission noise, named or passed in as an object."""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import sys
import textwrap

import pyro.distributions as dist
import pytest
import torch
from slam_runs import (
    CHECKPOINT_EVERY,
    CONFIG,
    HIDDEN,
    LAYERS,
    MAP_DIM,
    RAYCAST,
    REPO,
    STEPS,
    Crash,
    assert_same_run,
    crash_after_save,
    make_slam,
)
from small_slam import SMALL

from pyro_slam.slam import SLAM, checkpoint, with_overrides
from pyro_slam.slam.checkpoint import CheckpointError
from simulators import simulate_traversal


@pytest.fixture(scope="module")
def traversal():
    return simulate_traversal("simple-small", steps=STEPS, seed=0)


@pytest.fixture(scope="module")
def short():
    return simulate_traversal("simple-small", steps=6, seed=0)


def _wide():
    return dist.Normal(torch.zeros(1), torch.full((1,), 2.0)).to_event(1)


def _checkpoint(tr, path, config=SMALL, **kw):
    """Run ``config`` on ``tr`` to its end, writing its final checkpoint to ``path``."""
    SLAM(tr, config, checkpoint=path, checkpoint_every=100, **kw).run("online", progress=False)
    return path


def test_resume_refuses_another_prior(short, tmp_path):
    ckpt = _checkpoint(short, tmp_path / "wide.pt", prior=_wide())
    with pytest.raises(CheckpointError, match=r"prior \(.*scale=\[2\.0\].* in the checkpoint"):
        SLAM(short, SMALL).resume(ckpt)
    SLAM(short, SMALL, prior=_wide()).resume(ckpt)  # an equal prior resumes
    named = with_overrides(SMALL, {"emission": {"prior": "wide"}})
    with pytest.raises(CheckpointError, match=r"config emission\.prior \('wide' in the"):
        SLAM(short, SMALL).resume(_checkpoint(short, tmp_path / "named.pt", named))


def test_resume_refuses_another_noise(short, tmp_path):
    student = functools.partial(dist.StudentT, 3.0)
    ckpt = _checkpoint(short, tmp_path / "t.pt", noise=student)
    with pytest.raises(CheckpointError, match=r"noise \('StudentT\(3\.0\)' in the checkpoint"):
        SLAM(short, SMALL).resume(ckpt)
    named = with_overrides(SMALL, {"emission": {"noise": "student-t"}})
    with pytest.raises(CheckpointError, match=r"config emission\.noise"):
        SLAM(short, named).resume(ckpt)


def test_named_priors_and_noises_build_the_models_factors(short):
    default = SLAM(short, SMALL)
    assert default.model.prior is None and default.model.noise is dist.Normal
    cfg = with_overrides(SMALL, {"emission": {"prior": "wide", "noise": "student-t"}})
    slam = SLAM(short, cfg)
    torch.testing.assert_close(slam.model.prior_std(), torch.full((1,), 2.0))
    d = slam.model.noise_dist(torch.zeros(3))
    assert isinstance(d, dist.StudentT) and bool((d.df == 3.0).all())
    student = SLAM(short, with_overrides(SMALL, {"emission": {"prior": "student-t"}}))
    torch.testing.assert_close(student.model.prior_std(), torch.full((1,), 2.0).sqrt())


@pytest.mark.parametrize(
    "mode, crash_at, over",
    [
        ("online", 2, {}),  # online, after step 14
        ("offline", 2, {}),  # inside the online sweep that starts offline SLAM
        ("offline", 5, {}),  # between the two offline rounds
        ("offline", 7, {}),  # after the final checkpoint: nothing is redone
        ("offline", 5, {"transition": {"scale": [3.0, 3.0, 0.2]}}),  # scaled once, not on resume
        ("offline", 5, {"offline": {"estimate": "cache"}}),  # between rounds without filter passes
        ("online", 2, RAYCAST),  # the scan inserter's record of written cells is restored
        # the heading factor's frame guide, refined online, and the scan-matching proposal
        ("online", 2, {"heading": {"sigma": 1e-3}, "filter": {"proposal": "scan-match"}}),
    ],
)
def test_resume_reproduces_uninterrupted_run(traversal, tmp_path, mode, crash_at, over):
    ref = make_slam(traversal, over)
    r_ref = ref.run(mode, progress=False)

    ckpt = tmp_path / "ckpt.pt"
    first = make_slam(traversal, over, checkpoint=ckpt)
    crash_after_save(first, crash_at)
    with pytest.raises(Crash):
        first.run(mode, progress=False)
    del first

    resumed = make_slam(traversal, over, checkpoint=ckpt).resume(ckpt)
    assert 0 < resumed.state.t or resumed.state.round > 0 or resumed.state.phase != "online"
    if resumed.inserter is not None:
        assert resumed.inserter.inserted.any()
    r_res = resumed.run(mode, progress=False)
    assert_same_run(ref, r_ref, resumed, r_res)
    if ref.inserter is not None:
        assert torch.equal(ref.inserter.inserted, resumed.inserter.inserted)


def test_resume_after_sigkill(traversal, tmp_path):
    """A process killed with SIGKILL right after a checkpoint resumes to the same result."""
    ckpt = tmp_path / "ckpt.pt"
    script = textwrap.dedent(
        f"""
        import os, signal, torch
        torch.set_num_threads(1)
        from simulators import simulate_traversal
        from pyro_slam.model import EmissionMLP
        from pyro_slam.slam import SLAM, from_dict
        tr = simulate_traversal("simple-small", steps={STEPS}, seed=0)
        torch.manual_seed(0)
        emission = EmissionMLP({MAP_DIM}, max(tr.num_beams, 20), hidden={HIDDEN},
                               layers={LAYERS}, scale=tr.max_range)
        slam = SLAM(tr, from_dict({CONFIG.to_dict()!r}), emission=emission,
                    learn_emission=True, checkpoint={str(ckpt)!r},
                    checkpoint_every={CHECKPOINT_EVERY})
        save = slam.save
        def hooked(path):
            save(path)
            if slam.state.t == 14:
                os.kill(os.getpid(), signal.SIGKILL)
        slam.save = hooked
        slam.run("online", progress=False)
        """
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()[-2000:]
    ref = make_slam(traversal)
    r_ref = ref.run("online", False)
    resumed = make_slam(traversal, checkpoint=ckpt).resume(ckpt)
    assert resumed.state.t == 14 and resumed.state.phase == "online"
    assert_same_run(ref, r_ref, resumed, resumed.run("online", False))


def test_checkpoint_writes_are_atomic(traversal, tmp_path, monkeypatch):
    ckpt = tmp_path / "ckpt.pt"
    slam = make_slam(traversal, checkpoint=ckpt, checkpoint_every=100)
    slam.run("online", progress=False)
    good = ckpt.read_bytes()
    assert checkpoint.read(ckpt)["state"]["t"] == STEPS

    def boom(*args, **kwargs):
        raise OSError("disk full")

    slam.state.t = 3  # something that would change the file
    # 1) serialisation fails before anything is written
    with monkeypatch.context() as m:
        m.setattr(torch, "save", boom)
        with pytest.raises(OSError, match="disk full"):
            slam.save(ckpt)
    # 2) the temporary file is half written when the disk fills up
    with monkeypatch.context() as m:
        m.setattr(os, "fsync", boom)
        with pytest.raises(OSError, match="disk full"):
            slam.save(ckpt)
    # 3) the rename fails
    with monkeypatch.context() as m:
        m.setattr(os, "replace", boom)
        with pytest.raises(OSError, match="disk full"):
            slam.save(ckpt)
    assert ckpt.read_bytes() == good
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pt"]  # no temp files left
    # the surviving checkpoint still resumes
    again = make_slam(traversal, checkpoint=ckpt).resume(ckpt)
    assert again.state.t == STEPS and again.state.phase == "done"
    slam.save(ckpt)  # and a working save replaces it
    assert checkpoint.read(ckpt)["state"]["t"] == 3
