"""Planning environments: the learned DVBF-LM model (:class:`LearnedEnv`, built by
:func:`learned_env`) and the simulator's truth (:class:`GroundTruthEnv`), with one interface
(``scan``, ``rollout``, ``valid``, ``bounds``), and :func:`execute`, which runs a plan in the
simulator."""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pyro
import torch
from pyro.infer import Predictive
from scipy.optimize import minimize

from simulators import LidarConfig, World, raycast, simulate_traversal
from simulators.world import point_segment_distance

from ..model import DVBFLM, EmissionMLP, KinematicTransition
from ..pretrained import EMISSION_FILE, PRETRAINED, load_emission
from ..slam import SLAMConfig, build_model, fit_map, pretrain_emission
from ..slam.build import LAYERS, LIDAR_HIDDEN, MAP_DIM
from .planner import SAFETY_DELTA, inside_scan


# --------------------------------------------------------------------------- environments
class LearnedEnv:
    """The DVBF-LM model with a fixed map ``M`` (mean of ``q(M)``) as planning environment.

    Args:
        model: a :class:`~pyro_slam.model.DVBFLM` (its emission is used, frozen).
        M: map ``[w, h, D_m]``.
        clip_margin: stop this far before the predicted range ahead.
        bounds: ``(x0, x1, y0, y1)`` poses must stay within (default: the map extent).
    """

    name = "learned"

    def __init__(
        self,
        model,
        M: torch.Tensor,
        clip_margin: float = 0.01,
        bounds=None,
        scale: torch.Tensor | None = None,
        max_std: float = 0.6,
    ):
        self.model, self.M, self.scale, self.max_std = model, M, scale, max_std
        # the planner's copy of the model: its emission, map prior and noise, with kinematics
        # that stop short of predicted walls and no transition noise
        self.transition = KinematicTransition(0.0, "rotate_forward", clip_margin=clip_margin)
        self.planner_model = DVBFLM(model.grid, model.emission, self.transition,
                                    sigma_emission=model.sigma_emission, prior=model.prior,
                                    noise=model.noise)  # fmt: skip
        self.bounds = bounds if bounds is not None else model.grid.extent()
        self.seen: list[tuple] = []  # (pose [3], real scan [B], margin, radius)

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
        """Explored positions: chart std under ``q(M)`` below ``max_std`` of the prior's; the
        model's predicted scans are extrapolations elsewhere."""
        if self.scale is None:
            return np.ones(len(z), dtype=bool)
        ok = self.std(z) < self.max_std
        for pose, scan, margin, radius in self.seen:
            ok |= inside_scan(np.asarray(z)[:, :2], pose, scan, margin, radius)
        return ok

    @torch.no_grad()
    def rollout(self, z0: np.ndarray, controls: torch.Tensor):
        """Roll the model out under ``controls [P, L, 2]`` from pose ``z0 [3]``:
        :class:`pyro.infer.Predictive` on ``DVBFLM.model`` with the map at ``M``, the planner's
        transition (kinematics that stop short of predicted walls, no noise) and the model's
        emission, prior and noise; the predicted scans are its ``scan_t`` sites.

        Returns final poses ``[P, 3]``, travel ``[P]``, end scans ``[P, B]``, paths
        ``[P, L + 1, 3]``.
        """
        P, L, _ = controls.shape
        z0 = torch.as_tensor(z0, dtype=controls.dtype)
        sites = [f"z_{t}" for t in range(L + 1)] + [f"scan_{L}"]
        predictive = Predictive(
            self.planner_model.model,
            posterior_samples={"map": self.M[None], "z_0": z0[None]},
            return_sites=sites,
        )
        with pyro.validation_enabled(False):  # (a noise-free transition)
            s = predictive(None, controls, z0)
        path = torch.stack([s[f"z_{t}"].reshape(-1, 3).expand(P, 3) for t in range(L + 1)], 1)
        travel = (path[:, 1:, :2] - path[:, :-1, :2]).norm(dim=-1).sum(-1)  # [P]
        scans = s[f"scan_{L}"].reshape(P, -1)  # [P, B]
        return path[:, -1].numpy(), travel.numpy(), scans, path.numpy()  # path [P, L + 1, 3]


