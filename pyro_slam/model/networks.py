"""Neural networks of DVBF-LM (paper Appendix B, Table I).

* :class:`EmissionMLP`  -- ``mu_E``: chart ``m_t`` [..., D_m] -> world-frame range profile
  [..., n_world] (4 x 256, softsign).
* :class:`TransitionMLP` -- ``mu_T``: ``(cos h, sin h, u, mu_E(m_t))`` -> pose increment
  (6 x 256, ReLU).

Networks know nothing of Pyro or of sensors; :mod:`pyro_slam.model.emissions` wires them into
observation read-outs and :mod:`pyro_slam.model.model` into distributions.
"""

from __future__ import annotations

import torch
from torch import nn


class Softsign(nn.Module):
    """``x / (1 + |x|)``; in place when no gradient is needed (filtering: ~30% faster MLP)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if torch.is_grad_enabled() and x.requires_grad:
            return x / (1 + x.abs())
        return x.div_(x.abs().add_(1))


def mlp(n_in: int, n_out: int, hidden: int, layers: int, activation: type[nn.Module]):
    """``layers`` hidden layers of ``hidden`` units, then a linear read-out."""
    mods: list[nn.Module] = []
    d = n_in
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), activation()]
        d = hidden
    mods.append(nn.Linear(d, n_out))
    return nn.Sequential(*mods)


# the paper's LiDAR emission network (Appendix B-A): D_m = 10 map features, 4 x 256 softsign
# layers, a world-frame profile of at least 20 directions (one per beam where there are more)
LIDAR_MAP_DIM, LIDAR_HIDDEN, LIDAR_LAYERS, MIN_WORLD_DIRECTIONS = 10, 256, 4, 20
# the visual row MLPs, reduced from the paper's 4 x 256 to 4 x 64 for CPU; 32 angular bins
IMAGE_HIDDEN, IMAGE_LAYERS, IMAGE_BINS = 64, 4, 32


class EmissionMLP(nn.Module):
    """``mu_E``: map chart -> world-frame range profile at ``n_world`` equally spaced angles.

    Args:
        map_dim: ``D_m``.
        n_world: number of world-frame directions (``2 pi j / n_world``, j = 0..n_world-1).
        scale: output scale (e.g. the sensor's max range); the output is ``scale * net(m)``, so
            that the network works on O(1) numbers.
    """

    def __init__(
        self,
        map_dim: int,
        n_world: int,
        hidden: int = LIDAR_HIDDEN,
        layers: int = LIDAR_LAYERS,
        scale: float = 1.0,
    ):
        super().__init__()
        self.map_dim, self.n_world, self.scale = map_dim, n_world, float(scale)
        self.net = mlp(map_dim, n_world, hidden, layers, Softsign)

    def forward(self, m: torch.Tensor) -> torch.Tensor:
        """``m [..., D_m]`` -> ``[..., n_world]``."""
        return self.scale * self.net(m)


class TransitionMLP(nn.Module):
    """``mu_T``: predicts the pose increment from heading, control and predicted scan.

    Input ``[cos h, sin h, u (D_u), scan (n_scan)]``; output ``(dx, dy, dh)`` added to ``z``.
    Feeding the (predicted) scan ``mu_E(m_t)`` instead of ``m_t`` lets the network be pretrained
    with ground-truth scans (paper Appendix B-B).
    """

    def __init__(self, control_dim: int, n_scan: int, hidden: int = 256, layers: int = 6):
        super().__init__()
        self.control_dim, self.n_scan = control_dim, n_scan
        self.hidden, self.layers = hidden, layers
        self.net = mlp(2 + control_dim + n_scan, 3, hidden, layers, nn.ReLU)
        # input/output normalisation, set from data by `fit_normalisation`
        self.register_buffer("in_loc", torch.zeros(2 + control_dim + n_scan))
        self.register_buffer("in_scale", torch.ones(2 + control_dim + n_scan))
        self.register_buffer("out_scale", torch.ones(3))

    def features(self, z: torch.Tensor, u: torch.Tensor, scan: torch.Tensor) -> torch.Tensor:
        batch = torch.broadcast_shapes(z.shape[:-1], u.shape[:-1], scan.shape[:-1])
        h = z[..., 2:3].expand(*batch, 1)
        u = u.expand(*batch, u.shape[-1])
        scan = scan.expand(*batch, scan.shape[-1])
        return torch.cat([torch.cos(h), torch.sin(h), u, scan], dim=-1)

    def fit_normalisation(self, feats: torch.Tensor, deltas: torch.Tensor) -> None:
        """Standardise inputs ``[N, F]`` and scale outputs ``[N, 3]`` from training data."""
        self.in_loc.copy_(feats.mean(0))
        self.in_scale.copy_(feats.std(0).clamp_min(1e-6))
        self.out_scale.copy_(deltas.std(0).clamp_min(1e-6))

    def forward(self, z: torch.Tensor, u: torch.Tensor, scan: torch.Tensor) -> torch.Tensor:
        """``z [..., 3]``, ``u [..., D_u]``, ``scan [..., n_scan]`` (broadcasting) -> next pose
        ``[..., 3]``."""
        x = (self.features(z, u, scan) - self.in_loc) / self.in_scale
        return z + self.net(x) * self.out_scale
