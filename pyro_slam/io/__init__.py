"""Readers for real sensor logs: CARMEN (``.clf`` / ``.log``), ROS bags, and the Kümmerle et
al. (2009) relation files used to score trajectories on them. Every reader returns a
:class:`pyro_slam.data.Traversal` with ``control_model = "odometry_delta"``. Maps go out as ROS
``map_server`` occupancy grids (:mod:`pyro_slam.io.ros_map`)."""

from __future__ import annotations

import os
from pathlib import Path

from pyro_slam.data import Traversal, load
from pyro_slam.io.carmen import parse_carmen, read_carmen, write_carmen
from pyro_slam.io.common import ParseError, odometry_poses
from pyro_slam.io.relations import (
    read_relations,
    relation_error,
    relations_from_reference,
    write_relations,
)
from pyro_slam.io.ros_map import OccupancyGrid, occupancy_grid, read_map, write_map
from pyro_slam.io.rosbag import read_rosbag

CARMEN_SUFFIXES = (".clf", ".log", ".carmen")

__all__ = [
    "OccupancyGrid",
    "input_kind",
    "ParseError",
    "odometry_poses",
    "parse_carmen",
    "read_any",
    "occupancy_grid",
    "read_carmen",
    "read_map",
    "read_relations",
    "read_rosbag",
    "relation_error",
    "relations_from_reference",
    "write_carmen",
    "write_map",
    "write_relations",
]


def input_kind(path: str | os.PathLike) -> str | None:
    """Which reader :func:`read_any` picks for ``path``: ``"npz"``, ``"carmen"``, ``"rosbag"``,
    or None for an unknown type (by suffix; a ROS 2 bag is a folder with ``metadata.yaml``)."""
    path = Path(path)
    suffixes = [s.lower() for s in path.suffixes]
    if suffixes and suffixes[-1] == ".gz":
        suffixes = suffixes[:-1]
    last = suffixes[-1] if suffixes else ""
    if path.is_dir() and (path / "metadata.yaml").is_file() or last == ".bag":
        return "rosbag"
    if last == ".npz" and not path.is_dir():
        return "npz"
    if last in CARMEN_SUFFIXES and not path.is_dir():
        return "carmen"
    return None


def read_any(path: str | os.PathLike, **kw) -> Traversal:
    """Read a traversal from ``path``, choosing the reader by file type (:func:`input_kind`).

    ``.npz`` -> :func:`pyro_slam.data.load`; ``.clf`` / ``.log`` / ``.carmen`` (optionally
    ``.gz``) -> :func:`read_carmen`; ``.bag`` or a directory holding ``metadata.yaml`` (ROS 2
    bag) -> :func:`read_rosbag`. ``kw`` goes to the chosen reader.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or directory")
    kind = input_kind(path)
    if kind == "rosbag":
        return read_rosbag(path, **kw)
    if kind == "npz":
        if kw:
            raise TypeError(f"{path}: .npz datasets take no reader options, got {sorted(kw)}")
        return load(path)
    if kind == "carmen":
        return read_carmen(path, **kw)
    raise ValueError(
        f"{path}: unknown log type; expected .npz, {' / '.join(CARMEN_SUFFIXES)} (CARMEN), "
        ".bag (ROS 1) or a ROS 2 bag directory with metadata.yaml"
    )
