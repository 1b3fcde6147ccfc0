"""Planning environments: the learned DVBF-LM model (:class:`LearnedEnv`, built by
:func:`learned_env`) and the simulator's truth (:class:`GroundTruthEnv`), with one interface
(``scan``, ``rollout``, ``valid``, ``bounds``), and :func:`execute`, which runs a plan in the
simulator."""

from __future__ import annotations

import copy
import hashlib
from dataclasses import replace

import numpy as np
import pyro
import torch
from pyro import poutine
from scipy.optimize import minimize
from scipy.spatial import cKDTree

from simulators import LidarConfig, World, raycast, simulate_traversal
from simulators.world import point_segment_distance

from ..model import EmissionMLP, KinematicTransition
from ..model.networks import LIDAR_MAP_DIM
from ..pretrained import EMISSION_FILE, PRETRAINED, load_emission, transition_for
from ..slam import (
    SLAMConfig,
    build_model,
    fit_map,
    fit_noise,
    prepare_traversal,
    pretrain_emission,
)
from ..slam.components import emission_kind
from ..slam.presets import NAVIGATION_MAPPING
from .config import NAVIGATION
from .planner import SAFETY_DELTA, inside_scan


# --------------------------------------------------------------------------- environments
class _Rollouts:
    """Memoised rollouts, shared by both environments. A rollout is a deterministic function of
    its start pose, so :meth:`rollout` keeps each start pose's result per set of controls (up
    to ``memo_limit`` of them, the oldest dropped first): plans from one start, or through one
    pose, share them, and so do copies made by ``with_observation``. ``rollout_batch`` start
    poses cost about as much as one (the planner rolls out its next open nodes with it)."""

    rollout_batch = 1
    memo_limit = 20_000

    def rollout(self, z0, controls: torch.Tensor):
        """Roll out ``controls [P, L, 2]`` from a pose ``z0 [3]`` or from poses ``[K, 3]``.

        Returns final poses ``[(K,) P, 3]``, travel ``[(K,) P]``, end scans ``[(K,) P, B]``
        (a tensor) and step paths ``[(K,) P, L + 1, 3]``."""
        z = np.asarray(z0, dtype=np.float64)
        single = z.ndim == 1
        z = np.atleast_2d(z)  # [K, 3]
        memo = self._memos.setdefault(controls.numpy().tobytes(), {})
        keys = [row.tobytes() for row in z]
        new = list(dict.fromkeys(k for k in keys if k not in memo))
        if new:
            out = self._rollout(z[[keys.index(k) for k in new]], controls)
            for j, k in enumerate(new):
                memo[k] = tuple(v[j] for v in out)
            for old in list(memo)[: max(0, len(memo) - self.memo_limit)]:
                del memo[old]
        rows = [memo[k] for k in keys]
        if single:
            return rows[0]
        return tuple(torch.stack(v) if torch.is_tensor(v[0]) else np.stack(v) for v in zip(*rows))


