"""Random square mazes on a grid of cells, as wall segments in world coordinates ``[0, side]^2``.

Cell ``(i, j)`` is column ``i`` (x) and row ``j`` (y); its centre is ``((i + .5) w, (j + .5) w)``
for corridor width ``w``. A maze is a randomised depth-first-search perfect maze (a spanning tree
of the cell grid) with a few extra walls knocked out so that it contains loops.

Scales follow Table II of Mirchev et al. (RSS 2019): ``"{complexity}-{width}"`` with complexity
simple / moderate / complex = 3 / 6 / 12 cells per side and corridor width small / medium / large
= 1/12, 1/6, 1/4 units, so that the side length is ``cells * width`` (0.25 ... 3.0).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

COMPLEXITY_CELLS = {"simple": 3, "moderate": 6, "complex": 12}
CORRIDOR_WIDTHS = {"small": 1 / 12, "medium": 1 / 6, "large": 1 / 4}

# Table II: (map w = h, exploration steps, evaluation tiles per side); D_m = 20 throughout.
_TABLE_II = {
    "simple-small": (7, 1500, 3),
    "simple-medium": (12, 3000, 6),
    "simple-large": (18, 4500, 9),
    "moderate-small": (12, 3000, 6),
    "moderate-medium": (25, 6000, 12),
    "moderate-large": (37, 9000, 18),
    "complex-small": (25, 6000, 12),
    "complex-medium": (50, 12000, 18),
    "complex-large": (75, 18000, 24),
}
MAP_DEPTH = 20


@dataclass(frozen=True)
class Scale:
    """One row of Table II."""

    name: str
    cells: int  # cells per side
    corridor_width: float
    side: float  # cells * corridor_width
    map_dims: tuple[int, int, int]  # (w, h, D_m)
    steps: int  # exploration steps
    tiles: int  # evaluation tiles per side


def _build_scales() -> dict[str, Scale]:
    scales = {}
    for cname, cells in COMPLEXITY_CELLS.items():
        for wname, width in CORRIDOR_WIDTHS.items():
            name = f"{cname}-{wname}"
            w, steps, tiles = _TABLE_II[name]
            scales[name] = Scale(name, cells, width, cells * width, (w, w, MAP_DEPTH), steps, tiles)
    return scales


SCALES: dict[str, Scale] = _build_scales()


@dataclass
class Maze:
    """A generated maze.

    ``h_walls[i, j]`` is the wall below cell ``(i, j)`` (at ``y = j w``), shape ``[n, n + 1]``;
    ``v_walls[i, j]`` is the wall left of cell ``(i, j)`` (at ``x = i w``), shape ``[n + 1, n]``.
    ``walls`` are the same walls as maximal collinear segments, boundary included.
    """

    name: str
    seed: int
    cells: int
    corridor_width: float
    h_walls: np.ndarray  # [n, n+1] bool
    v_walls: np.ndarray  # [n+1, n] bool
    walls: np.ndarray = field(init=False)  # [W, 4] float64 (x1, y1, x2, y2)

    def __post_init__(self):
        self.walls = merge_walls(self.h_walls, self.v_walls, self.corridor_width)

    @property
    def side(self) -> float:
        return self.cells * self.corridor_width

    def cell_center(self, i, j) -> np.ndarray:
        """Centre of cell ``(i, j)`` (scalars or arrays) -> ``[..., 2]``."""
        w = self.corridor_width
        x, y = np.broadcast_arrays((np.asarray(i) + 0.5) * w, (np.asarray(j) + 0.5) * w)
        return np.stack([x, y], -1)

    def cell_of(self, xy) -> np.ndarray:
        """Integer cell indices ``[..., 2]`` of points ``xy`` ``[..., 2]`` (clipped to the grid)."""
        idx = np.floor(np.asarray(xy, dtype=np.float64) / self.corridor_width).astype(np.int64)
        return np.clip(idx, 0, self.cells - 1)

    def free_cells(self) -> np.ndarray:
        """All cells the agent can stand in, ``[C, 2]`` of ``(i, j)`` (every cell of a maze)."""
        i, j = np.meshgrid(np.arange(self.cells), np.arange(self.cells), indexing="ij")
        return np.stack([i.ravel(), j.ravel()], -1)

    def random_free_pose(self, rng: np.random.Generator, margin: float = 0.25) -> np.ndarray:
        """A pose ``[3]`` uniformly inside a random cell, ``margin * w`` from its edges."""
        cells = self.free_cells()
        i, j = cells[rng.integers(len(cells))]
        lo = np.array([i, j]) + margin
        xy = (lo + rng.uniform(0.0, 1.0 - 2 * margin, size=2)) * self.corridor_width
        return np.array([xy[0], xy[1], rng.uniform(-np.pi, np.pi)])

    def contains(self, xy) -> np.ndarray:
        """Whether points ``[..., 2]`` lie strictly inside the outer boundary -> ``[...]`` bool."""
        xy = np.asarray(xy, dtype=np.float64)
        return np.all((xy > 0.0) & (xy < self.side), axis=-1)

    def neighbours(self, i: int, j: int) -> list[tuple[int, int]]:
        """Cells reachable from ``(i, j)`` in one step (no wall in between)."""
        out = []
        if i > 0 and not self.v_walls[i, j]:
            out.append((i - 1, j))
        if i < self.cells - 1 and not self.v_walls[i + 1, j]:
            out.append((i + 1, j))
        if j > 0 and not self.h_walls[i, j]:
            out.append((i, j - 1))
        if j < self.cells - 1 and not self.h_walls[i, j + 1]:
            out.append((i, j + 1))
        return out


def _dfs_tree(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Randomised depth-first search over an ``n x n`` grid -> ``(h_walls, v_walls)``."""
    h = np.ones((n, n + 1), dtype=bool)
    v = np.ones((n + 1, n), dtype=bool)
    visited = np.zeros((n, n), dtype=bool)
    start = (int(rng.integers(n)), int(rng.integers(n)))
    stack = [start]
    visited[start] = True
    steps = ((-1, 0), (1, 0), (0, -1), (0, 1))
    while stack:
        i, j = stack[-1]
        options = [
            (i + di, j + dj)
            for di, dj in steps
            if 0 <= i + di < n and 0 <= j + dj < n and not visited[i + di, j + dj]
        ]
        if not options:
            stack.pop()
            continue
        a, b = options[rng.integers(len(options))]
        _open(h, v, (i, j), (a, b))
        visited[a, b] = True
        stack.append((a, b))
    return h, v


