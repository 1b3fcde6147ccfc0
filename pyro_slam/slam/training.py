"""Fitting with known poses: pretraining an emission (:func:`pretrain_emission`) and mapping
(:func:`fit_map`), both maximising ``E_q(M)[log p(x_t | z_t, M)] - KL(q(M) || p(M)) / T`` on
minibatches of time steps, with the poses ``z_t`` given; and the emission's noise fitted to a
traversal (:func:`fit_noise`)."""

from __future__ import annotations

import numpy as np
import pyro
import pyro.distributions as dist
import torch
from pyro.infer import SVI, TraceMeanField_ELBO
from pyro.optim import Adam
from torch.distributions import kl_divergence
from tqdm.auto import tqdm

from ..model import DVBFLM, Emission, EmissionMLP, LidarEmission, MapGuide, map_marginals
from .build import build_model, traversal_tensors
from .config import SLAMConfig

POSITIVE = dist.constraints.positive
SHARE = dist.constraints.interval(0.0, 0.5)  # an outlier probability fitted to a log


def _map_params(model: DVBFLM):
    """A fresh mean-field ``q(M)`` at the prior: ``loc``, ``log_scale`` ``[w, h, D_m]``."""
    loc = torch.zeros(model.grid.shape, requires_grad=True)
    log_scale = torch.zeros(model.grid.shape, requires_grad=True)
    return loc, log_scale


def _negative_elbo(model: DVBFLM, loc, log_scale, obs, mask, poses, idx, T: int):
    """``-E_q[log p(x | z, M)]`` (one sample, mean over the steps ``idx``) ``+ KL(q || p) / T``
    with the model's own map prior and emission noise (Monte Carlo KL where no closed form)."""
    q = dist.Normal(loc, log_scale.exp()).to_event(1)  # batch [w, h], event [D_m]
    M = q.rsample()
    mean = model.emission_mean(M, poses[idx], obs[idx])
    ll = model.emission_log_prob(obs[idx], mean, None if mask is None else mask[idx])
    prior = model.map_prior()
    try:
        kl = kl_divergence(q, prior).sum()
    except NotImplementedError:
        kl = (q.log_prob(M) - prior.log_prob(M)).sum()
    return -ll.mean() + kl / T


def pretrain_emission(
    traversals,
    config: SLAMConfig,
    *,
    emission: Emission | EmissionMLP | None = None,
    steps: int = 2000,
    batch_size: int = 256,
    lr_map: float = 0.05,
    lr_emission: float = 1e-3,
    seed: int = 0,
    progress: bool = True,
) -> tuple[Emission | EmissionMLP, dict]:
    """Fit ``mu_E`` on prepared traversals with ground-truth poses (one map belief per
    traversal), starting from ``emission`` (default: a new one of ``config.emission.kind``).
    The maps are discarded and the emission network is returned, to be reused (frozen) for
    SLAM in new mazes."""
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    models, params, data = [], [], []
    for tr in traversals:
        m, _ = build_model(tr, config, emission=emission)
        emission = m.emission
        loc, log_scale = _map_params(m)
        obs, _, mask, _ = traversal_tensors(tr)
        models.append(m)
        params += [loc, log_scale]
        data.append((obs, mask, torch.as_tensor(tr.poses, dtype=obs.dtype), loc, log_scale))
    opt = torch.optim.Adam(
        [{"params": params, "lr": lr_map}, {"params": emission.parameters(), "lr": lr_emission}]
    )
    bar = tqdm(range(steps), desc="pretrain emission", disable=not progress)
    for _ in bar:
        loss = 0.0
        for m, (obs, mask, poses, loc, log_scale) in zip(models, data):
            T = obs.shape[0]
            idx = torch.randint(T, (batch_size,), generator=gen)
            loss = loss + _negative_elbo(m, loc, log_scale, obs, mask, poses, idx, T)
        opt.zero_grad()
        loss.backward()
        opt.step()
        bar.set_postfix(loss=f"{loss.item():.2f}")
    with torch.no_grad():
        m, (obs, mask, poses, loc, _) = models[0], data[0]
        rmse = (m.emission_mean(loc, poses, obs) - obs).pow(2).mean().sqrt().item()
    if isinstance(emission, LidarEmission):  # the network (what the LiDAR checkpoints hold)
        emission = emission.net
    return emission, {"final_loss": loss.item(), "rmse_first_traversal": rmse}