class LearnedEnv(_Rollouts):
    """The DVBF-LM model with a fixed map ``M`` (mean of ``q(M)``) as planning environment.

    Args:
        model: a :class:`~pyro_slam.model.DVBFLM`: the planner's rollouts sample it, under its
            handlers (:meth:`~pyro_slam.model.DVBFLM.handled`), with its transition and its
            emission, each with its noise (a mapping model's transition stops short of the walls
            its predicted scans show, ``NavigationConfig.clip_margin``).
        M: map ``[w, h, D_m]``.
        bounds: ``(x0, x1, y0, y1)`` poses must stay within (default: the map extent).
        scale: ``q(M)``'s std ``[w, h, D_m]`` (explored space, :meth:`valid`).
        samples: rollouts drawn per start pose and primitive (:meth:`rollout`).
    """

    name = "learned"
    rollout_batch = 16  # one model run for 16 start poses costs ~2 x one for a single pose

    def __init__(
        self,
        model,
        M: torch.Tensor,
        bounds=None,
        scale: torch.Tensor | None = None,
        max_std: float = 0.6,
        hits: np.ndarray | None = None,
        hit_margin: float = 0.0,
        samples: int = NAVIGATION.rollout_samples,
    ):
        self.model, self.M, self.scale, self.max_std = model, M, scale, max_std
        # the mapping scans' returns (ScanHits) and the clearance a position keeps from them
        self.hits, self.hit_margin = hits, hit_margin
        if not (isinstance(samples, int) and samples >= 1):
            raise ValueError(f"samples must be a positive integer, got {samples!r}")
        self.samples = samples
        self.bounds = bounds if bounds is not None else model.grid.extent()
        self.seen: list[tuple] = []  # (pose [3], real scan [B], margin, radius)
        self._memos: dict = {}  # rollouts per controls and start pose (see _Rollouts)

    def with_observation(
        self, pose, scan, margin: float = SAFETY_DELTA, radius: float = 0.1
    ) -> LearnedEnv:
        """A copy that also trusts the free space of a *real* scan ``[B]`` taken at ``pose
        [3]`` (e.g. the agent's own LiDAR at the start): positions at least ``margin`` inside
        it and within ``radius`` of the pose (:func:`inside_scan`) count as valid even where
        the map is unexplored."""
        out = copy.copy(self)
        seen = (np.asarray(pose, float), np.asarray(scan, float), margin, radius)
        out.seen = [*self.seen, seen]
        return out

    @torch.no_grad()
    def scan(self, z: torch.Tensor) -> torch.Tensor:
        return self.model.emission_mean(self.M, z)

    @torch.no_grad()
    def std(self, xy) -> np.ndarray:
        """Mean std of the chart ``m = f_m(z, M)`` under ``q(M)`` at positions ``[N, 2]``,
        relative to the map prior's (1: nothing known there)."""
        xy = torch.as_tensor(np.asarray(xy)[..., :2], dtype=self.M.dtype)
        rel = self.scale / self.model.prior_std()
        var = self.model.grid.attend(rel**2, xy, power=2)
        return var.mean(-1).sqrt().numpy()

    def valid(self, z) -> np.ndarray:
        """Explored positions: chart std under ``q(M)`` below ``max_std`` of the prior's (the
        model's predicted scans are extrapolations elsewhere) and, with ``hits``, at least
        ``hit_margin`` from every return of the mapping scans; or inside the free space of a
        real scan (:meth:`with_observation`)."""
        if self.scale is None:
            return np.ones(len(z), dtype=bool)
        ok = self.std(z) < self.max_std
        if self.hits is not None and self.hit_margin > 0:
            ok &= self.hits.clearance(np.asarray(z)[:, :2], self.hit_margin) >= self.hit_margin
        for pose, scan, margin, radius in self.seen:
            ok |= inside_scan(np.asarray(z)[:, :2], pose, scan, margin, radius)
        return ok

    @torch.no_grad()
    def _rollout(self, z0: np.ndarray, controls: torch.Tensor):
        """``samples`` draws of :meth:`DVBFLM.model <pyro_slam.model.DVBFLM.model>` (under its
        handlers) for start poses ``z0 [K, 3]`` under ``controls [P, L, 2]``, in one trace
        vectorised over the draws as :class:`pyro.infer.Predictive` samples in parallel, with
        the map conditioned on ``M`` and ``z_0`` on the starts; the random numbers are a
        function of the starts and the controls (a rollout is deterministic, as the memo
        needs). The successors follow the model's noise-free transition (:meth:`_mean_path`);
        the end scans are the draws of the observation site ``x_L`` at the draws' poses (the
        planner's safety cost is the mean over them). Returns
        ``[K, P, ...]`` (see :meth:`rollout`), the scans ``[K, P, S, B]``."""
        K, (P, L, _), S = len(z0), controls.shape, self.samples
        init = torch.as_tensor(z0, dtype=controls.dtype)[:, None]  # [K, 1, 3]
        fixed = {"map": self.M, "z_0": init.expand(S, K, 1, 3)}
        model = poutine.condition(self.model.handled(), fixed)
        with torch.random.fork_rng(devices=[]), pyro.validation_enabled(False):
            torch.manual_seed(_seed(z0, controls))
            with pyro.plate("_num_predictive_samples", S, dim=-3):
                tr = poutine.trace(model).get_trace(None, controls, init)
        path = self._mean_path(init.expand(K, P, 3), controls)  # [K, P, L + 1, 3]
        travel = (path[..., 1:, :2] - path[..., :-1, :2]).norm(dim=-1).sum(-1)  # [K, P]
        scans = tr.nodes[f"x_{L}"]["value"].expand(S, K, P, -1).movedim(0, 2)  # [K, P, S, B]
        return path[:, :, -1].numpy(), travel.numpy(), scans, path.numpy()

    def _mean_path(self, z: torch.Tensor, controls: torch.Tensor) -> torch.Tensor:
        """The poses the controls ``[P, L, 2]`` lead to from ``z [K, P, 3]`` under the model's
        noise-free transition (its mean, reading the predicted scans): ``[K, P, L + 1, 3]``.
        The controls are executed open loop, so a node is where they take the agent, not
        the mean of noisy draws (whose heading noise would drift the plan from it)."""
        path = [z]
        for t in range(controls.shape[-2]):
            scan = self.model.emission_mean(self.M, z) if self.model.transition.needs_scan else None
            z = self.model.transition.mean(z, controls[:, t], scan)
            path.append(z)
        return torch.stack(path, -2)


