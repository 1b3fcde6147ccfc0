"""A run's outputs (:mod:`pyro_slam.slam.outputs`): settings refused before any work, naming
the field and its limit; the walls' fingerprint."""

from __future__ import annotations

import logging
import os
import signal
from dataclasses import replace
from pathlib import Path

import pytest

from pyro_slam.slam import ConfigError, SLAMConfig, outputs, with_overrides
from pyro_slam.slam.outputs import check_settings, run_folder, walls_fingerprint
from simulators import simulate_traversal


@pytest.fixture(scope="module")
def traversal():
    return simulate_traversal("simple-small", steps=4, seed=0)


def test_check_settings_refuses_what_cannot_mean_anything_naming_the_field(traversal):
    check_settings(traversal, SLAMConfig(), "t.npz")  # the defaults fit the simulator
    n, reach = traversal.num_beams, traversal.max_range
    cases = [
        ({"beam_stride": n}, rf"beam_stride {n} leaves fewer than 2 of the {n} beams of t\.npz"),
        ({"range_clip": reach + 0.1}, r"range_clip .* is beyond the sensor's range .* in t\.npz"),
        ({"emission": {"resolution": reach}}, r"emission\.resolution .* too coarse .* t\.npz"),
    ]
    for changes, message in cases:
        with pytest.raises(ConfigError, match=message):
            check_settings(traversal, with_overrides(SLAMConfig(), changes), "t.npz")
    # the limits themselves are accepted
    check_settings(traversal, with_overrides(SLAMConfig(), {"beam_stride": n - 1}), "t.npz")
    check_settings(traversal, replace(SLAMConfig(), range_clip=round(reach, 2)), "t.npz")


def test_walls_fingerprint_names_the_maze(traversal):
    walls = traversal.walls
    assert walls_fingerprint(walls) == walls_fingerprint(walls.tolist())  # the values count
    moved = walls.copy()
    moved.flat[0] += 1e-3
    assert walls_fingerprint(moved) != walls_fingerprint(walls)
    assert len(walls_fingerprint(walls)) == 32


OLD_RUN = {"metrics.json": "old", "slam.png": "old", "map.png": "old", "checkpoint.pt": "old"}
NEW_RUN = {"metrics.json": "new", "slam.png": "new", "map.pgm": "new", "checkpoint.pt": "new"}
# what a swap may change on disk: each call is one step a kill can stop the swap after
SWAP_STEPS = ("replace", "rename", "remove", "unlink", "rmdir", "mkdir")


def _write_run(out: Path, files: dict, overwrite: bool) -> None:
    with run_folder(out, overwrite=overwrite) as folder, folder.writing() as work:
        for name, text in files.items():
            (work / name).write_text(text)


def _killed_at(out: Path, step: int) -> bool:
    """Replace the run in ``out`` by ``NEW_RUN`` in a forked process that dies (no clean-up,
    as under SIGKILL) at its ``step``-th change on disk once the new run is written; False
    where the swap had fewer steps."""
    pid = os.fork()
    if pid == 0:  # the child: count the steps of the swap, die at the chosen one
        calls = [0]
        for name in SWAP_STEPS:
            real = getattr(os, name)

            def counted(*a, _real=real, **kw):
                calls[0] += 1
                if calls[0] == step:
                    os._exit(9)
                return _real(*a, **kw)

            setattr(outputs.os, name, counted)
        try:
            with run_folder(out, overwrite=True) as folder:
                work = folder.work
                with folder.writing():
                    for name, text in NEW_RUN.items():
                        real_write(work / name, text)
                    calls[0] = 0  # count from the swap on
        finally:
            os._exit(0)
    return os.waitpid(pid, 0)[1] != 0


def real_write(path: Path, text: str) -> None:
    with open(path, "w") as f:
        f.write(text)


def _run_in(out: Path) -> dict:
    return {p.name: p.read_text() for p in out.iterdir() if not p.name.startswith(".")}


def test_swap_interrupted_at_each_rename(tmp_path, caplog):
    """A process killed at each step of the swap in turn (each rename or removal, injected,
    not timed): the next run on the folder finds exactly one complete run, the previous one
    (killed before the list of the new run's files was in place) or the new one (after it),
    finishes what was left, names it, and leaves nothing of either behind."""
    seen = set()
    for step in range(1, 100):
        out = tmp_path / f"run{step}"
        _write_run(out, OLD_RUN, overwrite=False)
        if not _killed_at(out, step):
            assert _run_in(out) == NEW_RUN  # the swap ended before this step: all of it
            break
        left = [str(out / n) for n in (".partial", ".previous") if (out / n).exists()]
        caplog.clear()
        with caplog.at_level(logging.WARNING), run_folder(out, resume=False, overwrite=True):
            found = _run_in(out)
            assert found in (OLD_RUN, NEW_RUN), (step, found)
            assert not (out / ".previous").exists() and not (out / ".partial").exists(), step
        assert all(p in caplog.text for p in left), (step, left, caplog.text)  # each named
        seen.add("new" if found == NEW_RUN else "old")
    assert step > 8 and seen == {"old", "new"}, (step, seen)


def test_signal_during_the_swap_waits_and_says_so(tmp_path, monkeypatch):
    """SIGTERM arriving in the middle of the swap: the swap ends first, then the run stops
    with a message saying the folder holds the finished run, which it does."""
    out = tmp_path / "run"
    _write_run(out, OLD_RUN, overwrite=False)
    real = os.replace
    sent = []

    def replace(src, dst):
        if not sent and Path(dst).parent == out / ".previous":
            sent.append(True)
            signal.raise_signal(signal.SIGTERM)
        return real(src, dst)

    monkeypatch.setattr(outputs.os, "replace", replace)
    with pytest.raises(outputs.Interrupted) as e:
        with run_folder(out, overwrite=True) as folder, folder.writing() as work:
            for name, text in NEW_RUN.items():
                (work / name).write_text(text)
    assert sent and "the folder holds it" in str(e.value) and "as it was" not in str(e.value)
    assert _run_in(out) == NEW_RUN and sorted(p.name for p in out.iterdir()) == sorted(NEW_RUN)
