"""Diagnostics the benchmarks use that are not part of the library's SLAM (not a benchmark)."""

from __future__ import annotations

import numpy as np
import torch


def pin_cache(slam, poses, noise: float = 1e-3, seed: int = 0) -> None:
    """Diagnostic: ``slam``'s particle cache holds ``poses [T, 3]`` (+ ``noise`` std) from now on.

    Every later store (the online filter's, the ELBO chunks' refreshes, the offline passes')
    writes the given poses with fresh noise instead of its particles, so the map is learned at
    those poses (e.g. the ground truth or path integration) while the filter still localises
    against it. This separates "the filter cannot use the map" from "pose errors written into
    the map feed back into the filter" (``slam_accuracy --map-poses``, ``visual_slam
    --map-poses``). With scan insertion (``slam.inserter``), the scans are written at the given
    poses too. The pin is not part of checkpoints: call it again after ``slam.resume``.
    """
    cache = slam.cache
    poses = torch.as_tensor(np.asarray(poses), dtype=cache.z.dtype)
    if poses.shape != (slam.T, 3):
        shape = tuple(poses.shape)
        raise ValueError(f"pin_cache needs poses of shape ({slam.T}, 3), got {shape}")
    gen = torch.Generator().manual_seed(seed)

    def store(t, p, generator=None):  # [C] steps; the particles p are ignored
        eps = torch.randn(len(t), cache.num_particles, 3, generator=gen, dtype=poses.dtype)
        cache.z[t] = poses[t].unsqueeze(-2) + noise * eps
        cache.filled[t] = True

    cache.store = store
    if slam.inserter is not None:
        insert = slam.inserter.insert

        def insert_pinned(x, valid, z, var=0.0, scale=1.0):  # the step's scan at its pinned pose
            insert(x, valid, poses[slam.state.t].to(x.dtype), var, scale)

        slam.inserter.insert = insert_pinned
