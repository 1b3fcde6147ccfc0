"""The model's predictive of scans, as Pyro samples it: how far the scans a map predicts are
from the ones observed (:func:`scan_error`), and how often the observed reading falls in the
predictive's central band (:func:`band_coverage`), the calibration of the emission's noise."""

from __future__ import annotations

import numpy as np
import torch
from pyro import poutine


def scan_error(model, M, poses, observations, mask=None) -> float:
    """Mean absolute difference between the scans the model predicts under the map ``M [w, h,
    D_m]`` at ``poses [T, 3]`` (its emission's mean) and ``observations [T, N]``, over the
    valid readings (``mask [T, N]``)."""
    z = torch.as_tensor(np.asarray(poses), dtype=torch.get_default_dtype())
    x = torch.as_tensor(np.asarray(observations), dtype=z.dtype)
    with torch.no_grad():
        e = (model.emission_mean(torch.as_tensor(M), z, x) - x).abs()
    if mask is not None:
        m = torch.as_tensor(np.asarray(mask), dtype=torch.bool)
        return float(e[m].mean())
    return float(e.mean())


def band_coverage(
    model,
    M,
    poses,
    observations,
    controls,
    mask=None,
    samples: int = 200,
    every: int = 10,
    band=(0.1, 0.9),
    seed: int = 0,
) -> float:
    """The share of observed readings inside the central ``band`` (quantiles) of the model's
    predictive: :meth:`DVBFLM.model <pyro_slam.model.DVBFLM.model>` (under its handlers) traced
    with the map conditioned on ``M [w, h, D_m]`` and the poses on ``poses [T, 3]``
    (``controls [T-1, D_u]``, the model's argument), and ``samples`` draws of the observation
    site of every ``every``-th step from its distribution there, compared with ``observations
    [T, N]`` (valid readings only, ``mask``). A calibrated emission covers ``band[1] -
    band[0]`` of them."""
    z = torch.as_tensor(np.asarray(poses), dtype=torch.get_default_dtype())
    x = torch.as_tensor(np.asarray(observations), dtype=z.dtype)
    steps = list(range(0, len(z), every))
    data = {"map": torch.as_tensor(M, dtype=z.dtype)}
    data.update({f"z_{t}": z[t] for t in range(len(z))})
    controls = torch.as_tensor(np.asarray(controls), dtype=z.dtype)
    model = poutine.condition(model.handled(), data)
    with torch.no_grad(), torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        trace = poutine.trace(model).get_trace(None, controls, z[0])
        out = {t: trace.nodes[f"x_{t}"]["fn"].sample((samples,)) for t in steps}
    inside, count = 0.0, 0
    q = torch.tensor(band, dtype=z.dtype)
    for t in steps:
        draws = out[t].reshape(samples, -1)  # [S, N]
        lo, hi = torch.quantile(draws, q, dim=0)
        ok = (x[t] >= lo) & (x[t] <= hi)
        valid = torch.ones_like(ok) if mask is None else torch.as_tensor(np.asarray(mask[t]))
        inside += float(ok[valid.bool()].sum())
        count += int(valid.sum())
    return inside / max(count, 1)
