"""Angle wrapping, the one helper of the package, the library and the simulators."""

from __future__ import annotations

import math

import numpy as np
import torch


def wrap_angle(a, period: float = 2 * math.pi):
    """Wrap angles to ``[-period / 2, period / 2)`` (default ``[-pi, pi)``), any shape: a torch
    tensor stays a tensor; anything else becomes a numpy array (float64 unless it is one
    already)."""
    half = period / 2
    if isinstance(a, torch.Tensor):
        return torch.remainder(a + half, period) - half
    a = np.asarray(a)
    if a.dtype.kind != "f":
        a = a.astype(np.float64)
    return np.remainder(a + half, period) - half
