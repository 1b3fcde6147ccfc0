"""Active SLAM by mutual information (Mirchev et al. 2019, section VI, Appendices D and E).

* :class:`ExploreConfig` -- the agents' configuration (the paper's values by default,
  :meth:`ExploreConfig.smoke` the reduced budget; :func:`with_overrides` for nested changes).
* :func:`knn_entropy` -- Kozachenko--Leonenko k-NN differential entropy estimator (scipy
  ``cKDTree`` neighbour search).
* :class:`Mapper` -- DVBF-LM map learning from collected data: SVI on ``q(M)`` (and optionally
  the emission network) with :class:`~pyro.infer.TraceMeanField_ELBO` on the model's
  :meth:`~pyro_slam.model.DVBFLM.mapping_model`; infogain ``KL(q(M) || p(M))`` against the
  model's prior.
* :func:`mutual_information` -- ``I(x_{1:T}; M | u) ~= H(X) - 1/M sum_m H(X^(m))`` with samples
  from ancestral sampling of a Pyro rollout model (maps drawn from ``q(M)`` and substituted with
  ``poutine.condition``, poses from the known transition, scans from the emission).
* :func:`generate_candidates` -- ``F`` control sequences optimised in parallel with Adam on the
  obstacle penalty (histogram of predicted laser end points, bilinear log density) plus an L2
  turn regulariser (Appendix E).
* :class:`KnownObstacles` -- observed laser end points as point obstacles: planner rollouts
  (MI, execution) stop moves into them, as the simulator stops moves into walls (not in the
  paper; ``plan.block_radius = 0`` turns it off).
* :func:`run_agent` -- Algorithm 1 (``policy="mi"``) and the same loop for the baselines
  (``"random"``, ``"pema"``): execute ``T`` steps, append data, train SVI, log metrics.

Pose inference: the exploration experiments of the paper assume a *known* transition with
``sigma_T = 4e-4``; here the mapper is given the simulator's true poses plus ``N(0, sigma_T)``
noise (the pose posterior of a 20-particle filter under such a transition is essentially that
delta), so map learning is SVI on ``q(M)`` given poses. Rollouts for planning use the kinematic
transition with the same ``sigma_T``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import pyro
import torch
from pyro.infer import SVI, Predictive, TraceMeanField_ELBO
from pyro.optim import Adam
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree
from scipy.special import digamma, gammaln

from simulators import SCALES, World, make_maze

from ..model import DVBFLM, EmissionMLP, KinematicTransition, MapGrid, MapGuide, map_marginals
from ..model.guide import ParamScope, map_kl, sample_maps
from ..pretrained import EMISSION_FILE, PRETRAINED
from ..slam.config import (
    ConfigError,
    _check_components,
    _merge,
    _non_negative,
    _plain,
    _positive,
)

log = logging.getLogger(__name__)

# ----------------------------------------------------------------------------- entropy


def knn_entropy(x, k: int = 1) -> float:
    """Kozachenko--Leonenko estimate of the differential entropy (nats) of samples ``x [N, d]``.

    ``H = psi(N) - psi(k) + log V_d + d / N sum_i log r_i`` with ``r_i`` the distance of sample
    ``i`` to its ``k``-th nearest neighbour and ``V_d`` the volume of the unit ``d``-ball.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    n, d = x.shape
    if n <= k:
        raise ValueError(f"need more than k={k} samples, got {n}")
    r, _ = cKDTree(x).query(x, k=k + 1)
    r = np.maximum(r[:, -1], 1e-300)
    log_vd = 0.5 * d * math.log(math.pi) - gammaln(0.5 * d + 1)
    return float(digamma(n) - digamma(k) + log_vd + d * np.mean(np.log(r)))


# ----------------------------------------------------------------------------- config


@dataclass(frozen=True)
class PlanConfig:
    """Plans of the MI agent (Algorithm 1): ``horizon`` steps ``T`` planned per plan, of which
    the first ``execute_steps`` are executed before the next plan (0: the whole plan, the
    paper); at most ``max_replans`` replans within one block of executed steps when the next
    move is blocked; ``block_radius`` > 0: moves towards an observed laser end point closer
    than this are blocked in the planner's rollouts (MI scoring, execution), 0: no blocking
    (the paper)."""

    horizon: int = 50
    execute_steps: int = 0
    max_replans: int = 0
    block_radius: float = 0.0

    def __post_init__(self):
        h = self.horizon
        if not (isinstance(h, int) and not isinstance(h, bool) and h >= 2):
            raise ConfigError(f"explore.plan.horizon must be an integer >= 2, got {h!r}")
        _non_negative("explore.plan.execute_steps", self.execute_steps, integer=True)
        _non_negative("explore.plan.max_replans", self.max_replans, integer=True)
        _non_negative("explore.plan.block_radius", self.block_radius)


