"""Occupancy-grid scan insertion: a warm start of ``q(M)`` for the ray-cast LiDAR emission.

Each online scan's hits, placed from the pose estimate, are joined into a polyline (hits of
neighbouring beams closer than ``gap`` are one wall, sampled at half a grid spacing) and the
grid points nearest to it that no earlier scan hit get the mean ``occupancy`` and the scale
``scale`` in ``q(M)``. The grid points each beam crosses up to a grid spacing short of its return
(up to the range for a miss), where nothing was written yet, get the mean ``free`` and the same
scale: known free space, which a later hit may still overwrite. SVI then refines the map.
Readings at the sensor's range are misses and write no wall.
"""

from __future__ import annotations

import math

import torch

from .config import ScanInsertionConfig


class ScanInserter:
    """Writes scans into a map guide's mean and scale.

    Args:
        config: the :class:`~pyro_slam.slam.config.ScanInsertionConfig`.
        model: the :class:`~pyro_slam.model.DVBFLM` (its grid and ray-cast emission).
        leaves: where the guide keeps ``q(M)``'s mean and scale,
            :func:`~pyro_slam.model.guide.map_param_leaves`.
    """

    def __init__(self, config: ScanInsertionConfig, model, leaves):
        self.cfg, self.model = config, model
        self.loc, self.raw_scale, self.to_raw = leaves
        w, h, _ = model.grid.shape
        self.inserted = torch.zeros((w, h), dtype=torch.bool)  # [w, h] hit by a scan
        self.freed = torch.zeros((w, h), dtype=torch.bool)  # [w, h] crossed by a beam

    def hit_cells(self, x: torch.Tensor, valid: torch.Tensor, z: torch.Tensor):
        """Grid points ``(i [P], j [P])`` nearest to the polyline of the hits of scan
        ``x [B]`` (``valid [B]`` bool) placed from pose ``z [3]``."""
        em, g = self.model.emission, self.model.grid
        hit = (x < em.max_range * (1 - 1e-3)) & valid  # [B]
        ang = z[2] + em.beam_angles.to(x.dtype)  # [B]
        pts = z[:2] + x[:, None] * torch.stack([ang.cos(), ang.sin()], -1)  # [B, 2]
        w, h, _ = g.shape
        spacing = min(g.size[0] / (w - 1), g.size[1] / (h - 1))
        nxt = torch.roll(torch.arange(x.shape[0]), -1)  # [B] the neighbouring beam
        seg = hit & hit[nxt] & ((pts[nxt] - pts).norm(dim=-1) < self.cfg.gap)  # [B]
        n = int(math.ceil(self.cfg.gap / (0.5 * spacing))) + 1
        f = torch.linspace(0, 1, n, dtype=x.dtype)[:, None, None]  # [n, 1, 1]
        on = pts[seg] + f * (pts[nxt][seg] - pts[seg])  # [n, S, 2] along joined pairs
        p = torch.cat([pts[hit], on.reshape(-1, 2)])  # [P, 2]
        c = [(p[:, k] - g.origin[k]) * ((m - 1) / g.size[k]) for k, m in enumerate((w, h))]
        return tuple(ck.round().long().clamp(0, m - 1) for ck, m in zip(c, (w, h)))

    def free_cells(self, x: torch.Tensor, valid: torch.Tensor, z: torch.Tensor):
        """Grid points ``(i [P], j [P])`` the beams of scan ``x [B]`` (``valid [B]``) cross from
        pose ``z [3]`` up to a grid spacing short of their returns (up to the range where they
        miss), sampled at half a spacing."""
        em, g = self.model.emission, self.model.grid
        w, h, _ = g.shape
        spacing = min(g.size[0] / (w - 1), g.size[1] / (h - 1))
        hit = x < em.max_range * (1 - 1e-3)
        reach = torch.where(hit, x - spacing, x.new_tensor(em.max_range)).clamp_min(0)[valid]
        ang = z[2] + em.beam_angles.to(x.dtype)[valid]  # [V]
        n = int(math.ceil(em.max_range / (0.5 * spacing))) + 1
        d = torch.linspace(0, 1, n, dtype=x.dtype)[:, None] * reach  # [n, V]
        p = z[:2] + d[..., None] * torch.stack([ang.cos(), ang.sin()], -1)  # [n, V, 2]
        p = p.reshape(-1, 2)
        c = [(p[:, k] - g.origin[k]) * ((m - 1) / g.size[k]) for k, m in enumerate((w, h))]
        return tuple(ck.round().long().clamp(0, m - 1) for ck, m in zip(c, (w, h)))

    def insert(self, x: torch.Tensor, valid: torch.Tensor, z: torch.Tensor) -> None:
        """Write scan ``x [B]`` (``valid [B]``) placed from pose ``z [3]``: its walls where no
        scan hit yet, then (with ``free``) its free space where nothing was written yet."""
        scale = self.to_raw(self.raw_scale.new_tensor(self.cfg.scale))  # the store's unconstrained
        i, j = self.hit_cells(x, valid, z)
        new = ~self.inserted[i, j]  # [P]
        self._write(i[new], j[new], self.cfg.occupancy, scale)
        self.inserted[i[new], j[new]] = True
        if self.cfg.free is not None:
            i, j = self.free_cells(x, valid, z)
            new = ~(self.inserted[i, j] | self.freed[i, j])
            self._write(i[new], j[new], self.cfg.free, scale)
            self.freed[i[new], j[new]] = True

    def _write(self, i, j, value: float, raw_scale) -> None:
        with torch.no_grad():
            self.loc[i, j, 0] = value
            self.raw_scale[i, j, 0] = raw_scale

    def state_dict(self) -> dict:
        return {"inserted": self.inserted.clone(), "freed": self.freed.clone()}

    def load_state_dict(self, d: dict) -> None:
        self.inserted.copy_(d["inserted"])
        self.freed.copy_(d["freed"])
