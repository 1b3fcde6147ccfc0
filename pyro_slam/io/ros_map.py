"""Occupancy grids in the ROS ``map_server`` format: a ``.pgm`` image and a ``.yaml`` header.

:func:`occupancy_grid` builds the grid from a trajectory and its scans (each beam marks the
cells it crosses free and the cell of its hit occupied, log-odds per cell);
:func:`write_map` writes it, :func:`read_map` reads it back (the image with Pillow, the header
with PyYAML). Other tools (``map_server``, ``nav2``, ``rviz``, MRPT's ``grid-matching``) load
the pair directly.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from PIL import Image, UnidentifiedImageError
from tqdm.auto import tqdm

from pyro_slam.data import DatasetError, Traversal, atomic_write
from pyro_slam.io.common import ParseError

FREE, UNKNOWN, OCCUPIED = 254, 205, 0  # pgm grey levels, map_server's trinary convention
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196
HIT, MISS = 0.85, -0.4  # log-odds of a beam's end cell and of a cell it crosses
CHUNK_SAMPLES = 2_000_000  # points along the beams handled at once (bounds the memory)


@dataclass
class OccupancyGrid:
    """``image [H, W]`` uint8 grey levels (row 0 at the top, as the pgm stores it),
    ``resolution`` (metres per cell), ``origin`` ``(x, y, yaw)`` of the bottom-left cell."""

    image: np.ndarray
    resolution: float
    origin: tuple[float, float, float]


@dataclass
class _Beams:
    """The valid beams of a trajectory's scans, each ``[N]`` (``start``, ``direction``:
    ``[N, 2]``): the scan ``t`` it belongs to, its length (clipped) and whether it hit."""

    t: np.ndarray
    start: np.ndarray
    direction: np.ndarray
    length: np.ndarray
    hit: np.ndarray

    def ends(self) -> np.ndarray:
        """Where each beam stops ``[N, 2]``."""
        return self.start + self.length[:, None] * self.direction


def _beams(traversal: Traversal, poses: np.ndarray, max_range: float) -> _Beams:
    obs = np.asarray(traversal.observations, dtype=np.float64)  # [T, B]
    valid = np.ones(obs.shape, bool) if traversal.obs_mask is None else traversal.obs_mask
    t, b = np.nonzero(valid)  # scan-major: each scan's beams are contiguous
    r = obs[t, b]
    ang = poses[t, 2] + traversal.beam_angles[b]
    direction = np.stack([np.cos(ang), np.sin(ang)], -1)
    return _Beams(t, poses[t, :2], direction, np.minimum(r, max_range), r < max_range * (1 - 1e-3))


def occupancy_grid(
    traversal: Traversal,
    poses,
    resolution: float,
    margin: float = 1.0,
    max_range: float | None = None,
    progress: bool = False,
) -> OccupancyGrid:
    """The occupancy grid of ``traversal``'s scans placed at ``poses [T, 3]``: per cell, the log
    odds of hits (+0.85) and pass-throughs (-0.4, once per scan) of every valid beam; a cell no
    beam reached is unknown. Readings at or beyond ``max_range`` (default: the traversal's range
    clip, else the sensor's range) mark free space up to ``max_range`` only. The grid covers
    what the beams reached plus ``margin``, so a sensor's far "no return" value does not pad it.
    ``progress``: a tqdm bar over the scans."""
    p = np.asarray(poses, dtype=np.float64)
    if p.shape != (traversal.num_steps, 3):
        raise ValueError(f"poses must be [T, 3] = [{traversal.num_steps}, 3], got {p.shape}")
    rmax = float(max_range or traversal.metadata.get("range_clip") or traversal.max_range)
    beams = _beams(traversal, p, rmax)
    ends = beams.ends()
    reached = np.concatenate([p[:, :2], ends])
    lo = reached.min(0) - margin
    shape = np.floor((reached.max(0) + margin - lo) / resolution).astype(int) + 1  # [W, H]
    free = _free_counts(beams, len(p), lo, resolution, shape, progress)
    hit_cells = _cell_index(ends[beams.hit], lo, resolution, shape)
    hits = np.bincount(hit_cells, minlength=free.size)
    logodds = (MISS * free + HIT * hits).reshape(shape)
    prob = 1 / (1 + np.exp(-logodds))
    image = np.where(prob > OCCUPIED_THRESH, OCCUPIED, np.where(prob < FREE_THRESH, FREE, UNKNOWN))
    image = np.where((free + hits).reshape(shape) > 0, image, UNKNOWN).astype(np.uint8)
    return OccupancyGrid(np.flipud(image.T), float(resolution), (float(lo[0]), float(lo[1]), 0.0))


def _cell_index(xy: np.ndarray, lo: np.ndarray, resolution: float, shape) -> np.ndarray:
    """Flat cell indices ``[N]`` (``x * H + y``) of points ``xy [N, 2]`` in a ``[W, H]`` grid."""
    c = np.floor((xy - lo) / resolution).astype(np.int64)
    c = np.clip(c, 0, np.asarray(shape) - 1)
    return c[:, 0] * shape[1] + c[:, 1]


def _free_counts(beams: _Beams, scans: int, lo, resolution, shape, progress) -> np.ndarray:
    """Per cell ``[W * H]``: how many of the ``scans`` scans have a beam that passes through it
    before its end (points every half cell along each beam; a cell counts once per scan)."""
    cells = int(shape[0] * shape[1])
    step = 0.5 * resolution
    n = np.ceil(np.maximum(beams.length - resolution, 0) / step).astype(np.int64)  # [N]
    cum = np.concatenate([[0], np.cumsum(np.bincount(beams.t, n, minlength=scans))])  # [T+1]
    first_beam = np.searchsorted(beams.t, np.arange(scans + 1))  # [T+1]
    counts = np.zeros(cells, np.int64)
    with tqdm(total=scans, desc="map export", unit="scan", disable=not progress) as bar:
        s0 = 0
        while s0 < scans:  # whole scans at a time, about CHUNK_SAMPLES points
            s1 = int(np.searchsorted(cum, cum[s0] + CHUNK_SAMPLES, side="right")) - 1
            s1 = min(max(s1, s0 + 1), scans)
            nb = n[first_beam[s0] : first_beam[s1]]
            beam = np.repeat(np.arange(first_beam[s0], first_beam[s1]), nb)  # [M]
            along = np.arange(len(beam)) - np.repeat(np.cumsum(nb) - nb, nb)  # [M]
            pts = beams.start[beam] + (along * step)[:, None] * beams.direction[beam]  # [M, 2]
            keys = np.sort(beams.t[beam] * cells + _cell_index(pts, lo, resolution, shape))
            first = np.concatenate([[True], keys[1:] != keys[:-1]])  # (scan, cell) once
            counts += np.bincount(keys[first] % cells, minlength=cells)
            bar.update(s1 - s0)
            s0 = s1
    return counts


def write_map(grid: OccupancyGrid, path: str | os.PathLike) -> tuple[Path, Path]:
    """Write ``PATH.pgm`` (binary P5, Pillow) and ``PATH.yaml`` (PyYAML; ``path`` with or
    without a suffix); each atomically. Returns both paths."""
    base = Path(path).with_suffix("")
    pgm, header = base.with_suffix(".pgm"), base.with_suffix(".yaml")
    image = Image.fromarray(np.ascontiguousarray(grid.image, dtype=np.uint8))  # 8-bit grey
    atomic_write(pgm, lambda f: image.save(f, format="PPM"))
    x, y, yaw = grid.origin
    fields = {
        "image": pgm.name,
        "resolution": float(grid.resolution),
        "origin": [float(x), float(y), float(yaw)],
        "negate": 0,
        "occupied_thresh": OCCUPIED_THRESH,
        "free_thresh": FREE_THRESH,
    }
    text = yaml.safe_dump(fields, sort_keys=False, default_flow_style=None)
    atomic_write(header, lambda f: f.write(text.encode()))
    return pgm, header


def _load_header(path: Path) -> tuple[dict, dict]:
    """The ``.yaml`` header's fields and the line of each key; :class:`ParseError` otherwise."""
    text = path.read_text(encoding="utf-8-sig")
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        fields = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = None if mark is None else mark.line + 1
        raise ParseError(path, line, f"not YAML: {getattr(e, 'problem', None) or e}") from None
    if not isinstance(fields, dict):
        raise ParseError(path, 1, f"expected 'key: value' lines, got {text.strip()[:40]!r}")
    lines = {k.value: k.start_mark.line + 1 for k, _ in node.value}
    return fields, lines


def read_map(path: str | os.PathLike) -> OccupancyGrid:
    """Read a ``map_server`` pair from its ``.yaml`` (``image``, ``resolution``, ``origin``; the
    image an 8-bit pgm next to it); :class:`ParseError` naming the file and line."""
    path = Path(path).with_suffix(".yaml")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such map")
    fields, lines = _load_header(path)
    for key in ("image", "resolution", "origin"):
        if key not in fields:
            raise ParseError(path, None, f"missing field {key!r}")
    res, origin = fields["resolution"], fields["origin"]
    numbers = isinstance(origin, list) and all(_is_number(v) for v in [res, *origin])
    if not numbers or not res > 0 or len(origin) != 3:
        why = "resolution must be a number > 0 and origin 3 numbers"
        raise ParseError(path, lines.get("resolution"), why)
    if not isinstance(fields["image"], str):
        raise ParseError(
            path, lines.get("image"), f"image must be a file name, got {fields['image']!r}"
        )
    origin = tuple(float(v) for v in origin)
    return OccupancyGrid(_read_pgm(path.parent / fields["image"]), float(res), origin)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)


def _read_pgm(path: Path) -> np.ndarray:
    """The grey levels ``[H, W]`` uint8 of an 8-bit pgm."""
    try:
        with Image.open(path) as im:
            if im.format != "PPM" or im.mode != "L":
                raise DatasetError(f"{path}: not an 8-bit grey pgm (got {im.format} {im.mode})")
            return np.array(im, dtype=np.uint8)
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such map image") from None
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise DatasetError(f"{path}: not a readable pgm ({e})") from None
