"""The DVBF-LM generative model (Mirchev et al. 2019, section III-B) as a Pyro model.

    M        ~ N(0, 1)                                  map, [w, h, D_m]  (pyro.plate x 2)
    z_0      ~ N(z_init, sigma_0)                       initial pose, [3]
    m_t      = f_m(z_t, M)                              chart: bilinear attention (4 cells)
    x_t      ~ (1 - eps) N(mu_E(m_t, z_t), sigma_E)     emission, [N] (flattened observation),
               + eps U(0, R)                            with the beam model's outlier component
    z_{t+1}  ~ N(mu_T(z_t, u_t, mu_E(m_t)), sigma_T)     transition, [3]

and, with a heading factor (:class:`WallHeading`, not the paper's), the walls' frame and each
scan's wall direction:

    phi      ~ U(circle of circumference pi / 2)        the walls' frame (global)
    h_t      ~ (1 - eps_h) N(wrap(phi - theta_t), s_t)  the wall direction seen in x_t (observed
               + eps_h U(0, pi / 2)                     where the scan shows straight walls)

:class:`DVBFLM` holds the networks and exposes each factor as a plain function of tensors
(:meth:`chart`, :meth:`emission_mean`, :meth:`emission_log_prob`, :meth:`transition_dist`,
:meth:`heading_dist`) so that the Pyro model (:meth:`DVBFLM.model`), the SMCFilter model
(:class:`FilterModel`) and the fast differentiable particle filter (:mod:`pyro_slam.inference`)
all evaluate the *same* factors. Under a map belief ``q(M)`` instead of a map, the filter weighs
with :meth:`DVBFLM.marginal_emission`, a stated approximation of the emission marginalised over
``q(M)``.

The sensor enters only through the :class:`~pyro_slam.model.emissions.Emission` (``mu_E`` as a
function of chart and pose, with the observation flattened to ``[..., N]``): a
:class:`~pyro_slam.model.emissions.LidarEmission` (range profile rotated to the beams) or an
:class:`~pyro_slam.model.emissions.ImageEmission` (chart rotated and cropped to the camera's
view, then row-wise MLPs). Model, guide, filter and ELBO are the same for both.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import pyro
import pyro.distributions as dist
import torch
import torch.nn.functional as F
from pyro.poutine.messenger import Messenger

from ..geometry import interleave
from .emissions import Emission, LidarEmission
from .factors import Factors, _Memo
from .networks import EmissionMLP
from .noise import CircularUniform
from .transitions import Transition


@dataclass
class MapBelief:
    """A Gaussian map belief, ``loc`` and ``scale`` ``[w, h, D]`` (e.g. a mean-field ``q(M)``),
    with ``variance``, ``scale ** 2``, where its holder keeps it between reads (else None)."""

    loc: torch.Tensor
    scale: torch.Tensor
    variance: torch.Tensor | None = None


@dataclass(frozen=True)
class WallHeading:
    """The heading factor of a Manhattan world (not the paper's): each scan's straight walls
    show their direction ``h_t`` in the body frame, which is the walls' frame ``phi`` minus the
    heading, modulo ``period`` (a quarter turn), up to noise of a per-scan std (the data's,
    :class:`HeadingEvidence`); with probability ``outlier_prob`` a direction is an outlier
    uniform over the period (clutter taken for a wall)."""

    period: float = math.pi / 2
    outlier_prob: float = 0.0


@dataclass(eq=False)
class HeadingEvidence:
    """The wall directions seen in the scans: ``direction [...]`` (rad in ``[0, period)``, nan
    where a scan shows no straight wall), their std ``sigma [...]`` (or a number), and the walls'
    frame: a value (a sample of ``phi``) or the mean ``frame`` and variance ``frame_var`` of its
    belief (the filter then weighs with the evidence marginalised over it, exact for the
    Gaussian component)."""

    direction: torch.Tensor
    sigma: torch.Tensor | float
    frame: float | torch.Tensor = math.nan
    frame_var: float = 0.0

    def at(self, t) -> HeadingEvidence:
        """The evidence of step(s) ``t`` from one that holds a sequence ``direction [T]``."""
        sigma = self.sigma[t] if torch.is_tensor(self.sigma) and self.sigma.dim() else self.sigma
        return HeadingEvidence(self.direction[t], sigma, self.frame, self.frame_var)

    def per_particle(self) -> HeadingEvidence:
        """The evidence with a particle dimension added to its tensors (``[..., 1]``), so that
        it broadcasts against a particle batch ``[..., K]``."""

        def unsq(v):
            return v.unsqueeze(-1) if torch.is_tensor(v) and v.dim() else v

        return HeadingEvidence(
            unsq(self.direction), unsq(self.sigma), unsq(self.frame), unsq(self.frame_var)
        )

    def seen(self) -> torch.Tensor:
        """``[...]`` bool: a direction is observed (and a frame known)."""
        known = ~torch.isnan(torch.as_tensor(self.frame, dtype=self.direction.dtype))
        return ~torch.isnan(self.direction) & known

    def std(self) -> torch.Tensor:
        """``[...]``: the scan's std with the frame's variance added."""
        s = torch.as_tensor(self.sigma, dtype=self.direction.dtype)
        return (s**2 + self.frame_var).sqrt()


@dataclass(frozen=True)
class MapGrid:
    """Geometry of the map grid: ``cells = (w, h)`` grid points spanning ``origin + [0, size]``.

    Cell ``(i, j)`` sits at ``origin + (i * size_x / (w - 1), j * size_y / (h - 1))``; poses
    outside the extent read the border cells.
    """

    cells: tuple[int, int] = (32, 32)
    dim: int = 10
    origin: tuple[float, float] = (0.0, 0.0)
    size: tuple[float, float] = (1.0, 1.0)

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.cells[0], self.cells[1], self.dim)

    def extent(self) -> tuple[float, float, float, float]:
        """``(x0, x1, y0, y1)`` spanned by the grid points (for ``imshow``)."""
        (x0, y0), (sx, sy) = self.origin, self.size
        return (x0, x0 + sx, y0, y0 + sy)

    @classmethod
    def covering(cls, xmin, ymin, xmax, ymax, resolution: float, dim: int, margin: float = 0.0):
        """A grid over a bounding box with a given cell spacing (metric maps of real logs)."""
        x0, y0 = xmin - margin, ymin - margin
        sx, sy = xmax - xmin + 2 * margin, ymax - ymin + 2 * margin
        w = max(2, int(round(sx / resolution)) + 1)
        h = max(2, int(round(sy / resolution)) + 1)
        return cls((w, h), dim, (float(x0), float(y0)), (float(sx), float(sy)))

    def attend(self, M: torch.Tensor, xy: torch.Tensor, power: int = 1) -> torch.Tensor:
        """Bilinear attention ``f_m``: charts at positions ``xy``.

        Args:
            M: map ``[w, h, D]`` or ``[S, w, h, D]`` (``S`` map samples).
            xy: positions ``[..., 2]``; with a batched map, ``xy`` is ``[S, ..., 2]``.
            power: raise the four interpolation weights to this power (``power=2`` on the map
                variances gives the variance of the chart under a mean-field ``q(M)``).
        Returns:
            charts ``[..., D]`` (``[S, ..., D]`` with a batched map).
        """
        if power == 1:
            return self.read(M, xy[..., 0], xy[..., 1])
        w, h = self.cells
        D = M.shape[-1]
        a, b, base = self._corner(xy)
        wa = (1 - a) ** power, a**power
        wb = (1 - b) ** power, b**power
        if M.dim() == 3:
            flat = M.reshape(w * h, D)

            def cell(offset):
                return flat[base + offset]
        else:
            S = M.shape[0]
            flat = M.reshape(S, w * h, D)
            idx = base.reshape(S, -1)

            def cell(offset):
                out = torch.gather(flat, 1, (idx + offset).unsqueeze(-1).expand(-1, -1, D))
                return out.reshape(*base.shape, D)

        return (
            wa[0] * wb[0] * cell(0)
            + wa[1] * wb[0] * cell(h)
            + wa[0] * wb[1] * cell(1)
            + wa[1] * wb[1] * cell(h + 1)
        )

    def _corner(self, xy: torch.Tensor):
        """The interpolation fractions ``a, b [..., 1]`` and the flat index ``[...]`` of the
        lower-left grid point of each position (clamped to the grid)."""
        w, h = self.cells
        gx = ((xy[..., 0] - self.origin[0]) * ((w - 1) / self.size[0])).clamp(0, w - 1)
        gy = ((xy[..., 1] - self.origin[1]) * ((h - 1) / self.size[1])).clamp(0, h - 1)
        i0 = gx.detach().floor().clamp(max=w - 2)
        j0 = gy.detach().floor().clamp(max=h - 2)
        base = i0.long() * h + j0.long()
        return (gx - i0).unsqueeze(-1), (gy - j0).unsqueeze(-1), base

    def read(self, M: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """:meth:`attend` at positions given by their coordinates ``x, y [...]`` (the same read
        without interleaving them into ``[..., 2]``): ``[..., D]``."""
        w, h = self.cells
        gx = (x - self.origin[0]).mul_((w - 1) / self.size[0])
        gy = (y - self.origin[1]).mul_((h - 1) / self.size[1])
        return self._sample(M, gx, gy)

    def _sample(self, M: torch.Tensor, gx: torch.Tensor, gy: torch.Tensor) -> torch.Tensor:
        """Bilinear interpolation of ``M`` at grid coordinates ``gx, gy [...]`` (clamped to the
        grid; both overwritten) through ``grid_sample``: the four-cell sum in one fused kernel."""
        w, h = self.cells
        D = M.shape[-1]
        image = M.permute(0, 3, 2, 1) if M.dim() == 4 else M.permute(2, 1, 0)[None]  # [N, D, h, w]
        grid = interleave(gx.mul_(2 / (w - 1)).sub_(1), gy.mul_(2 / (h - 1)).sub_(1), M.dtype)
        grid = grid.reshape(image.shape[0], 1, -1, 2)
        out = F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=True)
        return out[:, :, 0].transpose(1, 2).reshape(*gx.shape, D)  # [..., D]

    def relative_variance(self, scale: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
        """Variance of the chart at ``xy [..., 2]`` under a mean-field ``q(M)`` with std
        ``scale [w, h, D]``, relative to the prior's (``scale = 1``) and averaged over the ``D``
        features: ``[..., 1]`` in ``[0, 1]``, i.e. ``sum a_i^2 s_i^2 / sum a_i^2`` over the
        four attended cells (bilinear weights ``a_i``). The squared weights are separable and,
        normalised, bilinear weights again at the fractions ``a^2 / ((1 - a)^2 + a^2)``, so this
        is one bilinear read of ``s^2`` at shifted positions."""
        return self.read_variance(scale, xy[..., 0], xy[..., 1])

    def read_variance(self, scale: torch.Tensor, x: torch.Tensor, y: torch.Tensor, squared=False):
        """:meth:`relative_variance` at positions given by their coordinates ``x, y [...]``
        (``squared``: ``scale`` holds the variances ``s^2``, for repeated reads of one map)."""
        w, h = self.cells
        gx = self._shifted(x, self.origin[0], (w - 1) / self.size[0], w)
        gy = self._shifted(y, self.origin[1], (h - 1) / self.size[1], h)
        return self._sample(scale if squared else scale**2, gx, gy).mean(-1, keepdim=True)

    @staticmethod
    def _shifted(x: torch.Tensor, origin: float, per_unit: float, n: int) -> torch.Tensor:
        """One axis of :meth:`read_variance`'s read: the grid coordinate ``[...]`` of positions
        ``x [...]`` with its fraction ``a`` replaced by ``a^2 / ((1 - a)^2 + a^2)`` (in place
        on fresh buffers: this runs on every march point of every particle)."""
        g = (x - origin).mul_(per_unit).clamp_(0, n - 1)
        corner = g.floor().clamp_(max=n - 2)
        a = g.sub_(corner)
        a2 = a * a
        rest = torch.rsub(a, 1)
        return corner.add_(a2.div_((rest * rest).add_(a2)))


class DVBFLM(Factors):
    """DVBF-LM.

    Args:
        grid: map geometry (:class:`MapGrid`); ``grid.dim`` must be the emission's ``map_dim``.
        emission: ``mu_E``, an :class:`~pyro_slam.model.emissions.Emission`; a bare
            :class:`~pyro_slam.model.emissions.EmissionMLP` is wrapped as a LiDAR emission with
            ``beam_angles``.
        transition: a :class:`~pyro_slam.transitions.Transition`.
        beam_angles: ``[B]`` beam directions relative to the heading (bare ``EmissionMLP`` only).
        sigma_emission: ``sigma_E`` (paper: 0.1 for training).
        init_scale: std of the initial-pose prior around the given start pose, ``[3]``.
        prior: the map prior ``p(M)``: a Pyro distribution over a cell's features (event
            ``[D_m]``, batch shape broadcastable to the grid ``[w, h]``) that exposes its
            marginal ``variance`` (the map belief's variance relative to it is how unknown a
            reading is, :meth:`marginal_emission`); default
            ``N(0, 1)``.
        noise: the emission noise, a callable ``noise(loc, scale)`` returning a distribution
            over each observation entry (batch shape that of ``loc``), e.g.
            ``pyro.distributions.StudentT`` partially applied; default ``Normal``.
        outlier_prob: ``eps``, the beam model's outlier probability per entry: the emission is
            :class:`~pyro_slam.model.noise.BeamMixture` of the noise and a uniform density over
            ``outlier_range`` (the sensor's range).
        heading: the heading factor (:class:`WallHeading`), or None.
        learn_emission, learn_transition: whether the model hands the emission's and the
            transition's networks to Pyro (``pyro.module``), so that SVI on :meth:`model`
            trains them; a network that is not learned is frozen (no gradient). Default: the
            emission is learned (a new network is the paper's), a (shipped) transition is not.
        handler: Pyro handlers applied to :meth:`model` wherever this library runs it (the
            filter's weights, scan insertion, SLAM's SVI, the planner's rollouts, MI): a
            function ``fn -> handled fn`` such as ``lambda fn: poutine.condition(fn, data)``,
            or a messenger such as ``poutine.scale(scale=0.5)`` (:meth:`handled`).

    Every factor is a Pyro distribution (:meth:`map_prior`, :meth:`emission_dist`,
    :meth:`transition_dist`; :class:`~pyro_slam.model.factors.Factors`), and everything that
    evaluates the model -- the Pyro model, the particle filter's proposals and weights, the
    training objective, map fitting, planning rollouts and MI -- reads these, so a swapped prior
    or noise model reaches all of them.
    """

    def __init__(
        self,
        grid: MapGrid,
        emission: Emission | EmissionMLP,
        transition: Transition,
        beam_angles=None,
        sigma_emission: float = 0.1,
        init_scale=(1e-3, 1e-3, 1e-3),
        prior: dist.Distribution | None = None,
        noise=None,
        outlier_prob: float = 0.0,
        outlier_range: float = 1.0,
        heading: WallHeading | None = None,
        learn_emission: bool = True,
        learn_transition: bool = False,
        handler=None,
    ):
        super().__init__()
        if not isinstance(emission, Emission):
            if beam_angles is None:
                raise ValueError("a bare emission network needs beam_angles (LiDAR read-out)")
            emission = LidarEmission(emission, beam_angles)
        if emission.map_dim != grid.dim:
            raise ValueError(f"emission expects D_m = {emission.map_dim}, map has {grid.dim}")
        if emission.reads_observation and getattr(transition, "needs_scan", False):
            raise ValueError(
                f"{type(emission).__name__}'s mean depends on the observed reading, so it is no "
                f"predicted scan for {type(transition).__name__}, which reads one"
            )
        self.grid = grid
        self.emission = emission
        self.transition = transition
        self.sigma_emission = float(sigma_emission)
        self.register_buffer(
            "init_scale", torch.as_tensor(init_scale, dtype=torch.get_default_dtype())
        )
        self.noise = dist.Normal if noise is None else noise
        self.prior = prior
        if not 0.0 <= outlier_prob < 1.0:
            raise ValueError(f"outlier_prob must be in [0, 1), got {outlier_prob!r}")
        if not outlier_range > 0:
            raise ValueError(f"outlier_range must be positive, got {outlier_range!r}")
        self.outlier_prob, self.outlier_range = float(outlier_prob), float(outlier_range)
        self.heading = heading
        self.learn_emission, self.learn_transition = bool(learn_emission), bool(learn_transition)
        self.handler = handler
        self._memo = _Memo()  # the last transition distribution (:meth:`transition_dist`)

    # ------------------------------------------------------------------------ Pyro model
    heading_scale = 1e-3  # std of sampled wall directions (rad), where none are observed

    @property
    def learn_emission(self) -> bool:
        """Whether :meth:`model` hands the emission's network to Pyro (SVI trains it); a
        network that is not learned is frozen."""
        return self._learn_emission

    @learn_emission.setter
    def learn_emission(self, value: bool) -> None:
        self._learn_emission = bool(value)
        self.emission.requires_grad_(self._learn_emission)

    @property
    def learn_transition(self) -> bool:
        """Whether :meth:`model` hands the transition's network to Pyro; frozen otherwise."""
        return self._learn_transition

    @learn_transition.setter
    def learn_transition(self, value: bool) -> None:
        self._learn_transition = bool(value)
        self.transition.requires_grad_(self._learn_transition)

    def handled(self):
        """:meth:`model` under the model's ``handler`` (itself without one): what the filter,
        scan insertion, SLAM's SVI, the planner and MI run."""
        return self.model if self.handler is None else self.handler(self.model)

    def _register_networks(self) -> None:
        """``pyro.module`` for the networks the model learns (:attr:`learn_emission`,
        :attr:`learn_transition`), and nothing else: a frozen network is not a parameter."""
        if self.learn_emission and any(True for _ in self.emission.parameters()):
            pyro.module("emission", self.emission)
        if self.learn_transition and any(True for _ in self.transition.parameters()):
            pyro.module("transition", self.transition)

    def sample_map(self) -> torch.Tensor:
        """The global map site ``"map"`` under its two plates; returns ``M [w, h, D_m]``."""
        w, h, _ = self.grid.shape
        with pyro.plate("map_x", w, dim=-2), pyro.plate("map_y", h, dim=-1):
            return pyro.sample("map", self.map_prior())

    def sample_frame(self):
        """The global site ``"frame"``, the walls' frame ``phi`` (with a heading factor; None
        otherwise): uniform on the circle of circumference ``period``."""
        if self.heading is None:
            return None
        return pyro.sample("frame", CircularUniform(self.heading.period))

    def mapping_model(self, poses, observations, mask=None, batch_size=None):
        """The model of scans taken at known poses (mapping): the map, then each scan
        ``observations [T, N]`` at ``poses [T, 3]`` (``mask [T, N]``) under the emission, in a
        plate ``"data"`` that subsamples ``batch_size`` of them per call. The ``model`` of
        :func:`~pyro_slam.slam.fit_map`."""
        self._register_networks()
        M = self.sample_map()
        T = poses.shape[0]
        with pyro.plate("data", T, subsample_size=min(batch_size or T, T)) as i:
            mean = self.emission_mean(M, poses[i], observations[i])
            mask_i = None if mask is None else mask[i]
            pyro.sample("x", self.emission_dist(mean, mask_i), obs=observations[i])

    def model(self, observations, controls, init_pose, mask=None, headings=None, window=None):
        """The full generative model of one traversal.

        Args:
            observations: ``[T, N]`` flattened observations (or None to sample them).
            controls: ``[..., T-1, D_u]`` (a batch of control sequences, e.g. planned motion
                primitives, broadcasts against the poses).
            init_pose: ``[3]`` start pose (the map frame is anchored at it), or ``[..., 3]``.
            mask: optional ``[T, B]`` bool, False = missing reading.
            headings: the wall directions ``direction [T]`` and their std of a
                :class:`HeadingEvidence` (its frame is ignored: the model samples ``phi``);
                None: with a heading factor, the directions are sampled.
            window: None for the whole traversal; a :class:`Window` runs a part of it (the
                global sites alone, or one step vectorised over particles, with the step's
                data from the window): what the filter and SLAM's objective trace.
        Returns:
            poses ``[..., T, 3]`` (a window: see :class:`Window`). Sites: ``map``,
            (``frame``,) ``z_t``, ``x_t``, (``h_t``,) and the predicted observation ``scan_t``
            (deterministic, ``mu_E``) of every step.
        """
        self._register_networks()
        if window is not None:
            return window.run(self)
        T = controls.shape[-2] + 1
        M, frame = self.sample_map(), self.sample_frame()
        poses = []
        prev = None
        for t in pyro.markov(range(T)):
            u = None if t == 0 else controls[..., t - 1, :]
            x = None if observations is None else observations[t]
            m = None if mask is None else mask[t]
            h = None if headings is None else headings.at(t)
            prev = self.step(t, M, frame, prev, u, x, m, h, init=init_pose)
            poses.append(prev[0])
        return torch.stack(torch.broadcast_tensors(*poses), -2)

    def step(self, t: int, M, frame, prev, u, x, mask=None, evidence=None, **how):
        """The sites of step ``t`` (:meth:`model`'s loop body), given the previous step's
        ``prev = (z, scan)`` (poses ``[..., 3]`` and their predicted scans) or None:

        * ``z_t`` from the transition at ``prev`` under the control ``u``; without ``prev``,
          from the initial-pose prior about ``how["init"]``, or, with ``how["given"]``, the
          poses of step ``t`` themselves (no site: a chunk's start particles);
        * ``scan_t`` (deterministic), the predicted observation at ``z_t``;
        * ``x_t``, observed at ``x`` (None: sampled) with ``mask``, under the map ``M`` (a
          :class:`MapBelief`: the emission marginalised over it);
        * with a heading factor, ``h_t``, the wall direction of ``evidence`` (a
          :class:`HeadingEvidence`; None: sampled) in the frame ``frame`` (a
          :class:`FrameBelief`: marginalised over it).

        ``how["window"]``: run in a :class:`Window` (the emission's mean read once, given the
        observation; ``how["dtype"]``: its reduced precision without gradients). Returns
        ``(z_t, scan_t)``."""
        if prev is not None:
            z = pyro.sample(f"z_{t}", self.transition_dist(prev[0], u, prev[1], validate=False))
        elif how.get("given") is not None:
            z = how["given"]
        else:
            z = pyro.sample(f"z_{t}", dist.Normal(how["init"], self.init_scale).to_event(1))
        scan, mean, eps = self._read(M, z, x, how.get("window", False), how.get("dtype"))
        pyro.deterministic(f"scan_{t}", scan, event_dim=1)
        pyro.sample(f"x_{t}", self.emission_dist(mean, mask, outlier_prob=eps), obs=x)
        if frame is not None:
            self._observe_heading(t, z, frame, evidence)
        return z, scan

    def _read(self, M, z, x, window: bool, dtype=None):
        """``(scan, mean, outlier_prob)`` at poses ``z``: the predicted scan, the mean the
        observation ``x`` is scored with (given ``x`` where the emission reads it) and the
        outlier probability (None: the model's). Under a :class:`MapBelief`, the marginalised
        emission (:meth:`marginal_emission`); in a window, one read given ``x`` serves as
        both."""
        if isinstance(M, MapBelief):
            mean, eps = self.marginal_emission(M, z, x)
            return mean, mean, eps
        if not window:
            scan = self.emission_mean(M, z)
            return scan, self._observed_mean(M, z, scan, x), None
        if dtype is not None and not torch.is_grad_enabled():
            with torch.autocast(z.device.type, dtype=dtype):
                mean = self.emission_mean(M, z, x).to(z.dtype)
        else:
            mean = self.emission_mean(M, z, x)
        return mean, mean, None

    def _observe_heading(self, t: int, z, frame, evidence: HeadingEvidence | None) -> None:
        """The site ``h_t``: observed where step ``t``'s scan shows a wall direction (in a
        known frame), with the scan's std and the frame belief's variance."""
        loc, var = (frame.mean, frame.var) if isinstance(frame, FrameBelief) else (frame, 0.0)
        if evidence is None:
            pyro.sample(f"h_{t}", self.heading_dist(z[..., 2], loc, self.heading_scale))
            return
        e = HeadingEvidence(evidence.direction, evidence.sigma, loc, var)
        frame = torch.as_tensor(loc, dtype=z.dtype).nan_to_num()  # (unknown: unseen)
        d = self.heading_dist(z[..., 2], frame, e.std().to(z.dtype)).mask(e.seen())
        pyro.sample(f"h_{t}", d, obs=e.direction.nan_to_num())


@dataclass(frozen=True, eq=False)
class FrameBelief:
    """A Gaussian belief ``N(mean, var)`` of the walls' frame ``phi``: the value the site
    ``"frame"`` takes in a filter's :class:`Window` (the heading factor is then marginalised
    over it, exact for its Gaussian component); ``mean`` nan: no frame known (no wall direction
    is used)."""

    mean: float | torch.Tensor = math.nan
    var: float | torch.Tensor = 0.0


class _Defaults(Messenger):
    """Gives the named sample sites a value unless a handler outside sets another (it runs
    first: a ``poutine.condition`` or ``poutine.replay`` around the model still sets theirs)."""

    def __init__(self, values: dict):
        super().__init__()
        self.values = {k: v for k, v in values.items() if v is not None}

    def _pyro_sample(self, msg) -> None:
        if msg["name"] in self.values and msg["value"] is None:
            msg["value"] = self.values[msg["name"]]
            msg["done"] = True


@dataclass(eq=False)
class Window:
    """A part of :meth:`DVBFLM.model` that the filter and SLAM's objective trace, in the way
    :class:`pyro.infer.SMCFilter` traces a model's ``step`` (the model's own sites, under
    whatever handlers wrap :meth:`DVBFLM.model`).

    Without a ``step``: the global sites alone, ``"map"`` taking the value ``map`` and
    ``"frame"`` the value ``frame`` unless a handler sets them (a :class:`MapBelief` and a
    :class:`FrameBelief`: the beliefs a filter marginalises over); returns ``(M, frame)``.

    With a ``step`` ``t``: that step's sites (:meth:`DVBFLM.step`) under the resolved globals
    ``map`` and ``frame``, vectorised over particles ``[..., K]`` in the plates
    ``"particles"`` (dim -1) and ``"chunks"`` (dim -2) (``plates=False``: an enclosing plate
    holds them, SMCFilter's): ``z_t`` from the transition at ``poses [..., K, 3]`` (the
    previous step's, with their predicted ``scans [..., K, B]``); with ``given``, ``poses`` are
    step ``t``'s own (no site ``z_t``: start particles weighed by their observation alone);
    without ``poses``, ``z_t`` from the initial-pose prior about ``init [3]`` over a batch of
    ``particles`` (a shape). The step's data broadcast against the particles: the control
    ``u [..., 1, D_u]``, the observation ``x [..., 1, N]`` and ``mask``, the wall directions
    ``heading`` (:meth:`HeadingEvidence.per_particle`; None: no site ``h_t``). ``dtype``: the
    emission's reduced precision where no gradient is needed. Returns ``(z_t, scan_t)``.

    A batch of chunks (``[C, K]``) holds different time steps; their sites are named after the
    first chunk's step."""

    step: int | None = None
    map: object = None
    frame: object = None
    poses: torch.Tensor | None = None
    scans: torch.Tensor | None = None
    given: bool = False
    init: torch.Tensor | None = None
    particles: tuple = ()
    u: torch.Tensor | None = None
    x: torch.Tensor | None = None
    mask: torch.Tensor | None = None
    heading: HeadingEvidence | None = None
    plates: bool = True
    dtype: torch.dtype | None = None

    def run(self, model: DVBFLM):
        if self.step is None:
            with _Defaults({"map": self.map, "frame": self.frame}):
                return model.sample_map(), model.sample_frame()
        prev = None if self.poses is None or self.given else (self.poses, self.scans)
        frame = None if self.heading is None else self.frame
        with self._plates():
            return model.step(
                self.step,
                self.map,
                frame,
                prev,
                self.u,
                self.x,
                self.mask,
                self.heading,
                init=self.init,
                given=self.poses if self.given else None,
                window=True,
                dtype=self.dtype,
            )

    def _plates(self):
        """The particle plates of the batch ``[..., K]`` (at most two dims)."""
        shape = self.poses.shape[:-1] if self.poses is not None else tuple(self.particles)
        stack = contextlib.ExitStack()
        if not self.plates:
            return stack
        if len(shape) > 2:
            raise ValueError(f"a window's particles are [K] or [C, K], got {tuple(shape)}")
        for name, size, d in zip(("particles", "chunks"), reversed(shape), (-1, -2)):
            stack.enter_context(pyro.plate(name, size, dim=d))
        return stack


class FilterModel:
    """The model's one-step :class:`Window`\\ s as the model object of
    :class:`pyro.infer.SMCFilter` (``init``/``step``; SMCFilter's particle plate holds the
    particles): each step runs :meth:`DVBFLM.model` under the model's handlers
    (:meth:`DVBFLM.handled`) with the global values ``M`` (a map ``[w, h, D_m]``, e.g. a sample
    of ``q(M)``, or a :class:`MapBelief`) and ``frame`` (a number or a :class:`FrameBelief`;
    None: from each step's :class:`HeadingEvidence`). ``state["z"]`` holds the poses and
    ``state["scan"]`` their predicted scans (the transition's input at the next step); the
    sites are the model's own, ``z_t``, ``scan_t``, ``x_t`` and ``h_t``."""

    def __init__(self, dvbflm: DVBFLM, M, frame=None):
        self.m, self.M, self.frame = dvbflm, M, frame

    def _run(self, state, window: Window) -> None:
        if window.frame is None and window.heading is not None:
            h = window.heading
            window.frame = FrameBelief(h.frame, h.frame_var)
        z, scan = self.m.handled()(None, None, None, window=window)
        state["z"], state["scan"] = z, scan

    def init(self, state, init_pose, x=None, mask=None, heading=None):
        self._run(state, self._window(0, x, None, mask, heading, init=init_pose))

    def step(self, state, t, x, u, mask=None, heading=None):
        w = self._window(t, x, u, mask, heading, poses=state["z"], scans=state["scan"])
        self._run(state, w)

    def _window(self, t, x, u, mask, heading, **kw) -> Window:
        return Window(
            t, self.M, self.frame, u=u, x=x, mask=mask, heading=heading, plates=False, **kw
        )
