"""Occupancy grids in the ROS ``map_server`` format: a ``.pgm`` image and a ``.yaml`` header.

:func:`occupancy_grid` builds the grid from a trajectory and its scans (each beam marks the
cells it crosses free and the cell of its hit occupied, log-odds per cell);
:func:`write_map` writes it, :func:`read_map` reads it back. Other tools (``map_server``,
``nav2``, ``rviz``, MRPT's ``grid-matching``) load the pair directly.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pyro_slam.data import DatasetError, Traversal, atomic_write
from pyro_slam.io.common import ParseError

FREE, UNKNOWN, OCCUPIED = 254, 205, 0  # pgm grey levels, map_server's trinary convention
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196


@dataclass
class OccupancyGrid:
    """``image [H, W]`` uint8 grey levels (row 0 at the top, as the pgm stores it),
    ``resolution`` (metres per cell), ``origin`` ``(x, y, yaw)`` of the bottom-left cell."""

    image: np.ndarray
    resolution: float
    origin: tuple[float, float, float]


def occupancy_grid(traversal: Traversal, poses, resolution: float, margin: float = 1.0,
                   max_range: float | None = None) -> OccupancyGrid:  # fmt: skip
    """The occupancy grid of ``traversal``'s scans placed at ``poses [T, 3]``: per cell, the log
    odds of hits (+0.85) and pass-throughs (-0.4) of every valid beam; a cell no beam reached is
    unknown. Readings at or beyond ``max_range`` (default: the sensor's) mark free space only."""
    p = np.asarray(poses, dtype=np.float64)
    obs = np.asarray(traversal.observations, dtype=np.float64)
    rmax = float(max_range or traversal.max_range)
    valid = np.ones(obs.shape, bool) if traversal.obs_mask is None else traversal.obs_mask.copy()
    hit = valid & (obs < rmax * (1 - 1e-3))
    ang = p[:, 2:3] + traversal.beam_angles[None, :]  # [T, B]
    lo, hi = p[:, :2].min(0) - rmax - margin, p[:, :2].max(0) + rmax + margin
    shape = np.ceil((hi - lo) / resolution).astype(int) + 1  # [W, H] cells along x, y
    logodds = np.zeros(shape)
    rng = np.minimum(obs, rmax)
    steps = np.arange(0.0, 1.0, 0.5 * resolution / rmax)  # fractions along the beam
    for t in range(len(p)):  # one scan at a time bounds the memory
        r, a = rng[t][valid[t]], ang[t][valid[t]]  # [V]
        dirs = np.stack([np.cos(a), np.sin(a)], -1)  # [V, 2]
        d = r[:, None] * steps[None, :]  # [V, S] samples along each beam
        pts = p[t, :2] + d[..., None] * dirs[:, None, :]  # [V, S, 2]
        free = _cells(pts[d < r[:, None] - resolution], lo, resolution)  # before the end
        np.add.at(logodds, tuple(np.unique(free, axis=0).T), -0.4)
        ends = (p[t, :2] + r[:, None] * dirs)[hit[t][valid[t]]]  # [H, 2]
        np.add.at(logodds, tuple(_cells(ends, lo, resolution).T), 0.85)
    seen = np.zeros(shape, bool)
    seen[logodds != 0] = True
    prob = 1 / (1 + np.exp(-logodds))
    image = np.where(prob > OCCUPIED_THRESH, OCCUPIED, np.where(prob < FREE_THRESH, FREE, UNKNOWN))
    image = np.where(seen, image, UNKNOWN).astype(np.uint8)
    return OccupancyGrid(np.flipud(image.T), float(resolution), (float(lo[0]), float(lo[1]), 0.0))


def _cells(xy: np.ndarray, lo: np.ndarray, resolution: float) -> np.ndarray:
    """Cell indices ``[N, 2]`` (x, y) of points ``xy [N, 2]``."""
    return np.floor((xy - lo) / resolution).astype(int)


def write_map(grid: OccupancyGrid, path: str | os.PathLike) -> tuple[Path, Path]:
    """Write ``PATH.pgm`` (binary P5) and ``PATH.yaml`` (``path`` with or without a suffix);
    each atomically. Returns both paths."""
    base = Path(path).with_suffix("")
    pgm, yaml = base.with_suffix(".pgm"), base.with_suffix(".yaml")
    h, w = grid.image.shape
    header = f"P5\n# pyro-slam occupancy grid\n{w} {h}\n255\n".encode()
    atomic_write(pgm, lambda f: f.write(header + grid.image.astype(np.uint8).tobytes()))
    x, y, yaw = grid.origin
    text = (f"image: {pgm.name}\nresolution: {grid.resolution!r}\n"
            f"origin: [{x!r}, {y!r}, {yaw!r}]\nnegate: 0\n"
            f"occupied_thresh: {OCCUPIED_THRESH}\nfree_thresh: {FREE_THRESH}\n")  # fmt: skip
    atomic_write(yaml, lambda f: f.write(text.encode()))
    return pgm, yaml


def read_map(path: str | os.PathLike) -> OccupancyGrid:
    """Read a ``map_server`` pair from its ``.yaml`` (``image``, ``resolution``, ``origin``; the
    image a binary P5 pgm next to it); :class:`ParseError` naming the file and line."""
    path = Path(path).with_suffix(".yaml")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such map")
    fields = {}
    for n, line in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), 1):
        if line.strip() and not line.lstrip().startswith("#"):
            key, sep, value = line.partition(":")
            if not sep:
                raise ParseError(path, n, f"expected 'key: value', got {line[:40]!r}")
            fields[key.strip()] = (value.strip(), n)
    for key in ("image", "resolution", "origin"):
        if key not in fields:
            raise ParseError(path, None, f"missing field {key!r}")
    try:
        resolution = float(fields["resolution"][0])
        origin = tuple(float(v) for v in fields["origin"][0].strip("[]").split(","))
    except ValueError:
        raise ParseError(path, fields["origin"][1], "resolution / origin must be numbers") from None
    if not resolution > 0 or len(origin) != 3:
        raise ParseError(path, fields["resolution"][1], "resolution > 0 and a 3-number origin")
    return OccupancyGrid(_read_pgm(path.parent / fields["image"][0]), resolution, origin)


def _read_pgm(path: Path) -> np.ndarray:
    data = path.read_bytes()
    tokens, pos = [], 0
    while len(tokens) < 4:  # magic, width, height, maxval (comments skipped)
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while end < len(data) and not data[end : end + 1].isspace():
            end += 1
        tokens.append(data[pos:end])
        pos = end
    if tokens[0] != b"P5" or tokens[3] != b"255":
        raise DatasetError(f"{path}: not an 8-bit binary pgm (P5, maxval 255)")
    w, h = int(tokens[1]), int(tokens[2])
    pixels = np.frombuffer(data[pos + 1 : pos + 1 + w * h], dtype=np.uint8)
    if pixels.size != w * h:
        raise DatasetError(f"{path}: holds {pixels.size} of {w * h} pixels")
    return pixels.reshape(h, w).copy()
