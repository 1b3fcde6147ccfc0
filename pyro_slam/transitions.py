"""Transition models ``p(z_{t+1} | z_t, u_t, m_t) = N(mu_T(z_t, u_t, mu_E(m_t)), sigma_T^2)``.

Two interchangeable choices (paper III-B, Appendix B-B), both :class:`Transition`\\ s:

* :class:`KinematicTransition` -- engineered: the simulator's kinematics (rotate, then move along
  the heading) or a robot-frame odometry increment; optionally stops short of walls that the
  model's predicted scan shows ahead (used by the planner).
* :class:`LearnedTransition` -- the 6 x 256 ReLU MLP of :class:`~pyro_slam.networks.TransitionMLP`,
  pretrained on a held-out maze with ground-truth poses and scans (:func:`pretrain_transition`).

``mean(z, u, scan)`` takes the emission mean ``mu_E(m_t)`` read in the body frame (``[..., B]``),
which is the predicted LiDAR scan at ``z_t``; kinematic transitions ignore it unless clipping.
Headings are *not* wrapped inside the model (trigonometry is periodic); wrap when reporting.
"""

from __future__ import annotations

import torch
from torch import nn
from tqdm.auto import tqdm

from .geometry import odometry_delta
from .networks import TransitionMLP


class Transition(nn.Module):
    """Base class: Gaussian transition with per-dimension std ``sigma`` (x, y, heading)."""

    def __init__(self, sigma):
        super().__init__()
        self.register_buffer("sigma", torch.as_tensor(sigma, dtype=torch.get_default_dtype()))

    def mean(self, z: torch.Tensor, u: torch.Tensor, scan: torch.Tensor | None) -> torch.Tensor:
        """``z [..., 3]``, ``u [..., D_u]``, ``scan [..., B]`` or None -> ``[..., 3]``."""
        raise NotImplementedError

    needs_scan = False


class KinematicTransition(Transition):
    """Engineered transition.

    Args:
        sigma: std of the Gaussian noise on (x, y, heading), shape ``[3]`` or scalar.
        control_model: ``"rotate_forward"`` (u = (rotation, forward offset)) or
            ``"odometry_delta"`` (u = (dx, dy, dtheta) in the robot frame).
        clip_margin: if not None, forward motion stops ``clip_margin`` short of the range that the
            predicted scan shows straight ahead (``scan[..., forward_beam]``).
        forward_beam: index of the beam pointing along the heading (beam angle 0).
    """

    def __init__(self, sigma, control_model="rotate_forward", clip_margin=None, forward_beam=0):
        super().__init__(sigma)
        if control_model not in ("rotate_forward", "odometry_delta"):
            raise ValueError(f"unknown control_model {control_model!r}")
        self.control_model = control_model
        self.clip_margin = clip_margin
        self.forward_beam = forward_beam
        self.needs_scan = clip_margin is not None

    def mean(self, z, u, scan=None):
        if self.control_model == "odometry_delta":
            out = odometry_delta(z, u)
            return torch.cat([out[..., :2], z[..., 2:] + u[..., 2:3]], dim=-1)
        h = z[..., 2] + u[..., 0]
        d = u[..., 1].expand_as(h)
        if self.clip_margin is not None and scan is not None:
            # the scan is read at z_t; after rotating, the forward range is that of the beam
            # nearest to the new heading -- approximate with the forward beam when the
            # rotation is small, which is what the planner's short steps produce.
            free = scan[..., self.forward_beam] - self.clip_margin
            d = torch.minimum(d, free.clamp_min(0.0))
        return torch.stack([z[..., 0] + d * torch.cos(h), z[..., 1] + d * torch.sin(h), h], -1)


class LearnedTransition(Transition):
    """Wraps a :class:`TransitionMLP`; ``scan`` is the body-frame predicted scan at ``z_t``."""

    needs_scan = True

    def __init__(self, net: TransitionMLP, sigma):
        super().__init__(sigma)
        self.net = net

    def mean(self, z, u, scan=None):
        if scan is None:
            raise ValueError("LearnedTransition needs the predicted scan mu_E(m_t)")
        return self.net(z, u, scan)

    def to_state(self) -> dict:
        """A ``torch.save``-able dict (weights only) that :meth:`from_state` reads back."""
        n = self.net
        meta = {"control_dim": n.control_dim, "n_scan": n.n_scan}
        meta["hidden"], meta["layers"] = n.hidden, n.layers
        return {"meta": meta, "state_dict": self.state_dict()}

    @classmethod
    def from_state(cls, blob: dict) -> LearnedTransition:
        m = blob["meta"]
        net = TransitionMLP(m["control_dim"], m["n_scan"], m["hidden"], m["layers"])
        out = cls(net, torch.zeros(3))
        out.load_state_dict(blob["state_dict"])
        return out


def pretrain_transition(
    traversals,
    *,
    hidden: int = 256,
    layers: int = 6,
    epochs: int = 30,
    batch_size: int = 256,
    lr: float = 1e-3,
    val_fraction: float = 0.1,
    seed: int = 0,
    progress: bool = True,
) -> tuple[LearnedTransition, dict]:
    """Fit a :class:`LearnedTransition` on traversals with ground-truth poses and scans.

    The network regresses ``z_{t+1} - z_t`` (heading difference wrapped) from ``(z_t, u_t,
    x_t)``; ``sigma_T`` is set to the residual std on the held-out last ``val_fraction`` of the
    data ("noise learned"). Returns the transition and a dict of training statistics.
    """
    from .geometry import wrap_angle

    gen = torch.Generator().manual_seed(seed)
    zs, us, xs, dz = [], [], [], []
    for tr in traversals:
        if tr.poses is None:
            raise ValueError("pretrain_transition needs traversals with ground-truth poses")
        p = torch.as_tensor(tr.poses, dtype=torch.float32)
        zs.append(p[:-1])
        us.append(torch.as_tensor(tr.controls, dtype=torch.float32))
        xs.append(torch.as_tensor(tr.observations[:-1], dtype=torch.float32))
        d = p[1:] - p[:-1]
        d[:, 2] = wrap_angle(d[:, 2])
        dz.append(d)
    z, u, x, d = (torch.cat(a) for a in (zs, us, xs, dz))
    net = TransitionMLP(u.shape[-1], x.shape[-1], hidden, layers)
    with torch.no_grad():
        net.fit_normalisation(net.features(z, u, x), d)
    n = z.shape[0]
    n_val = max(1, int(n * val_fraction))
    tr_idx, val_idx = torch.arange(n - n_val), torch.arange(n - n_val, n)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)

    def residual(idx):
        pred = net(z[idx], u[idx], x[idx]) - z[idx]
        return (pred - d[idx]) / net.out_scale

    bar = tqdm(range(epochs), desc="pretrain transition", disable=not progress)
    for _ in bar:
        perm = tr_idx[torch.randperm(len(tr_idx), generator=gen)]
        for i in range(0, len(perm), batch_size):
            loss = residual(perm[i : i + batch_size]).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
        with torch.no_grad():
            val = residual(val_idx).pow(2).mean().item()
        bar.set_postfix(val_mse=f"{val:.4f}")
    with torch.no_grad():
        res = residual(val_idx) * net.out_scale
        sigma = res.std(0).clamp_min(1e-5)
    stats = {"val_mse_normalised": val, "sigma": sigma.tolist(), "n_train": len(tr_idx)}
    return LearnedTransition(net, sigma), stats