def fit_map(
    traversal,
    model: DVBFLM,
    poses=None,
    steps: int = 1000,
    *,
    guide=None,
    batch_size: int = 256,
    lr: float = 0.05,
    seed: int = 0,
    progress: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mapping with known poses: SVI on :meth:`DVBFLM.mapping_model` (the model's map prior
    and emission, the emission frozen) with ``TraceMeanField_ELBO`` (analytic KL where both
    sides have one), by Adam on minibatches of time steps, with the poses ``z_t`` given
    (default: the traversal's ground truth; pass e.g. a SLAM posterior mean instead).
    ``guide``: a factory ``model -> map guide`` (default: the mean-field
    :class:`~pyro_slam.model.MapGuide`; e.g. :func:`~pyro_slam.model.autoguide`). The fit runs
    in a parameter store of its own. Returns ``(loc, scale)``, the marginal mean and std of
    ``q(M)``, each ``[w, h, D_m]`` (detached)."""
    if poses is None:
        if traversal.poses is None:
            raise ValueError("fit_map needs poses (the traversal has no ground truth)")
        poses = traversal.poses
    obs, _, mask, _ = traversal_tensors(traversal)
    z = torch.as_tensor(np.asarray(poses), dtype=obs.dtype)
    learn, frozen = (
        model.learn_emission,
        [p for p in model.emission.parameters() if p.requires_grad],
    )
    model.learn_emission = False
    for p in frozen:
        p.requires_grad_(False)
    with pyro.get_param_store().scope(), torch.random.fork_rng():
        torch.manual_seed(seed)
        q = (
            MapGuide(model.grid.shape, init_scale=model.prior_std())
            if guide is None
            else guide(model)
        )
        svi = SVI(model.mapping_model, q, Adam({"lr": lr}), TraceMeanField_ELBO())
        try:
            for _ in tqdm(range(steps), desc="fit map", disable=not progress):
                svi.step(z, obs, mask, batch_size)
        finally:
            model.learn_emission = learn
            for p in frozen:
                p.requires_grad_(True)
        loc, scale = map_marginals(q)
    return loc.detach(), scale.detach()


def fit_noise(
    traversal,
    model: DVBFLM,
    M,
    poses=None,
    steps: int = 300,
    batch_size: int = 256,
    lr: float = 0.02,
    seed: int = 0,
) -> tuple[float, float]:
    """The emission's noise fitted to a traversal by the ELBO: ``sigma_E`` and the outlier
    probability ``eps`` as Pyro parameters of :meth:`DVBFLM.mapping_model` (maximum likelihood
    under the model's noise family: the map is conditioned on ``M [w, h, D_m]``, e.g. the map
    belief's mean, and the guide has no site), at ``poses [T, 3]`` (default: the traversal's
    ground truth; e.g. a SLAM posterior mean), by Adam on minibatches of ``batch_size`` steps.
    Sets the model's ``sigma_emission`` and ``outlier_prob`` -- so that its predictive (e.g.
    :class:`pyro.infer.Predictive` on :meth:`DVBFLM.model` at that map, the planner's
    rollouts) and everything else that reads the model follow -- and returns them. Runs in a
    parameter store of its own."""
    if poses is None:
        poses = traversal.poses
    obs, _, mask, _ = traversal_tensors(traversal)
    z = torch.as_tensor(np.asarray(poses), dtype=obs.dtype)
    M = torch.as_tensor(M, dtype=obs.dtype).detach()
    before = float(model.sigma_emission), float(model.outlier_prob)
    eps0 = min(max(before[1], 0.01), 0.4)

    def noise_model(*args):
        model.sigma_emission = pyro.param("sigma_E", torch.tensor(before[0]), constraint=POSITIVE)
        model.outlier_prob = pyro.param("outlier_prob", torch.tensor(eps0), constraint=SHARE)
        pyro.condition(model.mapping_model, {"map": M})(*args)

    def no_latent(*args):  # (the map is given: nothing to infer)
        pass

    learn = model.learn_emission
    model.learn_emission = False
    fitted = before
    try:
        with pyro.get_param_store().scope(), torch.random.fork_rng():
            torch.manual_seed(seed)
            svi = SVI(noise_model, no_latent, Adam({"lr": lr}), TraceMeanField_ELBO())
            for _ in range(steps):
                svi.step(z, obs, mask, batch_size)
            fitted = tuple(float(pyro.param(n).detach()) for n in ("sigma_E", "outlier_prob"))
    finally:  # plain numbers again (the fitted ones, or, on an error, the model's own)
        model.learn_emission = learn
        model.sigma_emission, model.outlier_prob = fitted
    return fitted
