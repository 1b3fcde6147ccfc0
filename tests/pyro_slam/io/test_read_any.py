"""read_any dispatches on the file type."""

from __future__ import annotations

import numpy as np
import pytest
from io_helpers import synthetic_traversal

from pyro_slam.data import load
from pyro_slam.io import read_any, write_carmen


def test_dispatch(tmp_path):
    tr = synthetic_traversal()
    npz = tr.save(tmp_path / "t.npz")
    np.testing.assert_array_equal(read_any(npz).observations, load(npz).observations)
    for suffix in (".clf", ".log", ".carmen"):
        back = read_any(write_carmen(tr, tmp_path / f"t{suffix}"), beam_stride=1)
        np.testing.assert_array_equal(back.observations, tr.observations)
    with pytest.raises(ValueError, match=r"t.txt: unknown log type"):
        read_any(write_carmen(tr, tmp_path / "t.txt"))
    (tmp_path / "dir").mkdir()
    with pytest.raises(ValueError, match="unknown log type"):
        read_any(tmp_path / "dir")
    with pytest.raises(FileNotFoundError):
        read_any(tmp_path / "missing.clf")
    with pytest.raises(TypeError, match="take no reader options"):
        read_any(npz, beam_stride=2)
