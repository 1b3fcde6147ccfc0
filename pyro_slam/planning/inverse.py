"""Amortised inverse model ``q(z | x)``: observation targets -> pose targets (paper section V-c).

A VAE over single LiDAR scans whose *decoder is the frozen DVBF-LM emission* on a fixed map ``M``
(the mean of the learned ``q(M)``), trained once per maze on the scans of the traversal that
was used to learn the map (no poses enter the loss):

    model:  xy ~ N(c, (s/2)^2 I)        position prior, broad over the map extent (centre c,
                                        side s of the planning bounds), [N, 2]
            h  ~ Uniform(circle)        heading prior, flat (an improper flat density on the
                                        real line; the decoder is 2 pi-periodic in h), [N]
            x  ~ N(mu_E(f_m(z, M), z), sigma^2 I),  z = (xy, h)         [N, B]
    guide:  q(z | x) = N(xy; mu_xy(x), diag s_xy(x)^2) N(h; mu_h(x), s_h(x)^2)

The encoder (:class:`PoseEncoder`) first *canonicalises* the scan's rotation: a scan at
heading ``h`` reads the world-frame range profile at ``h + beam_angles``, so the phase ``psi``
of its first circular Fourier coefficient is ``h`` plus a function of the position only;
rotating the scan by ``-psi`` (:func:`~pyro_slam.networks.rotate_scan`, the emission's own
read-out) gives a scan that depends on the position alone. An MLP on the canonical scan
(divided by ``max_range``) outputs the position mean squashed into the bounds by a sigmoid, an
*unnormalised direction vector* ``(c, s)`` whose angle plus ``psi`` is the heading mean
``mu_h`` (continuous across the +-pi wrap-around, unlike a regressed angle), and three scales
squashed into ``[min_scale, max_scale]``. Samples ``h = mu_h + s_h eps`` live on the real
line; since the decoder reads the map at ``h`` through a periodic beam rotation, ``q`` acts as a
wrapped normal on the circle, whose entropy the Gaussian's equals up to ``O(exp(-2 pi^2 /
s_h^2))`` -- negligible for the small ``s_h`` the encoder learns. The ELBO ``E_q[log p(x | z,
M)] - KL(q(z | x) || p(z))`` is therefore exact up to the constant ``-log 2 pi`` of the flat
heading prior and that wrap-around term. It is maximised by :class:`pyro.infer.SVI` with
``Trace_ELBO`` (reparameterised samples) on minibatches of scans (a subsampled
``pyro.plate``); map and emission are constants of the model, hence frozen. The encoder is
initialised by a wake-sleep *sleep phase* on scans dreamed by the decoder at prior poses
(:meth:`InversePose.fit`): from a random encoder the ELBO alone got stuck in a collapsed local
optimum.

**Target pose = mode.** A single Gaussian cannot represent perceptual aliasing (several poses
explaining one scan), and on the 1 x 1 test mazes the encoder alone is far from accurate (see
``docs/navigation.md``), so :meth:`InversePose.infer` does not stop at the encoder mean: its
candidates are the mean and ``n_samples`` samples of ``q(z | x)`` plus ``n_restarts`` restarts,
the best-scoring poses of a coarse grid over the explored map (:meth:`restart_grid`); each is
refined by ``refine_steps`` Adam steps on ``log p(x | z, M) + log p(z)`` (the unnormalised
posterior of the model) and the candidate of highest ``log p(x | z, M)`` wins -- a mode of
``p(z | x, M)``. ``n_samples = n_restarts = refine_steps = 0`` gives the plain encoder mean,
the mode of ``q(z | x)``. :meth:`InversePose.modes` keeps several distinct modes, best first,
which the agent of :mod:`pyro_slam.planning.seek` visits in turn.
"""

from __future__ import annotations

import math

import numpy as np
import pyro
import pyro.distributions as dist
import torch
from pyro.infer import SVI, Trace_ELBO
from pyro.optim import Adam
from torch import nn
from tqdm import tqdm

