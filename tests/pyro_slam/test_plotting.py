"""The run plots read as they should: legends, titles and the map's grey levels."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pyro_slam import plotting
from pyro_slam.io import read_any
from pyro_slam.model import MapGrid
from pyro_slam.slam import SLAM
from simulators import simulate_traversal


@pytest.fixture
def figures(monkeypatch):
    """The figures the plot functions make, kept open instead of saved."""
    made = []

    def keep(fig, path):
        made.append(fig)
        return path

    monkeypatch.setattr(plotting, "_save", keep)
    yield made
    for fig in made:
        plotting.plt.close(fig)


@pytest.fixture(scope="module")
def run():
    tr = simulate_traversal("simple-small", steps=60, seed=1)
    rng = np.random.default_rng(0)
    drift = np.cumsum(rng.normal(0, 1e-3, (60, 3)), 0)
    grid = MapGrid(cells=(16, 16), dim=1)
    result = {
        "mean": tr.poses + drift,
        "path_integration": tr.poses - drift,
        "map_loc": rng.normal(size=(16, 16, 1)),
        "map_scale": np.ones((16, 16, 1)),
    }
    return tr, grid, result


def test_slam_plot_names_the_mode_only_when_known_and_titles_the_map(run, figures):
    tr, grid, result = run
    plotting.plot_slam(tr, result, grid, "slam.png")
    plotting.plot_slam(tr, {**result, "mode": "online"}, grid, "slam.png")
    labels = [[t.get_text() for t in f.axes[0].get_legend().get_texts()] for f in figures]
    assert "SLAM" in labels[0] and "SLAM (online)" in labels[1]
    assert not any("()" in name for name in labels[0] + labels[1])
    assert figures[0].axes[1].get_title() == "map belief: mean (occupancy, walls dark)"


def test_scan_map_titles_a_one_feature_map_as_occupancy(run, figures):
    tr, grid, result = run
    plotting.plot_scan_map(tr, result["mean"], "map.png", grid, result["map_loc"])
    assert "principal components" not in figures[0].axes[1].get_title()
    assert plotting.map_kind(np.zeros((4, 4, 10))) == "3 principal components"


DATA = Path(__file__).resolve().parents[3] / "shared" / "data"


def _unknown_known(loc: np.ndarray):
    """The cells the scans never reached (at the prior's mean, 0), the walls (the top 1 % of
    the reached) and free space (the bottom 1 %) of a map mean ``[w, h, 1]``, as ``[h, w]``
    pixel masks."""
    v = loc[..., 0].T
    reached = np.abs(v) > 1e-6
    hi, lo = np.percentile(v[reached], 99), np.percentile(v[reached], 1)
    return ~reached, reached & (v >= hi), reached & (v <= lo)


def test_map_image_unknown_is_grey():
    """Cells the scans never reached are mid-grey, walls dark and free space light, however
    much of the map is unknown: a 100 m world of which 4 % was mapped, and the SLAM maps of
    the first 150 scans of Intel and MIT-CSAIL (where those logs are here)."""
    world = np.zeros((2001, 1101, 1))  # 100 x 55 m at 0.05 m
    world[100:500, 100:300] = -1.0  # free space seen
    world[100:500, 300:303] = 2.0  # a wall
    maps = {"world": world}
    for name in ("intel.gfs.log", "mit-csail.clf"):
        if (DATA / name).is_file():
            tr = read_any(DATA / name).slice(0, 150)
            maps[name] = SLAM(tr, "real", seed=0).run("online", progress=False)["map_loc"]
    for name, loc in maps.items():
        img = plotting.map_image(np.asarray(loc))[..., 0]  # [h, w]
        unknown, walls, free = _unknown_known(np.asarray(loc))
        assert unknown.mean() > 0.3, name  # most of each map is unknown
        np.testing.assert_allclose(img[unknown], 0.5, err_msg=name)
        assert img[walls].max() < 0.3 and img[free].min() > 0.7, name
