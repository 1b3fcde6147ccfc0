"""PEMA baseline (Mirchev et al. 2019, Appendix F): an LSTM exploration policy trained with
Augmented Random Search (Mania et al. 2018) to maximise the number of visited tiles.

* :class:`PEMAPolicy` -- LSTM cell (256 units) over LiDAR scans; softsign on its output state,
  a linear layer gives the turn; the control is ``(turn, step_length)`` (constant offset along
  the heading). Weights live in one flat vector so that ARS can perturb them; ``P`` policies run
  batched (``torch.bmm``).
* :func:`ars` -- ARS V1-t: ``N`` Gaussian directions, rewards at ``theta +- nu delta``, the
  ``b`` best directions (by ``max(r+, r-)``) form the step, scaled by the std of their rewards.
* :func:`train_pema` -- rewards are visited-tile counts of ``T``-step rollouts from random starts
  in a set of training mazes (same starts for all perturbations of one iteration).
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass

import numpy as np
import torch

from simulators import SCALES, World, make_maze
from simulators.raycast import raycast

log = logging.getLogger(__name__)


class PEMAPolicy:
    """LSTM policy with flat weights ``theta [n]`` (or ``[P, n]`` for ``P`` policies at once)."""

    def __init__(
        self,
        n_beams: int = 20,
        hidden: int = 256,
        max_range: float = 0.53,
        step_length: float = 0.01,
        max_turn: float = math.pi / 4,
    ):
        self.B, self.H = n_beams, hidden
        self.max_range, self.step_length, self.max_turn = max_range, step_length, max_turn
        B, H = n_beams, hidden
        self.shapes = {
            "w_ih": (4 * H, B),
            "w_hh": (4 * H, H),
            "b": (4 * H,),
            "w_out": (1, H),
            "b_out": (1,),
        }
        self.size = sum(math.prod(s) for s in self.shapes.values())
        self.theta = self.init_params(torch.Generator().manual_seed(0))

    def init_params(self, generator=None) -> torch.Tensor:
        """PyTorch's LSTM initialisation U(-1/sqrt(H), 1/sqrt(H)); small read-out."""
        k = 1 / math.sqrt(self.H)
        th = (2 * torch.rand(self.size, generator=generator) - 1) * k
        n_out = self.H + 1
        th[-n_out:] *= 0.1
        return th

    def unflatten(self, theta: torch.Tensor) -> dict:
        theta = theta.reshape(-1, self.size)
        out, i = {}, 0
        for name, s in self.shapes.items():
            n = math.prod(s)
            out[name] = theta[:, i : i + n].reshape(theta.shape[0], *s)
            i += n
        return out

    def initial_state(self, P: int = 1):
        return torch.zeros(P, self.H), torch.zeros(P, self.H)

    def turn(self, w: dict, scans: torch.Tensor, state):
        """One LSTM step for ``P`` policies: ``scans [P, B]`` -> turns ``[P]``, new state."""
        h, c = state
        x = scans / self.max_range
        gates = torch.bmm(w["w_ih"], x.unsqueeze(-1)) + torch.bmm(w["w_hh"], h.unsqueeze(-1))
        gates = gates.squeeze(-1) + w["b"]
        i, f, g, o = gates.chunk(4, -1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        h = torch.sigmoid(o) * torch.tanh(c)
        s = h / (1 + h.abs())  # softsign on the output state
        rot = torch.bmm(w["w_out"], s.unsqueeze(-1)).squeeze(-1)[:, 0] + w["b_out"][:, 0]
        return rot.clamp(-self.max_turn, self.max_turn), (h, c)

    def act(self, scan, state):
        """Control ``[2]`` for one scan ``[B]`` with the policy's own weights."""
        with torch.no_grad():
            x = torch.as_tensor(np.asarray(scan), dtype=torch.get_default_dtype())[None]
            rot, state = self.turn(self.unflatten(self.theta), x, state)
        return np.array([float(rot[0]), self.step_length]), state


def rollout_rewards(policy: PEMAPolicy, thetas: torch.Tensor, mazes, starts, steps: int, tiles):
    """Visited-tile counts summed over mazes for each policy in ``thetas [P, n]``.

    ``starts[m]``: start pose ``[3]`` in maze ``m`` (shared by all policies); the agents move by
    the simulator kinematics (rotate, then move, stopping before walls; no actuation noise).
    """
    P = thetas.shape[0]
    w = policy.unflatten(thetas)
    total = np.zeros(P)
    for maze, start, n_tiles in zip(mazes, starts, tiles, strict=True):
        worlds = [World(maze, odometry_noise=0, pose=start) for _ in range(P)]
        angles = np.asarray([0.0]) + 2 * np.pi * np.arange(policy.B) / policy.B
        visited = [set() for _ in range(P)]
        state = policy.initial_state(P)
        pos = np.array([wd.pose for wd in worlds])
        for _ in range(steps):
            scans = raycast(maze.walls, pos[:, :2], pos[:, 2:3] + angles, policy.max_range)
            with torch.no_grad():
                rot, state = policy.turn(w, torch.as_tensor(scans, dtype=torch.float32), state)
            for p, wd in enumerate(worlds):
                wd.step((float(rot[p]), policy.step_length))
            pos = np.array([wd.pose for wd in worlds])
            ij = np.clip(np.floor(pos[:, :2] / maze.side * n_tiles).astype(int), 0, n_tiles - 1)
            for p in range(P):
                visited[p].add((int(ij[p, 0]), int(ij[p, 1])))
        total += np.array([len(v) / n_tiles**2 for v in visited])
    return total


@dataclass
class ARSConfig:
    iterations: int = 100
    directions: int = 16  # N
    top: int = 8  # b
    step_size: float = 0.02  # alpha
    noise: float = 0.02  # nu
    seed: int = 0

    def to_dict(self):
        return asdict(self)


def ars(objective, theta0: torch.Tensor, cfg: ARSConfig, callback=None):
    """Augmented Random Search (V1-t) maximising ``objective(thetas [P, n]) -> rewards [P]``.

    Returns the final ``theta`` and the per-iteration reward of the unperturbed ``theta``
    (evaluated on that iteration's episodes, ``objective`` called with ``2 N + 1`` policies).
    """
    gen = torch.Generator().manual_seed(cfg.seed)
    theta = theta0.clone()
    history = []
    N, b = cfg.directions, min(cfg.top, cfg.directions)
    for it in range(cfg.iterations):
        delta = torch.randn(N, theta.numel(), generator=gen)
        thetas = torch.cat([theta[None], theta + cfg.noise * delta, theta - cfg.noise * delta])
        r = np.asarray(objective(thetas), dtype=np.float64)
        r0, rp, rm = r[0], r[1 : N + 1], r[N + 1 :]
        history.append(float(r0))
        order = np.argsort(-np.maximum(rp, rm))[:b]
        sd = np.concatenate([rp[order], rm[order]]).std()
        if sd > 1e-12:
            diff = torch.as_tensor(rp[order] - rm[order], dtype=theta.dtype)
            theta = theta + cfg.step_size / (b * sd) * (diff[:, None] * delta[order]).sum(0)
        if callback is not None:
            callback(it, float(r0), theta)
    return theta, history


def train_pema(
    policy: PEMAPolicy,
    cfg: ARSConfig,
    scale_name: str = "moderate-medium",
    n_mazes: int = 10,
    steps: int = 1000,
    maze_seed0: int = 1000,
    progress: bool = False,
):
    """Train ``policy.theta`` with ARS on ``n_mazes`` training mazes of ``scale_name``
    (seeds ``maze_seed0 ...``, disjoint from evaluation mazes); random starts per iteration."""
    mazes = [make_maze(scale_name, maze_seed0 + i) for i in range(n_mazes)]
    tiles = [SCALES[scale_name].tiles] * n_mazes
    rng = np.random.default_rng(cfg.seed)

    def objective(thetas):
        starts = [m.random_free_pose(rng) for m in mazes]
        return rollout_rewards(policy, thetas, mazes, starts, steps, tiles)

    def cb(it, r0, _th):
        if progress:
            log.info("ARS iteration %d: reward %.3f", it, r0)

    policy.theta, history = ars(objective, policy.theta, cfg, cb)
    return history
