"""Occupancy grids in the ROS map_server format: built from scans, written, read back."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from pyro_slam.data import DatasetError, Traversal
from pyro_slam.io import ParseError
from pyro_slam.io.ros_map import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    OccupancyGrid,
    occupancy_grid,
    read_map,
    write_map,
)
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


def test_read_map_takes_any_yaml_spelling_of_the_header(tmp_path):
    """map_server headers written by other tools: a quoted image name, comments, block lists."""
    grid = OccupancyGrid(np.full((3, 4), FREE, np.uint8), 0.05, (1.0, -2.0, 0.0))
    pgm, _ = write_map(grid, tmp_path / "map")
    for text in (
        'image: "map.pgm"\nresolution: 0.05\norigin: [1.0, -2.0, 0.0]\n',
        "# a map\nimage: 'map.pgm'   # quoted\nresolution: 5.0e-2\norigin:\n- 1\n- -2\n- 0\n",
    ):
        (tmp_path / "other.yaml").write_text(text)
        back = read_map(tmp_path / "other.yaml")
        np.testing.assert_array_equal(back.image, grid.image)
        assert back.resolution == 0.05 and back.origin == (1.0, -2.0, 0.0)
    with Image.open(pgm) as im:  # a standard binary pgm
        assert im.format == "PPM" and im.mode == "L" and im.size == (4, 3)


def test_bad_map_values_and_images_are_named(tmp_path):
    (tmp_path / "m.yaml").write_text("image: m.pgm\nresolution: -1\norigin: [0, 0, 0]\n")
    with pytest.raises(ParseError, match="m.yaml:2"):
        read_map(tmp_path / "m.yaml")
    (tmp_path / "n.yaml").write_text("image: n.pgm\nresolution: [1\n")
    with pytest.raises(ParseError, match="n.yaml:"):
        read_map(tmp_path / "n.yaml")
    (tmp_path / "p.yaml").write_text("image: p.pgm\nresolution: 1\norigin: [0, 0, 0]\n")
    (tmp_path / "p.pgm").write_bytes(b"P5\n2 2\n255\n\x00")  # 1 of 4 pixels
    with pytest.raises(DatasetError, match="p.pgm"):
        read_map(tmp_path / "p.yaml")
    (tmp_path / "p.pgm").unlink()
    with pytest.raises(FileNotFoundError, match="p.pgm"):
        read_map(tmp_path / "p.yaml")


def _room_scans(T=30, B=90, room=4.0, max_range=80.0):
    """A robot turning in a ``room`` x ``room`` box whose scans have "no return" beams (at
    ``max_range``, masked), read with a 3 m range clip as the ``real`` preset does."""
    t = np.arange(T)
    poses = np.column_stack([1.5 + 0.03 * t, 2.0 + 0.01 * t, 0.2 * t])
    angles = np.linspace(-np.pi, np.pi, B, endpoint=False)
    a = poses[:, 2:3] + angles  # [T, B]
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (room - poses[:, :1]) / c, -poses[:, :1] / c)
        ty = np.where(s > 0, (room - poses[:, 1:2]) / s, -poses[:, 1:2] / s)
    obs = np.minimum(np.abs(tx), np.abs(ty))
    obs[:, ::7] = max_range  # no return
    meta = {"control_model": "odometry_delta"}
    tr = Traversal(obs, np.zeros((T - 1, 3)), np.zeros((0, 4)), angles, max_range, metadata=meta)
    tr.obs_mask = obs < max_range
    return tr.clip_ranges(3.0), poses


def test_map_covers_what_the_beams_reached_not_the_sensors_no_return_range():
    """The grid spans the path plus at most the range clip (the beams' reach), never the
    sensor's far "no return" value; every beam's hit is inside it."""
    tr, poses = _room_scans()
    grid = occupancy_grid(tr, poses, 0.05, margin=0.1)
    h, w = grid.image.shape
    span = poses[:, :2].max(0) - poses[:, :2].min(0) + 2 * (3.0 + 0.1)  # path + clip + margin
    assert w * 0.05 <= span[0] + 0.1 and h * 0.05 <= span[1] + 0.1
    assert w * 0.05 <= 4.0 + 0.3 and h * 0.05 <= 4.0 + 0.3  # the room: the beams stop at walls
    assert (grid.image == OCCUPIED).sum() > 100 and (grid.image == FREE).sum() > 1000
    x0, y0, _ = grid.origin
    assert -0.2 <= x0 <= 0.0 and -0.2 <= y0 <= 0.0  # the room's corner, not 80 m away
