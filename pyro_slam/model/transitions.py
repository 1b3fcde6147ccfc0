"""Transition models ``p(z_{t+1} | z_t, u_t, m_t) = N(mu_T(z_t, u_t, mu_E(m_t)), sigma_T^2)``.

Two interchangeable choices (paper III-B, Appendix B-B), both :class:`Transition`\\ s:

* :class:`KinematicTransition` -- engineered: the simulator's kinematics (rotate, then move along
  the heading) or a robot-frame odometry increment; optionally stops short of walls that the
  model's predicted scan shows ahead (used by the planner).
* :class:`LearnedTransition` -- the 6 x 256 ReLU MLP of
  :class:`~pyro_slam.model.networks.TransitionMLP`,
  pretrained on a held-out maze with ground-truth poses and scans (:func:`pretrain_transition`).

``mean(z, u, scan)`` takes the emission mean ``mu_E(m_t)`` read in the body frame (``[..., B]``),
which is the predicted LiDAR scan at ``z_t``; kinematic transitions ignore it unless clipping.
Headings are *not* wrapped inside the model (trigonometry is periodic); wrap when reporting.
"""

from __future__ import annotations

import torch
from torch import nn
from tqdm.auto import tqdm

from ..geometry import odometry_delta, wrap_angle
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
    """Wraps a :class:`TransitionMLP`; ``scan`` is the body-frame predicted scan at ``z_t``.

    With ``base_control_model`` set, the network predicts a correction to the kinematic
    prediction (``mean = kinematic(z, u) + mu_T(z, u, scan) - z``; collisions, actuation bias)
    instead of the whole increment -- a residual physics prior that the issue's 6 x 256 MLP
    learns far more accurately from one held-out traversal.
    """

    needs_scan = True

    def __init__(self, net: TransitionMLP, sigma, base_control_model: str | None = None):
        super().__init__(sigma)
        self.net = net
        self.base_control_model = base_control_model
        self.base = None
        if base_control_model is not None:
            self.base = KinematicTransition(0.0, base_control_model)

    def mean(self, z, u, scan=None):
        if scan is None:
            raise ValueError("LearnedTransition needs the predicted scan mu_E(m_t)")
        out = self.net(z, u, scan)
        if self.base is not None:
            out = out - z + self.base.mean(z, u)
        return out

    def to_state(self) -> dict:
        """A ``torch.save``-able dict (weights only) that :meth:`from_state` reads back."""
        n = self.net
        meta = {"control_dim": n.control_dim, "n_scan": n.n_scan}
        meta["hidden"], meta["layers"] = n.hidden, n.layers
        meta["base_control_model"] = self.base_control_model
        return {"meta": meta, "state_dict": self.state_dict()}

    @classmethod
    def from_state(cls, blob: dict) -> LearnedTransition:
        m = blob["meta"]
        net = TransitionMLP(m["control_dim"], m["n_scan"], m["hidden"], m["layers"])
        out = cls(net, torch.zeros(3), m.get("base_control_model"))
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
    residual: bool = True,
) -> tuple[LearnedTransition, dict]:
    """Fit a :class:`LearnedTransition` on traversals with ground-truth poses and scans.

    The network regresses ``z_{t+1} - z_t`` (heading difference wrapped) from ``(z_t, u_t,
    x_t)`` -- with ``residual=True`` minus the kinematic increment of the traversals'
    ``control_model``, see :class:`LearnedTransition`; ``sigma_T`` is set to the residual std
    on the held-out last ``val_fraction`` of the data ("noise learned"). Returns the transition
    and a dict of training statistics.
    """
    gen = torch.Generator().manual_seed(seed)
    zs, us, xs, dz = [], [], [], []
    control_model = traversals[0].metadata.get("control_model", "rotate_forward")
    base = KinematicTransition(0.0, control_model) if residual else None
    for tr in traversals:
        if tr.poses is None:
            raise ValueError("pretrain_transition needs traversals with ground-truth poses")
        p = torch.as_tensor(tr.poses, dtype=torch.float32)
        zs.append(p[:-1])
        us.append(torch.as_tensor(tr.controls, dtype=torch.float32))
        xs.append(torch.as_tensor(tr.observations[:-1], dtype=torch.float32))
        u_t = us[-1]
        ref = p[:-1] if base is None else base.mean(p[:-1], u_t)  # what the net corrects
        d = p[1:] - ref
        d[:, 2] = wrap_angle(d[:, 2])
        dz.append(d)
    z, u, x, d = (torch.cat(a) for a in (zs, us, xs, dz))
    net = TransitionMLP(u.shape[-1], x.shape[-1], hidden, layers)
    with torch.no_grad():
        net.fit_normalisation(net.features(z, u, x), d)
    n = z.shape[0]
    n_val = max(1, int(n * val_fraction))
    tr_idx, val_idx = torch.arange(n - n_val), torch.arange(n - n_val, n)
    opt = torch.optim.Adam(net.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)

    def err(idx):
        pred = net(z[idx], u[idx], x[idx]) - z[idx]
        return (pred - d[idx]) / net.out_scale

    # early stopping on the held-out tail: the residual targets are mostly actuation noise,
    # which a 6 x 256 network otherwise overfits
    best, best_state = float("inf"), None
    bar = tqdm(range(epochs), desc="pretrain transition", disable=not progress)
    for _ in bar:
        perm = tr_idx[torch.randperm(len(tr_idx), generator=gen)]
        for i in range(0, len(perm), batch_size):
            loss = err(perm[i : i + batch_size]).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
        with torch.no_grad():
            val = err(val_idx).pow(2).mean().item()
        if val < best:
            best, best_state = val, {k: v.clone() for k, v in net.state_dict().items()}
        bar.set_postfix(val_mse=f"{val:.4f}")
    net.load_state_dict(best_state)
    with torch.no_grad():
        res = err(val_idx) * net.out_scale
        sigma = res.std(0).clamp_min(1e-5)
    stats = {"val_mse_normalised": best, "sigma": sigma.tolist(), "n_train": len(tr_idx)}
    return LearnedTransition(net, sigma, control_model if residual else None), stats
