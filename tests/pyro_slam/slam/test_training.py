"""Mapping with known poses (:mod:`pyro_slam.slam.training`): ``q(M)`` sharpens where the scans
reach and keeps the prior elsewhere; the emission stays as it was."""

from __future__ import annotations

import torch
from small_slam import SMALL

from pyro_slam.slam import build_model, fit_map, prepare_traversal
from simulators import simulate_traversal


def test_fit_map_sharpens_the_map_where_the_scans_reach():
    tr = prepare_traversal(simulate_traversal("simple-small", steps=6, seed=0), SMALL)
    model, _ = build_model(tr, SMALL)
    loc, scale = fit_map(tr, model, steps=40, lr=0.1)
    assert loc.shape == scale.shape == model.grid.shape
    assert torch.isfinite(loc).all() and (scale > 0).all()
    assert float(scale.min()) < 0.8  # scanned cells: sharper than the prior N(0, 1)
    assert float(scale.max()) > 0.99  # cells no beam reached keep the prior's std
    assert model.learn_emission  # restored after the fit