def _seed(*arrays) -> int:
    """A seed that is a function of the arrays' values."""
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(np.asarray(a)).tobytes())
    return int.from_bytes(h.digest()[:8], "little") % (2**63)


class GroundTruthEnv(_Rollouts):
    """The simulator's truth: analytic raycast on the walls, exact pymunk kinematics."""

    name = "ground_truth"

    def __init__(self, maze, lidar=None):
        self.maze = maze
        self.lidar = lidar or LidarConfig()
        self.world = World(maze, self.lidar, odometry_noise=0, seed=0)
        self.bounds = maze_bounds(maze)
        self._grid_key, self._grid = None, None  # places(): the ray-cast search grid
        self._memos: dict = {}  # rollouts per controls and start pose (see _Rollouts)

    def scan(self, z) -> torch.Tensor:
        z = np.atleast_2d(np.asarray(z, dtype=np.float64))
        ang = z[:, 2:3] + self.lidar.beam_angles[None]
        r = raycast(self.maze.walls, z[:, :2], ang, self.lidar.max_range)
        return torch.as_tensor(r, dtype=torch.get_default_dtype())

    def _rollout(self, z0: np.ndarray, controls: torch.Tensor):
        """The pymunk world stepped through ``controls [P, L, 2]`` from each pose of ``z0 [K,
        3]``: ``[K, P, ...]`` (see :meth:`rollout`)."""
        c = controls.numpy()
        (P, L, _), K = c.shape, len(z0)
        paths = np.zeros((K, P, L + 1, 3))
        for i, p in np.ndindex(K, P):
            self.world.reset(z0[i])
            paths[i, p, 0] = self.world.pose
            for k in range(L):
                paths[i, p, k + 1] = self.world.step(c[p, k]) if c[p, k].any() else paths[i, p, k]
        travel = np.linalg.norm(np.diff(paths[..., :2], axis=-2), axis=-1).sum(-1)  # [K, P]
        scans = self.scan(paths[:, :, -1].reshape(-1, 3)).reshape(K, P, -1)
        return paths[:, :, -1], travel, scans, paths

    def valid(self, z) -> np.ndarray:
        return np.ones(len(z), dtype=bool)

    def places(
        self,
        scans,
        *,
        spacing: float = 0.01,
        n_headings: int = 360,
        coarse_tol: float = 0.03,
        separation: float = 0.05,
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """The exact inverse of the noise-free LiDAR: for each scan of ``scans [N, B]``, the
        distinct places whose *true* scan matches it, as ``(poses [k, 3], diffs [k])`` sorted by
        ``diffs``, the mean absolute range difference (``k = 0`` if no pose is within
        ``coarse_tol``).

        The positions of a ``spacing`` grid (free of walls) are ray-cast once in ``n_headings``
        directions (a multiple of the beam count: the scan of every grid heading is then a
        rotation of those rays). The grid poses whose scan is within ``coarse_tol`` of the
        target are thinned greedily, best first, to one per ``separation``, and each is refined
        by Nelder-Mead on the difference (non-smooth, so derivative-free); refinements that end
        within ``separation`` of a better one are dropped. ``poses[0]`` is the
        best match, the truth's mode: the ground-truth planner's goal for an observation target.
        Entries with ``diffs`` below ~1e-6 are exact look-alikes, perceptual aliasing that no
        inverse model reading this one scan can resolve.
        """

        B = self.lidar.n_beams
        if n_headings % B:
            raise ValueError(f"n_headings={n_headings} must be a multiple of the {B} beams")
        scans = np.atleast_2d(np.asarray(scans, dtype=np.float64))  # [N, B]
        if scans.shape[-1] != B:
            raise ValueError(f"scans have {scans.shape[-1]} beams, the LiDAR {B}: {scans.shape}")
        xy, rays, ranked = self._ray_grid(spacing, n_headings)  # [P, 2], [P, H], [P, B, s]
        angles = 2 * np.pi * np.arange(n_headings) / n_headings  # [H]
        out = []
        for x in scans:
            best, h = self._coarse(x, rays, ranked, coarse_tol)  # [P], [P]
            reps = _thin(xy, best.tolist(), coarse_tol, separation)
            refined = [
                self._refine(x, np.array([*xy[p], angles[h[p]]]), spacing, n_headings) for p in reps
            ]
            poses = [z for z, _ in refined]
            diffs = [d for _, d in refined]
            keep = _thin([z[:2] for z in poses], diffs, np.inf, separation)  # one per place
            out.append((np.array(poses).reshape(-1, 3)[keep], np.array(diffs)[keep]))
        return out

    def _refine(self, x, z0, spacing: float, n_headings: int) -> tuple[np.ndarray, float]:
        """Nelder-Mead from ``z0 [3]`` on the mean absolute difference between the true scan
        and ``x [B]``: the refined pose (heading wrapped) and its difference."""

        def diff(z):  # float64, no torch round trip
            ang = z[2] + self.lidar.beam_angles[None]
            r = raycast(self.maze.walls, z[None, :2], ang, self.lidar.max_range)
            return np.abs(r[0] - x).mean()

        step = [[0, 0, 0], [spacing / 2, 0, 0], [0, spacing / 2, 0], [0, 0, np.pi / n_headings]]
        options = {"initial_simplex": z0 + np.array(step), "xatol": 1e-8, "fatol": 1e-10}
        r = minimize(diff, z0, method="Nelder-Mead", options=options)
        z = r.x.copy()
        z[2] = (z[2] + np.pi) % (2 * np.pi) - np.pi
        return z, float(r.fun)

    @staticmethod
    def _coarse(x: np.ndarray, rays: torch.Tensor, ranked: torch.Tensor, tol: float):
        """The best grid heading of each grid position for scan ``x [B]``: mean absolute
        difference ``[P]`` (``inf`` where it exceeds ``tol``) and heading index ``[P]``.

        Grid pose ``(p, h)`` reads ray ``h + s i`` for beam ``i`` (``s = H / B``); with ``h = s
        q + r`` that is entry ``(q + i) mod B`` of row ``r`` of the rays reshaped ``[P, B, s]``,
        so every heading of one ``r`` sees the same multiset of ranges. The mean absolute
        difference between the sorted ranges and the sorted scan is a lower bound (sorted
        pairing minimises it), so only positions whose bound is within ``tol`` for some ``r``
        are compared heading by heading -- the same result as comparing them all. ``ranked
        [P, B, s]``: the rays so reshaped, sorted along ``B``."""
        (P, H), B = rays.shape, len(x)
        step = H // B
        xs = torch.as_tensor(np.sort(x), dtype=rays.dtype)[:, None]  # [B, 1]
        bound = (ranked - xs).abs().mean(1).min(1).values  # [P]
        cand = torch.nonzero(bound <= tol + 1e-9).squeeze(1)  # [C]
        sub = rays[cand]  # [C, H]
        d = torch.zeros_like(sub)  # [C, H]: grid pose (p, h) reads ray h + step * i
        for i in range(B):
            d += (torch.roll(sub, -i * step, dims=1) - float(x[i])).abs()
        best = torch.full((P,), float("inf"), dtype=rays.dtype)
        h = torch.zeros(P, dtype=torch.long)
        best[cand], h[cand] = (d / B).min(1)
        return best, h

    def _ray_grid(self, spacing: float, n_headings: int):
        """Cached: the wall-free positions ``[P, 2]`` of a ``spacing`` grid over the maze, their
        ranges ``[P, n_headings]`` at ``n_headings`` evenly spaced directions from 0, and those
        ranges reshaped ``[P, B, n_headings / B]`` and sorted along the beams (see
        :meth:`_coarse`)."""
        key = (spacing, n_headings)
        if self._grid_key != key:
            xs = np.arange(spacing / 2, self.maze.side, spacing)
            xy = np.stack(np.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
            xy = xy[[point_segment_distance(p, self.maze.walls).min() > 1e-3 for p in xy]]
            ang = 2 * np.pi * np.arange(n_headings) / n_headings
            rays = raycast(
                self.maze.walls,
                xy,
                np.broadcast_to(ang, (len(xy), n_headings)),
                self.lidar.max_range,
            )
            rays = torch.as_tensor(rays)
            B = self.lidar.n_beams
            ranked = torch.sort(rays.reshape(len(xy), B, n_headings // B), dim=1).values
            self._grid_key, self._grid = key, (xy, rays, ranked)
        return self._grid


class ScanHits:
    """The returns of a traversal's scans placed from its poses (the true ones, or a SLAM
    run's): a point set ``[H, 2]`` of the walls as the scans saw them, every wall face that
    a scan hit, wall ends included, whatever the map belief made of them.

    Args:
        traversal: a :class:`~pyro_slam.data.Traversal` (``observations [T, B]``).
        poses: ``[T, 3]`` the scans are placed from (default: the traversal's true poses).
    """

    def __init__(self, traversal, poses=None):
        z = np.asarray(traversal.poses if poses is None else poses, dtype=np.float64)  # [T, 3]
        x = np.asarray(traversal.observations, dtype=np.float64)  # [T, B]
        hit = x < traversal.max_range * (1 - 1e-3)  # [T, B]: readings at the range are misses
        ang = z[:, 2:3] + np.asarray(traversal.beam_angles)[None]  # [T, B]
        pts = z[:, None, :2] + x[..., None] * np.stack([np.cos(ang), np.sin(ang)], -1)
        self.points = pts[hit]  # [H, 2]
        self.tree = cKDTree(self.points)

    def clearance(self, xy, upto: float = np.inf) -> np.ndarray:
        """Distance ``[N]`` from positions ``xy [N, 2]`` to the nearest return (``inf`` where
        none is within ``upto``)."""
        d, _ = self.tree.query(np.asarray(xy, dtype=np.float64), k=1, distance_upper_bound=upto)
        return d


def _thin(xy, scores, tol: float, separation: float) -> list[int]:
    """Greedily, best score first: the indices of ``xy [n, 2]`` with ``scores [n]`` within
    ``tol`` that lie more than ``separation`` from every one kept before."""
    keep: list[int] = []
    for p in np.argsort(scores, kind="stable").tolist():
        if scores[p] > tol:
            break
        if all(np.hypot(*(np.asarray(xy[p]) - np.asarray(xy[q]))) > separation for q in keep):
            keep.append(p)
    return keep


def lookalikes(poses, diffs, target, tol: float = 1e-6, radius: float = 0.05) -> tuple[int, float]:
    """Perceptual aliasing of a target pose ``target [2 or 3]`` from its
    :meth:`GroundTruthEnv.places` ``(poses [k, 3], diffs [k])``: the number of look-alike places
    (``diffs < tol``) more than ``radius`` from the target, and how often a uniform choice among
    all its places within ``tol`` (the target's own counted once at least) lands farther than
    ``radius`` -- the expected failure of an ideal inverse that reads only the scan."""
    far = np.hypot(*(np.asarray(poses)[:, :2] - np.asarray(target)[:2]).T) > radius  # [k]
    alike = np.asarray(diffs) < tol  # [k]
    n_far, n_near = int((far & alike).sum()), int((~far & alike).sum())
    return n_far, n_far / (n_far + max(n_near, 1))


# --------------------------------------------------------------------------- learned map


def learned_env(
    maze,
    traversal=None,
    steps: int = NAVIGATION.traversal_steps,
    seed: int = 1,
    fit_steps: int = NAVIGATION.fit_steps,
    poses=None,
    progress: bool = False,
    max_std: float = NAVIGATION.max_std,
    emission_steps: int = NAVIGATION.emission_steps,
    n_world: int = NAVIGATION.n_world,
    tour=None,
    hit_margin: float = NAVIGATION.hit_margin,
    *,
    prior=None,
    noise=None,
    guide=None,
    slam=None,
    noise_fit: bool | None = None,
):
    """A :class:`LearnedEnv` for ``maze``.

    From a fitted :class:`~pyro_slam.slam.SLAM` (``slam``): its model (transition, emission,
    map prior, noise, handlers) and its map belief ``q(M)``, as SLAM left them, at its poses.

    Otherwise: simulate a traversal (unless given; ``steps`` exploring steps, then a tour
    through the positions ``tour`` ``[P, 2]`` it missed, see
    :func:`simulators.simulate_traversal`), and fit ``q(M)`` with
    :func:`~pyro_slam.slam.fit_map` at ``poses`` (default: the true poses, i.e. mapping with
    known poses) under a frozen emission, in the model with the map ``prior`` and emission
    ``noise`` given (:class:`~pyro_slam.model.DVBFLM`), with the map ``guide`` factory given
    (default: mean-field). The emission is the shipped pretrained one (``emission_steps = 0``;
    20 world directions) or, with ``emission_steps > 0``, one fitted to this traversal together
    with a map by :func:`~pyro_slam.slam.pretrain_emission` (``n_world`` world directions, from
    scratch, at the same ``poses``), after which ``q(M)`` is refitted under it.

    The planner also keeps ``hit_margin`` (0: off) from the traversal's returns placed from
    ``poses`` (:class:`ScanHits`), so a wall the map belief lost near its end is still
    avoided (on the tuning mazes' SLAM maps, pose targets reached: 100/100 at 0.02 against
    89/100 without).

    The planner's rollouts sample the model with its noise; ``noise_fit`` (default: for the
    model fitted here, not for a SLAM run's) first fits the emission's noise to the traversal
    at ``poses`` and the map's mean (:func:`~pyro_slam.slam.fit_noise`), so that the scans the
    planner scores are as noisy as the traversal's own, not as the training noise.

    Everything is seeded by ``seed``, whatever ran before in the process.

    Returns ``(env, (q_loc, q_scale), traversal)``."""
    torch.manual_seed(seed)  # the new emission's initial weights
    if slam is not None:
        model, traversal = slam.model, slam.tr
        belief = slam.map_belief()
        loc, scale = belief.loc, belief.scale
        poses = slam.result()["mean"] if poses is None else poses
    else:
        if traversal is None:
            traversal = simulate_traversal(maze, steps=steps, seed=seed, tour=tour)
        model = _mapping_model(
            traversal, poses, emission_steps, n_world, seed, progress, prior, noise
        )
        loc, scale = fit_map(
            traversal, model, poses, fit_steps, guide=guide, seed=seed, progress=progress
        )
    if noise_fit if noise_fit is not None else slam is None and NAVIGATION.fit_noise:
        fit_noise(traversal, model, loc, poses, seed=seed)
    hits = ScanHits(traversal, poses) if hit_margin > 0 else None
    env = LearnedEnv(
        model,
        loc,
        bounds=maze_bounds(maze),
        scale=scale,
        max_std=max_std,
        hits=hits,
        hit_margin=hit_margin,
    )
    return env, (loc, scale), traversal


def _mapping_model(traversal, poses, emission_steps, n_world, seed, progress, prior, noise):
    """The model :func:`learned_env` maps with: the configuration
    :data:`~pyro_slam.slam.presets.NAVIGATION_MAPPING`, with the shipped emission or one
    pretrained on ``traversal`` (see there), the map ``prior`` and the emission ``noise``."""
    if emission_steps > 0:
        fit_on = traversal if poses is None else replace(traversal, poses=np.asarray(poses))
        em = EmissionMLP(LIDAR_MAP_DIM, n_world, scale=traversal.max_range)
        em, _ = pretrain_emission(
            [fit_on],
            NAVIGATION_MAPPING,
            emission=em,
            steps=emission_steps,
            seed=seed,
            progress=progress,
        )
    else:
        em = load_emission(PRETRAINED / EMISSION_FILE, traversal)
    control_model = traversal.metadata.get("control_model", "rotate_forward")
    transition = KinematicTransition(
        NAVIGATION_MAPPING.transition.sigma, control_model, clip_margin=NAVIGATION.clip_margin
    )
    return build_model(
        traversal,
        NAVIGATION_MAPPING,
        transition,
        em,
        prior=prior,
        noise=noise,
        learn_emission=False,
    )[0]


def run_env(
    maze,
    traversal,
    config: SLAMConfig,
    map_loc,
    map_scale,
    poses,
    hit_margin: float = 0.02,
    prior=None,
    noise=None,
) -> LearnedEnv:
    """A :class:`LearnedEnv` in the map a SLAM run left: its ``q(M)`` (``map_loc``,
    ``map_scale [w, h, D_m]``, e.g. a run folder's ``posterior.npz``) under the model its
    ``config`` builds over ``traversal`` (the ray-cast emission, or the shipped emission MLP)
    with the run's map ``prior`` and emission ``noise`` (the defaults where None), keeping
    ``hit_margin`` from the scans placed at the run's pose means ``poses [T, 3]``.
    ``ValueError`` for a map this model cannot read."""
    tr = prepare_traversal(traversal, config)
    kind = emission_kind(config.emission.kind)
    emission = kind.shipped(tr) if kind.shipped is not None else None
    transition = transition_for(tr) if config.transition.kind == "learned" else None
    if kind.observation != "lidar" or (kind.learned and emission is None):
        raise ValueError(
            f"the run's emission.kind {kind.name!r} cannot be rebuilt for planning (a LiDAR "
            "emission without learned parameters, or with shipped ones, can)"
        )
    model, _ = build_model(
        tr, config, transition, emission, prior=prior, noise=noise, learn_emission=False
    )
    loc, scale = (torch.as_tensor(np.asarray(a), dtype=torch.float32) for a in (map_loc, map_scale))
    if tuple(loc.shape) != tuple(model.grid.shape) or loc.shape != scale.shape:
        raise ValueError(
            f"the run's map {tuple(loc.shape)} does not fit the grid {tuple(model.grid.shape)} "
            "its configuration builds over this traversal (another traversal?)"
        )
    if NAVIGATION.fit_noise:  # the rollouts' noise: the run's scans' about its map and poses
        fit_noise(tr, model, loc, poses)
    hits = ScanHits(tr, poses) if hit_margin > 0 else None
    bounds = maze_bounds(maze)
    return LearnedEnv(model, loc, bounds=bounds, scale=scale, hits=hits, hit_margin=hit_margin)


def maze_bounds(maze, margin: float = SAFETY_DELTA):
    """The maze's extent shrunk by ``margin``: unexplored space outside the outer walls reads
    as free in the learned model (prior map), so the search is kept inside."""
    return (margin, maze.side - margin, margin, maze.side - margin)


def free_grid(maze, n: int = 5, clearance: float = 0.04) -> np.ndarray:
    """An ``n x n`` grid of positions over the maze; a point closer than ``clearance`` to a wall
    moves to the centre of its maze cell. Returns ``[n * n, 2]``."""
    pts = []
    for j in range(n):
        for i in range(n):
            p = np.array([(i + 0.5) / n, (j + 0.5) / n]) * maze.side
            if point_segment_distance(p, maze.walls).min() < clearance:
                c = maze.cell_of(p)
                p = maze.cell_center(c[0], c[1])
            pts.append(p)
    return np.array(pts)


def execute(maze, start, controls, noise=0, seed: int = 0):
    """Run ``controls [T, 2]`` in the pymunk :class:`~simulators.World` from ``start``.

    ``noise``: actuation noise (``0`` = none, ``None`` = the simulator's calibrated default).
    Returns the executed poses ``[T + 1, 3]`` and the number of blocked moves.
    """
    w = World(maze, odometry_noise=noise, seed=seed, pose=start)
    poses = [w.pose]
    for u in np.asarray(controls):
        poses.append(w.step(u))
    return np.array(poses), w.collisions