@dataclass(frozen=True)
class CandidateConfig:
    """Candidate generation (Algorithm 2, Appendix E): ``count`` control sequences (``F``)
    optimised with ``steps`` Adam steps at learning rate ``lr`` on the obstacle penalty plus
    ``turn_reg`` times the L2 norm of the per-step heading changes; the penalty's expectation
    takes ``pose_samples`` pose rollouts per candidate; the (pre-tanh) turn parameters start
    from ``N(0, init_std^2)``."""

    count: int = 40
    steps: int = 500
    lr: float = 1e-3
    turn_reg: float = 2.0
    pose_samples: int = 2
    init_std: float = 0.3

    def __post_init__(self):
        _positive("explore.candidates.count", self.count, integer=True)
        _non_negative("explore.candidates.steps", self.steps, integer=True)
        _positive("explore.candidates.lr", self.lr)
        _non_negative("explore.candidates.turn_reg", self.turn_reg)
        _positive("explore.candidates.pose_samples", self.pose_samples, integer=True)
        _non_negative("explore.candidates.init_std", self.init_std)


@dataclass(frozen=True)
class MIConfig:
    """The MI estimate ``H(X) - 1/M sum_m H(X^(m))`` (Appendix D): ``L`` samples of the
    marginal, ``M`` maps of the conditional term with ``K`` samples each, k-NN entropies with
    ``knn_k`` neighbours; every ``obs_stride``-th future scan enters the sample vectors."""

    L: int = 30
    M: int = 40
    K: int = 100
    knn_k: int = 1
    obs_stride: int = 1

    def __post_init__(self):
        for name in ("L", "M", "K", "knn_k", "obs_stride"):
            _positive(f"explore.mi.{name}", getattr(self, name), integer=True)
        for name in ("L", "K"):  # the k-NN estimator needs more than k samples
            if getattr(self, name) <= self.knn_k:
                raise ConfigError(
                    f"explore.mi.{name} must exceed explore.mi.knn_k = {self.knn_k}, "
                    f"got {getattr(self, name)!r}"
                )


@dataclass(frozen=True)
class MotionConfig:
    """How every agent moves: ``step_length`` forward per step after a turn of at most
    ``max_turn`` (rad); ``sigma_T``: the std of the known kinematic transition (the mapper's
    pose noise and the planner's rollouts)."""

    sigma_T: float = 4e-4
    step_length: float = 0.01
    max_turn: float = math.pi / 4

    def __post_init__(self):
        for name in ("sigma_T", "step_length", "max_turn"):
            _positive(f"explore.motion.{name}", getattr(self, name))


