"""The run plots read as they should: legends and titles."""

from __future__ import annotations

import numpy as np
import pytest

from pyro_slam import plotting
from pyro_slam.model import MapGrid
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
