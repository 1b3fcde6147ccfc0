import numpy as np
import pytest

from simulators.maze import Maze


@pytest.fixture
def open_box() -> Maze:
    """A 3x3-cell maze of side 1 with only the outer boundary (no interior walls)."""
    n = 3
    h = np.zeros((n, n + 1), dtype=bool)
    v = np.zeros((n + 1, n), dtype=bool)
    h[:, [0, n]] = True
    v[[0, n], :] = True
    return Maze("open-box", 0, n, 1 / 3, h, v)