class GroundTruthEnv:
    """The simulator's truth: analytic raycast on the walls, exact pymunk kinematics."""

    name = "ground_truth"

    def __init__(self, maze, lidar=None):
        self.maze = maze
        self.lidar = lidar or LidarConfig()
        self.world = World(maze, self.lidar, odometry_noise=0, seed=0)
        self.bounds = maze_bounds(maze)
        self._grid_key, self._grid = None, None  # places(): the ray-cast search grid

    def scan(self, z) -> torch.Tensor:
        z = np.atleast_2d(np.asarray(z, dtype=np.float64))
        ang = z[:, 2:3] + self.lidar.beam_angles[None]
        r = raycast(self.maze.walls, z[:, :2], ang, self.lidar.max_range)
        return torch.as_tensor(r, dtype=torch.get_default_dtype())

    def rollout(self, z0: np.ndarray, controls: torch.Tensor):
        c = controls.numpy()
        P, L, _ = c.shape
        paths = np.zeros((P, L + 1, 3))
        for p in range(P):
            self.world.reset(z0)
            paths[p, 0] = self.world.pose
            for k in range(L):
                paths[p, k + 1] = self.world.step(c[p, k]) if c[p, k].any() else paths[p, k]
        travel = np.linalg.norm(np.diff(paths[:, :, :2], axis=1), axis=-1).sum(1)
        return paths[:, -1], travel, self.scan(paths[:, -1]), paths

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

        def diff(z, x):  # float64, no torch round trip
            r = raycast(self.maze.walls, z[None, :2], z[2] + self.lidar.beam_angles[None],
                        self.lidar.max_range)  # fmt: skip
            return np.abs(r[0] - x).mean()

        B = self.lidar.n_beams
        if n_headings % B:
            raise ValueError(f"n_headings={n_headings} must be a multiple of the {B} beams")
        scans = np.atleast_2d(np.asarray(scans, dtype=np.float64))  # [N, B]
        if scans.shape[-1] != B:
            raise ValueError(f"scans have {scans.shape[-1]} beams, the LiDAR {B}: {scans.shape}")
        xy, rays = self._ray_grid(spacing, n_headings)  # [P, 2], [P, H]
        angles = 2 * np.pi * np.arange(n_headings) / n_headings  # [H]
        step = n_headings // B
        out = []
        for x in scans:
            d = torch.zeros_like(rays)  # [P, H]: grid pose (p, h) reads ray h + step * i
            for i in range(B):
                d += (torch.roll(rays, -i * step, dims=1) - float(x[i])).abs()
            best, h = (d / B).min(1)  # [P]
            reps: list[int] = []
            for p in torch.argsort(best).tolist():
                if best[p] > coarse_tol:
                    break
                if all(np.hypot(*(xy[p] - xy[q])) > separation for q in reps):
                    reps.append(p)
            poses, diffs = [], []
            for p in reps:
                z0 = np.array([*xy[p], angles[h[p]]])
                simplex = z0 + np.array([[0, 0, 0], [spacing / 2, 0, 0], [0, spacing / 2, 0],
                                         [0, 0, np.pi / n_headings]])  # fmt: skip
                r = minimize(
                    diff, z0, args=(x,), method="Nelder-Mead",
                    options={"initial_simplex": simplex, "xatol": 1e-8, "fatol": 1e-10},
                )  # fmt: skip
                z = r.x.copy()
                z[2] = (z[2] + np.pi) % (2 * np.pi) - np.pi
                poses.append(z)
                diffs.append(float(r.fun))
            keep: list[int] = []  # refinements that converged to one place count once
            for j in np.argsort(diffs, kind="stable"):
                if all(np.hypot(*(poses[j][:2] - poses[q][:2])) > separation for q in keep):
                    keep.append(j)
            out.append((np.array(poses).reshape(-1, 3)[keep], np.array(diffs)[keep]))
        return out

    def _ray_grid(self, spacing: float, n_headings: int):
        """Cached: the wall-free positions ``[P, 2]`` of a ``spacing`` grid over the maze and
        their ranges ``[P, n_headings]`` at ``n_headings`` evenly spaced directions from 0."""
        key = (spacing, n_headings)
        if self._grid_key != key:
            xs = np.arange(spacing / 2, self.maze.side, spacing)
            xy = np.stack(np.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
            xy = xy[[point_segment_distance(p, self.maze.walls).min() > 1e-3 for p in xy]]
            ang = 2 * np.pi * np.arange(n_headings) / n_headings
            rays = raycast(self.maze.walls, xy, np.broadcast_to(ang, (len(xy), n_headings)),
                           self.lidar.max_range)  # fmt: skip
            self._grid_key, self._grid = key, (xy, torch.as_tensor(rays))
        return self._grid


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
    steps: int = 3000,
    seed: int = 1,
    fit_steps: int = 1500,
    poses=None,
    progress: bool = False,
    max_std: float = 0.6,
    emission_steps: int = 0,
    n_world: int = 20,
    tour=None,
):
    """A :class:`LearnedEnv` for ``maze``: simulate a traversal (unless given; ``steps``
    exploring steps, then a tour through the positions ``tour`` ``[P, 2]`` it missed, see
    :func:`simulators.simulate_traversal`), fit ``q(M)``
    with :func:`~pyro_slam.slam.fit_map` at ``poses`` (default: the true poses, i.e. mapping
    with known poses) under a frozen emission.

    The emission is the shipped pretrained one (``emission_steps = 0``; 20 world directions)
    or, with ``emission_steps > 0``, one fitted to this traversal together with a map by
    :func:`~pyro_slam.slam.pretrain_emission` (``n_world`` world directions, from scratch, at
    the same ``poses``), after which ``q(M)`` is refitted under it.

    Returns ``(env, (q_loc, q_scale), traversal)``."""
    if traversal is None:
        traversal = simulate_traversal(maze, steps=steps, seed=seed, tour=tour)
    cfg = SLAMConfig()  # the paper's LiDAR emission MLP
    if emission_steps > 0:
        fit_on = traversal if poses is None else replace(traversal, poses=np.asarray(poses))
        em = EmissionMLP(MAP_DIM, n_world, LIDAR_HIDDEN, LAYERS, scale=traversal.max_range)
        em, _ = pretrain_emission([fit_on], cfg, emission=em, steps=emission_steps, seed=seed,
                                  progress=progress)  # fmt: skip
    else:
        em = load_emission(PRETRAINED / EMISSION_FILE, traversal)
    model, _ = build_model(traversal, cfg, emission=em)
    loc, scale = fit_map(traversal, model, poses, fit_steps, seed=seed, progress=progress)
    env = LearnedEnv(model, loc, bounds=maze_bounds(maze), scale=scale, max_std=max_std)
    return env, (loc, scale), traversal


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