def _open(h: np.ndarray, v: np.ndarray, c0: tuple[int, int], c1: tuple[int, int]) -> None:
    """Remove the wall between adjacent cells ``c0`` and ``c1``."""
    (i0, j0), (i1, j1) = c0, c1
    if i0 == i1:
        h[i0, max(j0, j1)] = False
    else:
        v[max(i0, i1), j0] = False


def _remove_extra_walls(h: np.ndarray, v: np.ndarray, fraction: float, rng) -> None:
    """Knock out ``round(fraction * #interior walls)`` random interior walls (creates loops)."""
    interior = [("h", i, j) for i, j in np.argwhere(h[:, 1:-1])]
    interior += [("v", i, j) for i, j in np.argwhere(v[1:-1, :])]
    k = int(round(fraction * len(interior)))
    for idx in rng.permutation(len(interior))[:k]:
        kind, i, j = interior[idx]
        if kind == "h":
            h[i, j + 1] = False
        else:
            v[i + 1, j] = False


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs of ``True`` in a 1-D bool array as ``(start, stop)`` index pairs."""
    padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def merge_walls(h: np.ndarray, v: np.ndarray, w: float) -> np.ndarray:
    """Unit wall flags -> maximal collinear segments ``[W, 4]`` (horizontal first)."""
    segs = []
    for j in range(h.shape[1]):  # horizontal line y = j w, pieces along x
        segs += [(a * w, j * w, b * w, j * w) for a, b in _runs(h[:, j])]
    for i in range(v.shape[0]):  # vertical line x = i w, pieces along y
        segs += [(i * w, a * w, i * w, b * w) for a, b in _runs(v[i, :])]
    return np.asarray(segs, dtype=np.float64).reshape(-1, 4)


def make_maze(name: str = "moderate-medium", seed: int = 0, loop_fraction: float = 0.1) -> Maze:
    """Generate the maze of scale ``name`` (a key of :data:`SCALES`) reproducibly from ``seed``.

    ``loop_fraction`` of the interior walls left by the DFS are removed to create loops.
    """
    if name not in SCALES:
        raise ValueError(f"unknown maze scale {name!r}; choose one of {sorted(SCALES)}")
    if not 0.0 <= loop_fraction <= 1.0:
        raise ValueError(f"loop_fraction must lie in [0, 1], got {loop_fraction}")
    scale = SCALES[name]
    rng = np.random.default_rng(seed)
    h, v = _dfs_tree(scale.cells, rng)
    _remove_extra_walls(h, v, loop_fraction, rng)
    return Maze(name, int(seed), scale.cells, scale.corridor_width, h, v)