from ..geometry import wrap_angle
from ..metrics import heading_error  # noqa: F401 (re-exported)
from ..model import DVBFLM, mlp, rotate_scan


class PoseEncoder(nn.Module):
    """``q(z | x)``: scans ``[..., B]`` -> pose mean ``[..., 3]`` and scale ``[..., 3]``.

    Beams are assumed evenly spaced over the circle, beam ``i`` at ``2 pi i / B`` (the
    simulator's LiDAR).

    Args:
        n_beams: ``B``; scans with another last dimension raise :class:`ValueError`.
        max_range: sensor range, the scans are divided by it.
        bounds: ``(x0, x1, y0, y1)`` the position mean is squashed into.
        hidden, layers: MLP width and depth (ReLU).
        min_scale, max_scale: range of the position scales; the heading scale is capped at
            ``max_heading_scale`` (rad) so that ``q`` cannot spread over the whole circle, where
            the Gaussian entropy would no longer be the wrapped normal's.
    """

    def __init__(
        self,
        n_beams: int,
        max_range: float,
        bounds,
        hidden: int = 256,
        layers: int = 3,
        min_scale: float = 1e-3,
        max_scale: float = 0.2,
        max_heading_scale: float = 1.0,
    ):
        super().__init__()
        self.n_beams, self.max_range = int(n_beams), float(max_range)
        self.register_buffer("min_scale", torch.tensor(min_scale))
        self.register_buffer("max_scale", torch.tensor([max_scale, max_scale, max_heading_scale]))
        x0, x1, y0, y1 = (float(b) for b in bounds)
        self.register_buffer("lo", torch.tensor([x0, y0]))
        self.register_buffer("span", torch.tensor([x1 - x0, y1 - y0]))
        ang = 2 * math.pi * torch.arange(self.n_beams) / self.n_beams  # [B], evenly spaced
        self.register_buffer("beam_angles", ang)
        self.register_buffer("cos", torch.cos(ang))
        self.register_buffer("sin", torch.sin(ang))
        self.net = mlp(self.n_beams, 7, hidden, layers, nn.ReLU)

    def check(self, x: torch.Tensor) -> torch.Tensor:
        x = torch.as_tensor(x, dtype=self.lo.dtype)
        if x.dim() == 0 or x.shape[-1] != self.n_beams:
            raise ValueError(
                f"expected scans of shape [..., {self.n_beams}] (one reading per beam), "
                f"got shape {tuple(x.shape)}"
            )
        return x

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``x [..., B]`` -> ``loc [..., 3]`` (x, y, heading in [-pi, pi)), ``scale [..., 3]``."""
        x = self.check(x)
        c1 = (x * self.cos).sum(-1), -(x * self.sin).sum(-1)  # first Fourier coefficient
        psi = torch.atan2(c1[1], c1[0])  # [...]
        canon = rotate_scan(x, -psi, self.beam_angles)  # [..., B]
        o = self.net(canon / self.max_range)  # [..., 7]
        xy = self.lo + self.span * torch.sigmoid(o[..., :2])  # [..., 2]
        heading = wrap_angle(torch.atan2(o[..., 3], o[..., 2]) + psi)  # [...]
        scale = self.min_scale + (self.max_scale - self.min_scale) * torch.sigmoid(o[..., 4:])
        return torch.cat([xy, heading.unsqueeze(-1)], -1), scale


class InversePose:
    """The VAE ``q(z | x)`` with the frozen DVBF-LM emission on map ``M`` as decoder.

    Args:
        dvbflm: a :class:`~pyro_slam.model.DVBFLM` with a LiDAR emission (frozen here).
        M: map ``[w, h, D_m]`` (e.g. the mean of ``q(M)``).
        bounds: ``(x0, x1, y0, y1)`` of the prior and the encoder (default: the map extent).
        sigma: decoder std. Default: the model's own ``sigma_E`` (the planning model's is
            fitted to its mapping traversal, :func:`~pyro_slam.slam.fit_noise`), rather than
            the training ``sigma_E = 0.1``: with 0.1 the likelihood of one 20-beam scan barely
            localises, the dreamed scans of the sleep phase are mostly noise, and ``q(z | x)``
            stays blurred.
        max_range: sensor range (default: the emission's output scale).
        encoder: a :class:`PoseEncoder` (default: a new one).
        valid: optional ``poses [n, 3] -> bool [n]`` marking where the map is known (e.g.
            :meth:`~pyro_slam.planning.LearnedEnv.valid`: chart std under ``q(M)`` below a
            threshold). Dreamed poses and inferred targets are restricted to it: elsewhere the
            emission extrapolates and can explain a scan better than the true pose does.
    """

    def __init__(
        self,
        dvbflm: DVBFLM,
        M: torch.Tensor,
        bounds=None,
        sigma: float | None = None,
        max_range: float | None = None,
        encoder: PoseEncoder | None = None,
        valid=None,
    ):
        if dvbflm.beam_angles is None:
            raise ValueError("the inverse model needs a LiDAR emission (beam_angles)")
        self.dvbflm, self.M, self.valid = dvbflm, M.detach(), valid
        self.bounds = tuple(float(b) for b in (bounds or dvbflm.grid.extent()))
        self.sigma = float(dvbflm.sigma_emission if sigma is None else sigma)
        if max_range is None:
            max_range = getattr(dvbflm.emission, "net", None)
            max_range = max_range.scale if max_range is not None else 1.0
        n_beams = len(dvbflm.beam_angles)
        self.encoder = encoder or PoseEncoder(n_beams, max_range, self.bounds)
        x0, x1, y0, y1 = self.bounds
        self.prior_loc = torch.tensor([(x0 + x1) / 2, (y0 + y1) / 2])
        self.prior_scale = torch.tensor([(x1 - x0) / 2, (y1 - y0) / 2])

    # ------------------------------------------------------------------ model / guide
    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Predicted scans ``mu_E(f_m(z, M), z)``: ``z [..., 3]`` -> ``[..., B]``."""
        return self.dvbflm.emission_mean(self.M, z)

    def log_likelihood(self, x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """``log p(x | z, M)``: ``x [..., B]``, ``z [..., 3]`` -> ``[...]``."""
        return self.dvbflm.emission_log_prob(x, self.decode(z), sigma=self.sigma)

    def log_prior(self, z: torch.Tensor) -> torch.Tensor:
        """``log p(z)`` up to the constant ``-log 2 pi`` of the flat heading: ``[..., 3]`` ->
        ``[...]``."""
        return dist.Normal(self.prior_loc, self.prior_scale).log_prob(z[..., :2]).sum(-1)

    def model(self, scans: torch.Tensor, batch_size: int | None = None):
        """``scans [N, B]``; a plate over scans, subsampled to ``batch_size``."""
        N = scans.shape[0]
        with pyro.plate("scans", N, subsample_size=batch_size) as idx:
            xy = pyro.sample("xy", dist.Normal(self.prior_loc, self.prior_scale).to_event(1))
            h = pyro.sample("heading", dist.ImproperUniform(dist.constraints.real, (len(idx),), ()))
            z = torch.cat([xy, h.unsqueeze(-1)], -1)  # [n, 3]
            mean = self.decode(z)  # [n, B]
            pyro.sample("x", self.dvbflm.emission_dist(mean, sigma=self.sigma), obs=scans[idx])

    def guide(self, scans: torch.Tensor, batch_size: int | None = None):
        """The amortised ``q(z | x)``, registered as ``pyro.module("pose_encoder")``."""
        pyro.module("pose_encoder", self.encoder)
        N = scans.shape[0]
        with pyro.plate("scans", N, subsample_size=batch_size) as idx:
            loc, scale = self.encoder(scans[idx])  # [n, 3] each
            pyro.sample("xy", dist.Normal(loc[:, :2], scale[:, :2]).to_event(1))
            pyro.sample("heading", dist.Normal(loc[:, 2], scale[:, 2]))

    # ------------------------------------------------------------------------ training
    def sample_prior(self, n: int, generator=None) -> torch.Tensor:
        """Poses uniform over the bounds (and ``valid``) and the circle: ``[n, 3]`` (fewer if
        rejection sampling on ``valid`` falls short after 20 rounds). Used for dreamed scans."""
        x0, x1, y0, y1 = self.bounds
        lo, span = torch.tensor([x0, y0, -math.pi]), torch.tensor([x1 - x0, y1 - y0, 2 * math.pi])
        out, have = [], 0
        for _ in range(20):
            z = lo + span * torch.rand((2 * n, 3), generator=generator)
            if self.valid is not None:
                z = z[torch.as_tensor(self.valid(z.numpy()), dtype=torch.bool)]
            out.append(z)
            have += len(z)
            if have >= n:
                break
        return torch.cat(out)[:n]

    def encoder_log_prob(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``log q(z | x)`` with the heading residual wrapped to ``[-pi, pi)``: ``z [..., 3]``,
        ``x [..., B]`` -> ``[...]``."""
        loc, scale = self.encoder(x)
        r = z - loc
        r = torch.cat([r[..., :2], wrap_angle(r[..., 2:])], -1)
        return dist.Normal(0.0, scale).log_prob(r).sum(-1)

    def fit(
        self,
        scans,
        steps: int = 2000,
        sleep_steps: int = 1000,
        batch_size: int = 256,
        lr: float = 1e-3,
        seed: int = 0,
        progress: bool = False,
    ) -> list[float]:
        """Train ``q(z | x)`` on ``scans [N, B]``; returns the per-step ELBO per scan (up to
        the constant ``-log 2 pi``) of the ELBO phase.

        1. *Sleep phase* (``sleep_steps``; wake-sleep initialisation): maximise
           ``E_{p(z) p(x | z, M)}[log q(z | x)]`` on scans dreamed by the decoder at poses drawn
           uniformly over the bounds. This gives the encoder a global, if blurred, picture of
           the map; the ELBO alone, whose reparameterised gradient only sees the decoder
           locally, gets stuck in poor local optima from a random encoder (observed: all
           scans mapped to one corner with a maximal heading scale).
        2. *ELBO phase* (``steps``): SVI with ``Trace_ELBO`` on minibatches of the real scans.

        Neither phase uses poses of the traversal.
        """
        scans = self.encoder.check(scans)
        pyro.set_rng_seed(seed)
        gen = torch.Generator().manual_seed(seed)
        for p in self.dvbflm.emission.parameters():
            p.requires_grad_(False)
        bs = min(batch_size, scans.shape[0])
        hist = []
        try:
            opt = torch.optim.Adam(self.encoder.parameters(), lr=lr)
            for _ in tqdm(range(sleep_steps), desc="sleep q(z|x)", disable=not progress):
                with torch.no_grad():
                    z = self.sample_prior(batch_size, gen)  # [n, 3]
                    mean = self.decode(z)  # [n, B]
                    x = mean + self.sigma * torch.randn(mean.shape, generator=gen)
                loss = -self.encoder_log_prob(z, x).mean()
                opt.zero_grad()
                loss.backward()
                opt.step()
            # a scope of its own: an encoder fitted before under the same name (another maze's)
            # would otherwise stay in the param store and be what the optimiser steps
            with pyro.get_param_store().scope():
                svi = SVI(self.model, self.guide, Adam({"lr": lr}), Trace_ELBO())
                for _ in tqdm(range(steps), desc="ELBO q(z|x)", disable=not progress):
                    hist.append(-svi.step(scans, bs) / scans.shape[0])
        finally:
            for p in self.dvbflm.emission.parameters():
                p.requires_grad_(True)
        return hist

    @torch.no_grad()
    def elbo(self, scans, num_particles: int = 8, seed: int = 0) -> float:
        """Monte Carlo ELBO per scan on ``scans [N, B]`` (up to ``-log 2 pi``)."""
        scans = self.encoder.check(scans)
        pyro.set_rng_seed(seed)
        loss = Trace_ELBO(num_particles=num_particles).loss(self.model, self.guide, scans)
        return -loss / scans.shape[0]

    # ----------------------------------------------------------------------- inference
    def restart_grid(self, spacing: float = 0.04, headings: int = 12) -> torch.Tensor:
        """Restart poses: positions on a ``spacing`` grid over the bounds (``valid`` ones
        only) times ``headings`` evenly spaced headings: ``[C, 3]``."""
        x0, x1, y0, y1 = self.bounds
        xs = torch.arange(x0 + spacing / 2, x1, spacing)
        ys = torch.arange(y0 + spacing / 2, y1, spacing)
        xy = torch.cartesian_prod(xs, ys)  # [P, 2]
        if self.valid is not None:
            ok = self.valid(torch.cat([xy, torch.zeros(len(xy), 1)], -1).numpy())
            xy = xy[torch.as_tensor(ok, dtype=torch.bool)]
        h = 2 * math.pi * torch.arange(headings) / headings - math.pi
        return torch.cat([xy.repeat_interleave(headings, 0), h.repeat(len(xy)).unsqueeze(-1)], -1)

    def refine(self, x: torch.Tensor, z: torch.Tensor, steps: int = 50, lr: float = 3e-3):
        """Local ascent of ``log p(x | z, M) + log p(z)``: ``steps`` Adam steps from poses
        ``z [..., 3]`` for scans ``x [..., B]``; returns the refined poses ``[..., 3]``."""
        if not steps:
            return z
        frozen = [p.requires_grad for p in self.dvbflm.emission.parameters()]
        for p in self.dvbflm.emission.parameters():
            p.requires_grad_(False)
        z = z.detach().clone().requires_grad_(True)
        opt = torch.optim.Adam([z], lr=lr)
        try:
            for _ in range(steps):
                loss = -(self.log_likelihood(x, z) + self.log_prior(z)).sum()
                opt.zero_grad()
                loss.backward()
                opt.step()
        finally:
            for p, r in zip(self.dvbflm.emission.parameters(), frozen, strict=True):
                p.requires_grad_(r)
        return z.detach()

    def candidates(
        self,
        scans,
        n_samples: int = 16,
        n_restarts: int = 32,
        refine_steps: int = 50,
        lr: float = 3e-3,
        restart_spacing: float = 0.03,
        restart_headings: int = 36,
        seed: int = 0,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Refined candidate poses for observations ``scans [N, B]``: poses ``[N, K, 3]``, their
        ``log p(x | z, M)`` ``[N, K]`` and their score ``[N, K]`` (the log-likelihood, less
        ``1e6`` where the pose is not ``valid``).

        Candidates: the encoder mean, ``n_samples`` samples of ``q(z | x)`` and the
        ``n_restarts`` poses of :meth:`restart_grid` with the highest ``log p(x | z, M)`` (the
        grid's predicted scans are computed once and cached); each is refined by
        ``refine_steps`` Adam steps on ``log p(x | z, M) + log p(z)``.
        """
        x = self.encoder.check(scans).reshape(-1, self.encoder.n_beams)  # [N, B]
        gen = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            loc, scale = self.encoder(x)  # [N, 3]
            eps = torch.randn((x.shape[0], n_samples, 3), generator=gen)
            cands = [loc.unsqueeze(1), loc.unsqueeze(1) + scale.unsqueeze(1) * eps]
            if n_restarts:
                key = (restart_spacing, restart_headings)
                if getattr(self, "_grid_key", None) != key:
                    self._grid = self.restart_grid(restart_spacing, restart_headings)  # [C, 3]
                    self._grid_scans = self.decode(self._grid)  # [C, B]
                    self._grid_key = key
                ll = self.dvbflm.emission_log_prob(
                    x.unsqueeze(1), self._grid_scans.unsqueeze(0), sigma=self.sigma
                )  # [N, C]
                top = ll.topk(min(n_restarts, ll.shape[1]), dim=1).indices  # [N, R]
                cands.append(self._grid[top])
            z = torch.cat(cands, 1)  # [N, K, 3]
        xk = x.unsqueeze(1).expand(-1, z.shape[1], -1)  # [N, K, B]
        z = self.refine(xk, z, refine_steps, lr)
        with torch.no_grad():
            ll = self.log_likelihood(xk, z)  # [N, K]
            score = ll
            if self.valid is not None:
                ok = torch.as_tensor(self.valid(z.reshape(-1, 3).numpy()), dtype=torch.bool)
                score = torch.where(ok.reshape(ll.shape), ll, ll - 1e6)
        return self._clamped(z), ll, score

    def _clamped(self, z: torch.Tensor) -> torch.Tensor:
        """Poses ``[..., 3]`` with the position clamped into the bounds, the heading wrapped."""
        x0, x1, y0, y1 = self.bounds
        z = z.clone()
        z[..., 0] = z[..., 0].clamp(x0, x1)
        z[..., 1] = z[..., 1].clamp(y0, y1)
        z[..., 2] = wrap_angle(z[..., 2])
        return z

    def infer(self, scans, **kw) -> tuple[torch.Tensor, torch.Tensor]:
        """Target poses for observations: ``scans [N, B]`` (or ``[B]``) -> poses ``[N, 3]``
        (heading wrapped to ``[-pi, pi)``) and their ``log p(x | z, M)`` ``[N]``: per scan the
        :meth:`candidates` (keyword arguments go there) of highest score, a mode of
        ``p(z | x, M)``. ``n_samples = n_restarts = refine_steps = 0`` gives the encoder mean,
        the mode of ``q(z | x)``.
        """
        single = self.encoder.check(scans).dim() == 1
        z, ll, score = self.candidates(scans, **kw)  # [N, K, 3], [N, K], [N, K]
        best = score.argmax(1)
        rows = torch.arange(z.shape[0])
        pose, ll = z[rows, best], ll[rows, best]
        return (pose[0], ll[0]) if single else (pose, ll)

    def modes(self, scans, k: int = 3, separation: float = 0.1, **kw) -> list[torch.Tensor]:
        """Up to ``k`` distinct modes of ``p(z | x, M)`` per observation, best first: for
        ``scans [N, B]`` a list of ``N`` pose tensors ``[k_i, 3]``. Greedily by score, a
        candidate (:meth:`candidates`; keyword arguments go there) is kept when it lies more
        than ``separation`` from every kept one and is ``valid`` (unless none is); the first
        is :meth:`infer`'s answer."""
        if k < 1 or not separation > 0:
            raise ValueError(f"k={k} and separation={separation}: need k >= 1, separation > 0")
        z, _, score = self.candidates(scans, **kw)  # [N, K, 3], [N, K]
        out = []
        for zi, si in zip(z, score, strict=True):
            order = torch.argsort(si, descending=True, stable=True)
            ok = si[order] > si[order[0]] - 1e5  # the valid ones, if the best is valid
            keep: list[int] = []
            for j in order[ok].tolist():
                if len(keep) == k:
                    break
                if all(float(torch.dist(zi[j, :2], zi[q, :2])) > separation for q in keep):
                    keep.append(j)
            out.append(zi[keep])
        return out


def fit_inverse(env, traversal, steps: int = 2000, seed: int = 0, **kw) -> InversePose:
    """Train ``q(z | x)`` for a :class:`~pyro_slam.planning.LearnedEnv` (its model and map
    ``M``, bounds and explored region of the planner) on the traversal's scans ``[T, B]``;
    keyword arguments go to :meth:`InversePose.fit`."""
    torch.manual_seed(seed)
    inv = InversePose(
        env.model, env.M, bounds=env.bounds, max_range=traversal.max_range, valid=env.valid
    )
    inv.fit(np.asarray(traversal.observations), steps=steps, seed=seed, **kw)
    return inv
