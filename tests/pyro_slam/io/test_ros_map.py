"""Occupancy grids in the ROS map_server format: built from scans, written, read back."""

from __future__ import annotations

import numpy as np
import pytest

from pyro_slam.io import ParseError
from pyro_slam.io.ros_map import FREE, OCCUPIED, UNKNOWN, occupancy_grid, read_map, write_map
from simulators import simulate_traversal


def test_map_round_trips_and_marks_walls_free_space_and_unknown(tmp_path):
    tr = simulate_traversal("simple-small", steps=200, seed=1)
    grid = occupancy_grid(tr, tr.poses, 0.01, margin=0.05)
    pgm, yaml = write_map(grid, tmp_path / "map.yaml")
    assert pgm.name == "map.pgm" and yaml.read_text().startswith("image: map.pgm\n")
    back = read_map(tmp_path / "map")
    np.testing.assert_array_equal(back.image, grid.image)
    assert back.resolution == grid.resolution and back.origin == grid.origin
    assert set(np.unique(grid.image)) == {FREE, UNKNOWN, OCCUPIED}
    # the walls the scans hit are occupied cells: a wall point maps to an occupied cell (or a
    # neighbour of one), the start pose to a free cell
    h = grid.image.shape[0]

    def cell(xy):  # image row (from the top) and column of a world point
        c = np.floor((np.asarray(xy) - grid.origin[:2]) / grid.resolution).astype(int)
        return h - 1 - c[1], c[0]

    hits = tr.observations[0] < tr.max_range - 1e-6
    ang = tr.poses[0, 2] + tr.beam_angles[hits]
    ends = tr.poses[0, :2] + tr.observations[0][hits][:, None] * np.stack(
        [np.cos(ang), np.sin(ang)], -1
    )
    for end in ends:
        r, c = cell(end)
        assert (grid.image[r - 1 : r + 2, c - 1 : c + 2] == OCCUPIED).any()
    assert grid.image[cell(tr.poses[0, :2])] == FREE
    assert grid.image[0, 0] == UNKNOWN  # the margin no beam reached


def test_bad_map_files_are_named(tmp_path):
    (tmp_path / "m.yaml").write_text("image: m.pgm\nresolution: fast\norigin: [0, 0, 0]\n")
    with pytest.raises(ParseError, match="m.yaml"):
        read_map(tmp_path / "m.yaml")
    (tmp_path / "n.yaml").write_text("image n.pgm\n")
    with pytest.raises(ParseError, match="n.yaml:1"):
        read_map(tmp_path / "n.yaml")
    with pytest.raises(FileNotFoundError):
        read_map(tmp_path / "missing.yaml")
