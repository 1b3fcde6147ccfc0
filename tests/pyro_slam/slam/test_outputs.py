"""A run's outputs (:mod:`pyro_slam.slam.outputs`): settings refused before any work, naming
the field and its limit; the walls' fingerprint."""

from __future__ import annotations

from dataclasses import replace

import pytest

from pyro_slam.slam import ConfigError, SLAMConfig, with_overrides
from pyro_slam.slam.outputs import check_settings, walls_fingerprint
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