@dataclass(frozen=True)
class MappingConfig:
    """The mapper: DVBF-LM with ``map_dim`` map features (``D_m``; 10 fits the shipped
    pretrained emission, the paper has 20), emission noise ``sigma_E``, the emission started
    from the shipped pretrained one if ``pretrained_emission`` and learned along if
    ``learn_emission``; ``train_steps`` SVI steps after each block of executed steps on
    batches of ``batch`` steps, Adam learning rates ``lr_map`` (``q(M)``) and
    ``lr_emission``."""

    train_steps: int = 500
    batch: int = 128
    lr_map: float = 1e-3
    lr_emission: float = 1e-3
    learn_emission: bool = True
    map_dim: int = 10
    pretrained_emission: bool = True
    sigma_E: float = 0.1

    def __post_init__(self):
        _non_negative("explore.mapping.train_steps", self.train_steps, integer=True)
        for name in ("batch", "map_dim"):
            _positive(f"explore.mapping.{name}", getattr(self, name), integer=True)
        for name in ("lr_map", "lr_emission", "sigma_E"):
            _positive(f"explore.mapping.{name}", getattr(self, name))
        for name in ("learn_emission", "pretrained_emission"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(
                    f"explore.mapping.{name} must be true or false, got {getattr(self, name)!r}"
                )


@dataclass(frozen=True)
class ObstacleConfig:
    """The candidates' obstacle density: a histogram of the laser end points predicted from
    the mean map at (at most ``endpoint_poses``) past poses, ``hist_factor`` bins per map cell
    and side, counts blurred by a Gaussian of ``hist_blur`` bins (0: none)."""

    endpoint_poses: int = 2000
    hist_factor: int = 4
    hist_blur: float = 1.0

    def __post_init__(self):
        _positive("explore.obstacles.endpoint_poses", self.endpoint_poses, integer=True)
        _positive("explore.obstacles.hist_factor", self.hist_factor, integer=True)
        _non_negative("explore.obstacles.hist_blur", self.hist_blur)


@dataclass(frozen=True)
class ExploreConfig:
    """The exploration agents' configuration: one component per concern, plus the ``seed``
    of the mapper, the planner and the simulator. ``ExploreConfig()`` holds the paper's values
    (Appendices D and E); :meth:`smoke` is the reduced CPU budget; :func:`with_overrides`
    applies a nested dict of changes, e.g. ``{"mi": {"K": 20}}``."""

    plan: PlanConfig = field(default_factory=PlanConfig)
    candidates: CandidateConfig = field(default_factory=CandidateConfig)
    mi: MIConfig = field(default_factory=MIConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    obstacles: ObstacleConfig = field(default_factory=ObstacleConfig)
    seed: int = 0

    def __post_init__(self):
        _check_components(self, "explore.")
        _non_negative("explore.seed", self.seed, integer=True)

    @classmethod
    def smoke(cls, **over) -> ExploreConfig:
        """The reduced budget (:data:`SMOKE` applied to the paper's values), then the nested
        changes ``over``, e.g. ``smoke(mi={"K": 5}, seed=1)``."""
        return with_overrides(with_overrides(cls(), SMOKE), over)

    def to_dict(self) -> dict:
        """Plain nested dict (JSON-ready)."""
        return _plain(asdict(self))

    @classmethod
    def from_dict(cls, d: dict) -> ExploreConfig:
        """The configuration written by :meth:`to_dict` (missing fields: the defaults)."""
        return with_overrides(cls(), d)


SMOKE = {
    # receding horizon: with the benchmark's T = 50, replan after half of each plan; replan at
    # every blocked move
    "plan": {"horizon": 25, "execute_steps": 25, "max_replans": 1000, "block_radius": 0.02},
    "candidates": {"count": 8, "steps": 200, "lr": 2e-2, "init_std": 0.05},
    "mi": {"L": 20, "M": 8, "K": 20, "obs_stride": 5},
    "mapping": {"train_steps": 60, "lr_map": 2e-2},
}
"""How :meth:`ExploreConfig.smoke` differs from the paper's values."""


def with_overrides(config: ExploreConfig, changes: dict) -> ExploreConfig:
    """``config`` with a nested dict of changes, e.g. ``{"plan": {"horizon": 10}, "seed": 3}``
    (a component may also be given whole). Unknown fields and bad values raise
    :class:`~pyro_slam.slam.config.ConfigError` naming the dotted field
    (``explore.mi.K``)."""
    return _merge(config, changes, ExploreConfig, "explore.")


# ----------------------------------------------------------------------------- mapper


def scale_grid(scale, dim: int) -> MapGrid:
    """The Table II map grid ``w x h`` spanning the maze ``[0, side]^2``."""
    w, h, _ = scale.map_dims
    return MapGrid((w, h), dim, (0.0, 0.0), (scale.side, scale.side))


def _emission(cfg: ExploreConfig, n_world: int, max_range: float) -> EmissionMLP:
    dim = cfg.mapping.map_dim
    em = EmissionMLP(dim, n_world, 256, 4, scale=max_range)
    if cfg.mapping.pretrained_emission:
        blob = torch.load(PRETRAINED / EMISSION_FILE, weights_only=True)
        if blob["meta"].get("map_dim") == dim and blob["meta"]["n_world"] == n_world:
            em.load_state_dict(blob["state_dict"])
    return em


def exploration_model(grid: MapGrid, beam_angles, max_range: float, cfg, prior=None, noise=None):
    """The model the exploring agent maps with (:class:`Mapper`): the emission MLP of
    ``cfg.mapping`` (shipped weights where they fit), the kinematic transition with std
    ``cfg.motion.sigma_T``, ``sigma_E`` ``cfg.mapping.sigma_E``, the map ``prior`` and emission
    ``noise`` (:class:`~pyro_slam.model.DVBFLM`)."""
    em = _emission(cfg, max(len(beam_angles), 20), max_range)
    trans = KinematicTransition(cfg.motion.sigma_T)
    return DVBFLM(
        grid,
        em,
        trans,
        beam_angles,
        cfg.mapping.sigma_E,
        prior=prior,
        noise=noise,
        learn_emission=cfg.mapping.learn_emission,
    )


class Mapper:
    """A DVBF-LM model plus its ``q(M)``, trained by SVI on the data collected so far; the
    mutual information of planned controls (:func:`mutual_information`) is the model's own
    predictive (:class:`pyro.infer.Predictive` on :meth:`DVBFLM.model
    <pyro_slam.model.DVBFLM.model>`, under its handlers) under maps from ``q(M)``.

    Args:
        model: the :class:`~pyro_slam.model.DVBFLM` (:func:`exploration_model`, or a SLAM
            run's, :meth:`from_slam`): its transition, emission, map prior, noise and
            handlers reach the map fit, the infogain and the MI samples.
        cfg: :class:`ExploreConfig`.
        guide: the map guide (default: the mean-field :class:`~pyro_slam.model.MapGuide`),
            called with ``guide_args``.
        scope: the parameter store the guide keeps its parameters in (default: its own,
            :class:`~pyro_slam.model.guide.ParamScope`).

    :meth:`new` builds the exploring agent's mapper for a maze.
    """

    def __init__(self, model: DVBFLM, cfg: ExploreConfig, guide=None, scope=None, guide_args=()):
        self.cfg, self.model = cfg, model
        self.scope = ParamScope() if scope is None else scope
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.max_range = float(getattr(model.emission, "reading_range", model.outlier_range))
        self.beam_angles = model.beam_angles.double().numpy()
        mapping = cfg.mapping

        def per_param(name, _p):
            return {"lr": mapping.lr_emission if name.startswith("emission") else mapping.lr_map}

        self.guide_args = tuple(guide_args)
        with self.scope():
            if guide is None:
                guide = MapGuide(model.grid.shape, init_scale=model.prior_std())
            self.guide = guide
            if hasattr(guide, "params"):  # create its parameters
                guide.params()
            else:
                sample_maps(guide, 1, self.guide_args)
            self.svi = SVI(
                self.model.mapping_model, self.guide, Adam(per_param), TraceMeanField_ELBO()
            )
        self.poses: list[np.ndarray] = []
        self.obs: list[np.ndarray] = []

    @classmethod
    def new(
        cls,
        grid: MapGrid,
        beam_angles,
        max_range: float,
        cfg,
        *,
        prior=None,
        noise=None,
        guide=None,
    ) -> Mapper:
        """The exploring agent's mapper: :func:`exploration_model` (its emission's weights
        drawn from ``cfg.seed``) and a map guide (factory) ``guide``."""
        pyro.set_rng_seed(cfg.seed)  # SVI and rollout sampling use the global RNGs
        model = exploration_model(grid, beam_angles, max_range, cfg, prior, noise)
        mapper = cls(model, cfg, None if guide is None else guide(model))
        mapper.beam_angles = np.asarray(beam_angles, dtype=np.float64)  # (as given, not float32)
        mapper.max_range = float(max_range)
        return mapper

    @classmethod
    def from_slam(cls, slam, cfg: ExploreConfig) -> Mapper:
        """A mapper on a SLAM run: its model (under its handlers) and its map guide, in its
        parameter store; MI is then the run's own predictive under its map belief."""
        return cls(slam.model, cfg, slam.map_guide, slam.scope, slam.elbo.model_args)

    # -- data
    def add(self, poses, scans) -> None:
        """Append true poses ``[n, 3]`` (noised by ``sigma_T``) and scans ``[n, B]``."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        noise = np.random.default_rng(len(self.poses) + self.cfg.seed).normal(size=poses.shape)
        self.poses.append(poses + self.cfg.motion.sigma_T * noise)
        self.obs.append(np.asarray(scans, dtype=np.float64).reshape(poses.shape[0], -1))

    def tensors(self):
        z = torch.as_tensor(np.concatenate(self.poses), dtype=torch.get_default_dtype())
        x = torch.as_tensor(np.concatenate(self.obs), dtype=torch.get_default_dtype())
        return z, x

    def train(self, steps: int) -> list[float]:
        """``steps`` SVI steps on :meth:`~pyro_slam.model.DVBFLM.mapping_model` of the data."""
        if not self.poses:
            return []
        z, x = self.tensors()
        batch = self.cfg.mapping.batch
        with self.scope():
            return [self.svi.step(z, x, None, batch) / len(z) for _ in range(steps)]

    def marginals(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The marginal mean and std of ``q(M)``, ``[w, h, D_m]`` (detached)."""
        with self.scope():
            loc, scale = map_marginals(self.guide, self.guide_args)
        return loc.detach(), scale.detach()

    def infogain(self) -> float:
        """``KL(q(M) || p(M))`` (nats, summed over cells and features) against the model's map
        prior (:func:`~pyro_slam.model.guide.map_kl`)."""
        return float(map_kl(*self.marginals(), self.model.map_prior()))

    # -- the model's predictive for MI
    def sample_observations(self, controls, init_pose, n_maps, n_paths, stride=1):
        """``[n_maps, n_paths, T' * B]`` scans predicted by the model (``DVBFLM.model`` through
        :class:`pyro.infer.Predictive`): ``n_maps`` maps from ``q(M)``, ``n_paths`` pose
        rollouts under each for ``controls [T-1, 2]`` from ``init_pose``; the scans ``x_t`` of
        every ``stride``-th step counted back from the last."""
        T = controls.shape[0] + 1
        kept = [t for t in range(T) if (T - 1 - t) % stride == 0]
        with torch.no_grad():
            with self.scope():
                maps = sample_maps(self.guide, n_maps, self.guide_args)  # [n_maps, w, h, D]
            pred = Predictive(
                self.model.handled(),
                posterior_samples={"map": maps.repeat_interleave(n_paths, 0)},
                return_sites=[f"x_{t}" for t in kept],
                parallel=True,
            )
            s = pred(None, controls, init_pose)
        xs = [s[f"x_{t}"].reshape(n_maps, n_paths, -1) for t in kept]
        return torch.cat(xs, -1)


def mutual_information(mapper: Mapper, controls, init_pose, cfg: ExploreConfig) -> float:
    """``I(x_{1:T}; M | u) ~= H(X) - 1/M sum_m H(X^(m))`` (nats).

    ``X``: ``L`` samples of the marginal (one rollout under each of ``L`` maps from ``q(M)``);
    ``X^(m)``: ``K`` rollouts under map ``m``, ``m = 1..M``.
    """
    init_pose = torch.as_tensor(init_pose, dtype=torch.get_default_dtype())
    s = cfg.mi.obs_stride
    marg = mapper.sample_observations(controls, init_pose, cfg.mi.L, 1, s)[:, 0]
    cond = mapper.sample_observations(controls, init_pose, cfg.mi.M, cfg.mi.K, s)
    h_marg = knn_entropy(marg.numpy(), cfg.mi.knn_k)
    h_cond = np.mean([knn_entropy(c.numpy(), cfg.mi.knn_k) for c in cond])
    return float(h_marg - h_cond)


# ----------------------------------------------------------------------------- candidates


def obstacle_log_density(mapper: Mapper):
    """Histogram of predicted laser end points (mean map, at past poses) on a grid of
    ``obstacles.hist_factor`` x the map cells, as a log density ``[W, H, 1]`` and the
    :class:`MapGrid` that interpolates it bilinearly."""
    cfg = mapper.cfg.obstacles
    g = mapper.model.grid
    w, h, _ = g.shape
    w, h = w * cfg.hist_factor, h * cfg.hist_factor
    z, _ = mapper.tensors()
    if len(z) > cfg.endpoint_poses:
        z = z[torch.linspace(0, len(z) - 1, cfg.endpoint_poses).long()]
    with torch.no_grad():
        scan = mapper.model.emission_mean(mapper.marginals()[0], z)  # [N, B]
    ang = z[:, 2:3] + mapper.model.beam_angles
    hit = scan < 0.95 * mapper.max_range  # beams that see something
    ex = (z[:, 0:1] + scan * torch.cos(ang))[hit].numpy()
    ey = (z[:, 1:2] + scan * torch.sin(ang))[hit].numpy()
    (x0, y0), (sx, sy) = g.origin, g.size
    counts, _, _ = np.histogram2d(ex, ey, bins=(w, h), range=((x0, x0 + sx), (y0, y0 + sy)))
    if cfg.hist_blur > 0:
        counts = gaussian_filter(counts, cfg.hist_blur, mode="constant")
    area = (sx / w) * (sy / h)
    dens = (counts + 0.1) / (counts.sum() + 0.1 * w * h) / area
    logd = torch.as_tensor(np.log(dens), dtype=torch.get_default_dtype())[..., None]
    centres = MapGrid((w, h), 1, (x0 + 0.5 * sx / w, y0 + 0.5 * sy / h), (sx - sx / w, sy - sy / h))
    return logd, centres


def observed_endpoints(poses, scans, beam_angles, max_range: float) -> np.ndarray:
    """World coordinates ``[N, 2]`` of the laser end points that hit something (range below
    ``0.95 max_range``) for poses ``[n, 3]`` and scans ``[n, B]``."""
    poses, scans = np.asarray(poses).reshape(-1, 3), np.asarray(scans).reshape(len(poses), -1)
    ang = poses[:, 2:3] + np.asarray(beam_angles)
    hit = scans < 0.95 * max_range
    ex = poses[:, 0:1] + scans * np.cos(ang)
    ey = poses[:, 1:2] + scans * np.sin(ang)
    return np.stack([ex[hit], ey[hit]], -1)


class KnownObstacles:
    """Observed laser end points as point obstacles, for belief-consistent rollouts.

    A move ``p -> q`` is *blocked* when ``q`` lies within ``radius`` of an end point ``e`` and
    moves towards it (``(q - p) . (e - p) > 0``). The simulator stops a move at a wall; a
    rollout that ignored known walls would let the planner value the unexplored space behind
    a wall it cannot reach (and the MI criterion then prefers exactly those candidates).
    """

    def __init__(self, points, radius: float):
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        self.radius = float(radius)
        self.tree = cKDTree(self.points) if len(self.points) else None

    def blocked(self, p, q) -> np.ndarray:
        """``p, q [..., 2]`` -> ``[...]`` bool."""
        p, q = np.asarray(p, dtype=np.float64), np.asarray(q, dtype=np.float64)
        if self.tree is None or self.radius <= 0:
            return np.zeros(p.shape[:-1], dtype=bool)
        d, i = self.tree.query(q.reshape(-1, 2))
        e = self.points[np.minimum(i, len(self.points) - 1)].reshape(q.shape)
        towards = np.sum((q - p) * (e - p), -1) > 0
        return (d.reshape(q.shape[:-1]) < self.radius) & towards

    def effective_controls(self, pose, controls):
        """Deterministic rollout of ``controls [..., T-1, 2]`` from ``pose [3]`` in which
        blocked moves keep their rotation but do not move (as in the simulator). Returns the
        controls with blocked forward offsets set to 0, and the ``[..., T-1]`` blocked mask."""
        u = np.array(controls, dtype=np.float64)
        z = np.broadcast_to(np.asarray(pose, dtype=np.float64), (*u.shape[:-2], 3)).copy()
        mask = np.zeros(u.shape[:-1], dtype=bool)
        for t in range(u.shape[-2]):
            h = z[..., 2] + u[..., t, 0]
            q = z[..., :2] + u[..., t, 1:2] * np.stack([np.cos(h), np.sin(h)], -1)
            b = self.blocked(z[..., :2], q)
            mask[..., t] = b
            u[..., t, 1] = np.where(b, 0.0, u[..., t, 1])
            z[..., :2] = np.where(b[..., None], z[..., :2], q)
            z[..., 2] = h
        return u, mask


def known_obstacles(mapper: Mapper, extra=None) -> KnownObstacles:
    """:class:`KnownObstacles` from all scans given to ``mapper`` (plus ``extra = (poses,
    scans)`` not yet added)."""
    z, x = (np.concatenate(a) for a in (mapper.poses, mapper.obs))
    pts = observed_endpoints(z, x, mapper.beam_angles, mapper.max_range)
    if extra is not None and len(extra[0]):
        more = observed_endpoints(*extra, mapper.beam_angles, mapper.max_range)
        pts = np.concatenate([pts, more])
    return KnownObstacles(pts, mapper.cfg.plan.block_radius)


def controls_from_params(p: torch.Tensor, cfg: ExploreConfig) -> torch.Tensor:
    """Unconstrained ``[..., T-1]`` -> controls ``[..., T-1, 2]`` (first turn up to pi)."""
    lim = torch.full(p.shape[-1:], cfg.motion.max_turn, dtype=p.dtype)
    lim[0] = math.pi
    rot = lim * torch.tanh(p)
    return torch.stack([rot, torch.full_like(rot, cfg.motion.step_length)], -1)


def kinematic_rollout(z0: torch.Tensor, controls: torch.Tensor, sigma=0.0, generator=None):
    """Poses ``[..., T, 3]`` from ``z0 [3]`` under ``controls [..., T-1, 2]`` (rotate, move).

    Step ``t``: ``h = h_{t-1} + rot_t``, ``p_t = p_{t-1} + d_t (cos h, sin h)``, then
    ``z_t += sigma * eps_t``. Computed with cumulative sums (no loop over time), which is what
    makes candidate optimisation with hundreds of Adam steps affordable.
    """
    z0 = z0.expand(*controls.shape[:-2], 3)
    rot, d = controls[..., 0], controls[..., 1]  # [..., T-1]
    if sigma:
        eps = sigma * torch.randn((*rot.shape, 3), generator=generator, dtype=controls.dtype)
        eh = eps[..., 2].cumsum(-1)  # [..., T-1] heading noise up to and including step t
        h_move = z0[..., 2:3] + rot.cumsum(-1) + eh - eps[..., 2]  # heading of step t's move
        h = z0[..., 2:3] + rot.cumsum(-1) + eh
        dxy = eps[..., :2]  # [..., T-1, 2]
    else:
        h_move = h = z0[..., 2:3] + rot.cumsum(-1)
        dxy = 0.0
    step = torch.stack([d * torch.cos(h_move), d * torch.sin(h_move)], -1) + dxy
    xy = z0[..., None, :2] + step.cumsum(-2)  # [..., T-1, 2]
    return torch.cat([z0[..., None, :], torch.cat([xy, h.unsqueeze(-1)], -1)], -2)


def generate_candidates(mapper: Mapper, pose, cfg: ExploreConfig, generator=None):
    """Algorithm 2: ``F`` control sequences ``[F, T-1, 2]`` minimising the expected obstacle
    penalty along their predicted poses (+ turn regulariser, + leaving the map extent)."""
    F, T = cfg.candidates.count, cfg.plan.horizon
    logd, centres = obstacle_log_density(mapper)
    z0 = torch.as_tensor(pose, dtype=torch.get_default_dtype())
    p = cfg.candidates.init_std * torch.randn(F, T - 1, generator=generator)
    p[:, 0] = 3.0 * torch.rand(F, generator=generator) - 1.5  # spread the initial turn
    p.requires_grad_(True)
    opt = torch.optim.Adam([p], lr=cfg.candidates.lr)
    g = mapper.model.grid
    lo = torch.tensor(g.origin) + 0.01
    hi = lo + torch.tensor(g.size) - 0.02
    for _ in range(cfg.candidates.steps):
        u = controls_from_params(p, cfg)
        uu = u.unsqueeze(0).expand(cfg.candidates.pose_samples, -1, -1, -1)
        z = kinematic_rollout(z0, uu, cfg.motion.sigma_T, generator)  # [S, F, T, 3]
        xy = z[..., :2]
        pen = centres.attend(logd, xy.reshape(-1, 2)).reshape(xy.shape[:-1])  # [S, F, T]
        out = (torch.relu(lo - xy) + torch.relu(xy - hi)).pow(2).sum(-1) * 1e4
        turn = cfg.candidates.turn_reg * u[..., 1:, 0].pow(2).sum(-1)
        loss_f = (pen + out).mean(0).sum(-1) + turn
        opt.zero_grad()
        loss_f.sum().backward()
        opt.step()
    return controls_from_params(p.detach(), cfg)


# ----------------------------------------------------------------------------- agents


def exploration_ratio(positions, side: float, tiles: int) -> float:
    """Fraction of the ``tiles x tiles`` evaluation tiles containing a visited position."""
    ij = np.clip(np.floor(np.asarray(positions)[:, :2] / side * tiles).astype(int), 0, tiles - 1)
    return len({(int(a), int(b)) for a, b in ij}) / tiles**2


class _Episode:
    """One agent in one maze: the world, its mapper, the policy's state and the data of the
    current block of steps (see :func:`run_agent`)."""

    def __init__(self, scale_name: str, policy: str, cfg: ExploreConfig, maze_seed: int, pema):
        if policy not in ("mi", "random", "pema"):
            raise ValueError(f"unknown policy {policy!r}")
        self.policy, self.cfg, self.pema = policy, cfg, pema
        self.scale = SCALES[scale_name]
        self.world = World(make_maze(scale_name, maze_seed), seed=maze_seed + 1000 * cfg.seed)
        lid = self.world.lidar_config
        grid = scale_grid(self.scale, cfg.mapping.map_dim)
        own = replace(cfg, seed=cfg.seed + maze_seed)
        self.mapper = Mapper.new(grid, lid.beam_angles, lid.max_range, own)
        self.gen = torch.Generator().manual_seed(cfg.seed * 7919 + maze_seed)
        self.rng = np.random.default_rng(cfg.seed * 7919 + maze_seed)
        self.state = pema.initial_state() if policy == "pema" else None
        self.mis: list[float] = []
        self.poses, self.scans, self.flushed = [], [], 0
        self.ctl, self.k, self.replans = None, 0, 0

    def plan(self) -> np.ndarray:
        """The candidate plan of highest MI from the current pose: controls ``[H, 2]``."""
        pose, cfg = self.world.pose, self.cfg
        cands = generate_candidates(self.mapper, pose, cfg, self.gen)
        # MI of the belief-consistent rollout: moves into known obstacles do not move
        eff, _ = known_obstacles(self.mapper).effective_controls(pose, cands.numpy())
        eff = torch.as_tensor(eff, dtype=cands.dtype)
        vals = [mutual_information(self.mapper, c, pose, cfg) for c in eff]
        best = int(np.argmax(vals))
        self.mis.append(float(vals[best]))
        return cands[best].numpy()

    def flush(self) -> None:
        """Hand the block's data not yet given to the mapper over to it."""
        if len(self.poses) > self.flushed:
            self.mapper.add(
                np.array(self.poses[self.flushed :]), np.array(self.scans[self.flushed :])
            )
            self.flushed = len(self.poses)

    def _mi_control(self) -> np.ndarray:
        cfg = self.cfg
        u = self.ctl[self.k] if self.k < len(self.ctl) else np.array([0.0, cfg.motion.step_length])
        self.k += 1
        if cfg.plan.block_radius > 0 and self.replans < cfg.plan.max_replans:
            # the next planned move runs into an observed obstacle (the current scan included):
            # the rest of this open-loop plan is void, replan from here
            scan = self.scans[-1] if self.scans else self.world.lidar()
            beams, max_range = self.mapper.beam_angles, self.mapper.max_range
            pts = observed_endpoints(
                np.array([self.world.pose]), np.array([scan]), beams, max_range
            )
            _, b = KnownObstacles(pts, cfg.plan.block_radius).effective_controls(
                self.world.pose, u[None]
            )
            if b[0]:
                self.flush()
                self.ctl, self.k, self.replans = self.plan(), 1, self.replans + 1
                u = self.ctl[0]
        return u

    def control(self) -> np.ndarray:
        """The policy's next control ``[2]``."""
        if self.policy == "mi":
            return self._mi_control()
        if self.policy == "random":
            motion = self.cfg.motion
            turn = self.rng.uniform(-motion.max_turn, motion.max_turn)
            return np.array([turn, motion.step_length])
        scan_now = self.scans[-1] if self.scans else self.world.lidar()
        u, self.state = self.pema.act(scan_now, self.state)
        return u

    def block(self, n: int) -> list:
        """Execute ``n`` steps (MI: from a new plan); returns the poses reached."""
        if self.policy == "mi":
            self.ctl, self.k, self.replans = self.plan(), 0, 0
        self.poses, self.scans, self.flushed = [], [], 0
        for _ in range(n):
            u = self.control()
            hits = self.world.collisions
            self.world.step(u)
            self.poses.append(self.world.pose)
            self.scans.append(self.world.lidar())
            blocked = self.world.collisions > hits
            if self.policy == "mi" and blocked and self.replans < self.cfg.plan.max_replans:
                # blocked: the rest of this open-loop plan is void; replan from here with the
                # data so far (no SVI until the block ends)
                self.flush()
                self.ctl, self.k, self.replans = self.plan(), 0, self.replans + 1
        return self.poses


def run_agent(
    scale_name: str,
    policy: str,
    steps: int,
    cfg: ExploreConfig,
    maze_seed: int = 0,
    pema_policy=None,
    progress=False,
) -> dict:
    """Run one agent for ``steps`` steps in the maze ``make_maze(scale_name, maze_seed)``.

    ``policy``: ``"mi"`` (Algorithm 1), ``"random"`` (rotation ~ U(-max_turn, max_turn)) or
    ``"pema"`` (``pema_policy``, a :class:`~pyro_slam.planning.pema.PEMAPolicy` with its
    weights). Every block of ``cfg.plan.execute_steps`` steps (0: ``cfg.plan.horizon``, the
    whole plan, as in Algorithm 1; fewer is receding-horizon control): append the executed
    data, ``cfg.mapping.train_steps`` SVI steps, record infogain and exploration ratio. Returns
    curves and the true path. ``progress``: ``True`` prints each block, a tqdm bar is advanced
    by the executed steps.
    """
    ep = _Episode(scale_name, policy, cfg, maze_seed, pema_policy)
    world, mapper, scale = ep.world, ep.mapper, ep.scale
    path = [world.pose]
    mapper.add(world.pose[None], world.lidar()[None])
    ratio0 = exploration_ratio(np.array(path), scale.side, scale.tiles)
    curve = {"steps": [0], "infogain": [0.0], "ratio": [ratio0]}
    done = 0
    while done < steps:
        n = min(cfg.plan.execute_steps or cfg.plan.horizon, cfg.plan.horizon, steps - done)
        path += ep.block(n)
        done += n
        ep.flush()
        mapper.train(cfg.mapping.train_steps)
        curve["steps"].append(done)
        curve["infogain"].append(mapper.infogain())
        curve["ratio"].append(exploration_ratio(np.array(path), scale.side, scale.tiles))
        if hasattr(progress, "update"):  # a tqdm bar
            progress.update(n)
        elif progress:
            log.info("%s %s step %d: %.3f", policy, scale_name, done, curve["ratio"][-1])
    curve["mi"] = ep.mis
    curve["collisions"] = int(world.collisions)
    curve["path"] = np.array(path).tolist()
    return curve
