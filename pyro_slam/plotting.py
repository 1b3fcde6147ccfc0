"""Plots of SLAM runs (trajectories, map belief, error vs time with percentile bands) and of
navigation runs (plan over the map belief, executed trajectory).

All functions write a PNG (matplotlib, Agg backend) and return its path.
"""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from . import metrics  # noqa: E402
from .data import atomic_write  # noqa: E402


def _save(fig, path) -> Path:
    path = Path(path)
    buf = io.BytesIO()
    fig.savefig(buf, dpi=120, bbox_inches="tight", format=path.suffix.lstrip(".") or "png")
    plt.close(fig)
    atomic_write(path, lambda f: f.write(buf.getvalue()))
    return path


def _walls(ax, walls):
    if len(walls):
        ax.add_collection(LineCollection(np.asarray(walls).reshape(-1, 2, 2), colors="k", lw=1.2))


def map_image(loc: np.ndarray, prior: float = 0.0) -> np.ndarray:
    """Map mean ``[w, h, D]`` -> RGB ``[h, w, 3]`` in [0, 1] via its (up to) 3 principal
    components. ``D = 1`` (an occupancy or ramp map: higher is a wall): grey levels on a scale
    centred on the prior's mean ``prior``, so that a cell the scans never reached is mid-grey
    on every map, walls dark and free space light (the scale: the 98th percentile of how far
    the cells the scans reached moved from the prior)."""
    w, h, d = loc.shape
    if d == 1:
        moved = loc[..., 0] - prior  # [w, h]
        reached = np.abs(moved[np.abs(moved) > 1e-6])
        scale = float(np.percentile(reached, 98)) if reached.size else 1.0
        gray = 0.5 - 0.5 * np.clip(moved / max(scale, 1e-9), -1, 1)
        return np.repeat(gray.T[..., None], 3, -1)
    flat = loc.reshape(-1, d) - loc.reshape(-1, d).mean(0)
    _, _, vt = np.linalg.svd(flat, full_matrices=False)
    pcs = flat @ vt[: min(3, d)].T
    pcs = np.pad(pcs, ((0, 0), (0, 3 - pcs.shape[1])))
    lo, hi = np.percentile(pcs, 2, axis=0), np.percentile(pcs, 98, axis=0)
    rgb = np.clip((pcs - lo) / np.maximum(hi - lo, 1e-9), 0, 1)
    return rgb.reshape(w, h, 3).transpose(1, 0, 2)


def map_kind(loc: np.ndarray) -> str:
    """What :func:`map_image` shows of a map mean ``[w, h, D]`` (for a title)."""
    d = loc.shape[-1]
    return "occupancy, walls dark" if d == 1 else f"{min(3, d)} principal components"


def plot_slam(traversal, result: dict, grid, path_png, title: str = "") -> Path:
    """Three panels: trajectories (true / SLAM / path integration) on the walls, the map belief's
    mean (:func:`map_image`) and its mean std. ``result``: ``mean [T, 3]``, ``map_loc [w, h,
    D]``, ``map_scale [w, h, D]``, optionally ``path_integration [T, 3]`` and ``mode``."""
    est = result["mean"]  # [T, 3]
    pi = result.get("path_integration")
    fig, axes = plt.subplots(1, 3, figsize=(17, 5.5))
    ax = axes[0]
    _walls(ax, traversal.walls)
    if traversal.poses is not None:
        ax.plot(*traversal.poses[:, :2].T, color="k", lw=0.8, alpha=0.6, label="true")
    if pi is not None:
        ax.plot(*pi[:, :2].T, color="tab:red", lw=0.8, label="path integration")
    mode = result.get("mode")
    ax.plot(*est[:, :2].T, color="tab:blue", lw=0.8, label=f"SLAM ({mode})" if mode else "SLAM")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title or "trajectories")
    ext = grid.extent()  # (x0, x1, y0, y1)
    loc, scale = result["map_loc"], result["map_scale"]
    axes[1].imshow(map_image(loc), origin="lower", extent=ext, interpolation="nearest")
    _walls(axes[1], traversal.walls)
    axes[1].set_title(f"map belief: mean ({map_kind(loc)})")
    im = axes[2].imshow(scale.mean(-1).T, origin="lower", extent=ext, cmap="magma", vmin=0, vmax=1)
    _walls(axes[2], traversal.walls)
    fig.colorbar(im, ax=axes[2], fraction=0.046, pad=0.04)
    axes[2].set_title("map belief: mean std (1 = prior)")
    for a in axes[1:]:
        a.set_aspect("equal")
    return _save(fig, path_png)


def plot_errors(traversal, result: dict, path_png) -> Path:
    """Localisation error and error relative to distance travelled vs time, SLAM vs PI."""
    true = traversal.poses
    fig, axes = plt.subplots(1, 2, figsize=(12, 4), layout="constrained")
    curves = {"SLAM": result["mean"]}
    if result.get("path_integration") is not None:
        curves["path integration"] = result["path_integration"]
    for (name, est), c in zip(curves.items(), ["tab:blue", "tab:red"]):
        axes[0].plot(metrics.localisation_error(est, true), color=c, label=name)
        axes[1].plot(metrics.relative_error(est, true), color=c, label=name)
    axes[0].set_ylabel("localisation error")
    axes[1].set_ylabel("error / distance travelled")
    axes[1].set_yscale("log")
    for a in axes:
        a.set_xlabel("time step")
        a.legend()
        a.grid(alpha=0.3)
    return _save(fig, path_png)


def plot_error_bands(curves: dict[str, np.ndarray], path_png, distance=None, title="") -> Path:
    """Paper Fig. 4: median and 50% / 80% bands of ``[runs, T]`` error curves per method.

    ``distance [runs, T]`` (optional) adds a second panel with errors relative to it.
    """
    colors = ["tab:blue", "tab:green", "tab:red", "tab:purple", "tab:orange"]
    n = 1 if distance is None else 2
    fig, axes = plt.subplots(1, n, figsize=(6.5 * n, 4), squeeze=False, layout="constrained")
    for (name, e), c in zip(curves.items(), colors):
        if distance is None:
            panels = [e]
        else:  # relative error is undefined before the agent has moved (distance ~ 0)
            rel = np.where(distance > 0.05, e / np.maximum(distance, 1e-9), np.nan)
            panels = [e, rel]
        for ax, v in zip(axes[0], panels):
            t = np.arange(v.shape[1])
            ok = ~np.isnan(v).all(0)
            t, v = t[ok], v[:, ok]
            ax.plot(t, np.nanmedian(v, 0), color=c, label=name)
            for lo, hi, a in ((25, 75, 0.35), (10, 90, 0.15)):
                p_lo, p_hi = np.nanpercentile(v, lo, 0), np.nanpercentile(v, hi, 0)
                ax.fill_between(t, p_lo, p_hi, color=c, alpha=a, lw=0)
    axes[0, 0].set_ylabel("localisation error")
    if n == 2:
        axes[0, 1].set_ylabel("error / distance travelled")
        axes[0, 1].set_yscale("log")
    for ax in axes[0]:
        ax.set_xlabel("time step")
        ax.grid(alpha=0.3)
        ax.legend()
    if title:
        fig.suptitle(title + " (median, 50% and 80% bands)")
    return _save(fig, path_png)


def plot_scan_map(traversal, poses, path_png, grid=None, map_loc=None, title="", others=None):
    """Map image of a real log: scan endpoints reprojected with the estimated ``poses`` and the
    trajectory (left), and the map belief's mean (:func:`map_image`, right, when
    ``grid`` and ``map_loc`` are given). ``others``: ``{name: [T, 3] poses}`` drawn as extra
    trajectories (e.g. odometry)."""
    xy, _ = metrics.scan_points(traversal, poses)
    n = 1 if map_loc is None else 2
    fig, axes = plt.subplots(1, n, figsize=(7 * n, 6.5), squeeze=False)
    ax = axes[0, 0]
    ax.scatter(xy[:, 0], xy[:, 1], s=0.2, c="k", alpha=0.35, linewidths=0)
    for (name, p), c in zip((others or {}).items(), ["tab:red", "tab:green", "tab:purple"]):
        ax.plot(*np.asarray(p)[:, :2].T, color=c, lw=0.7, label=name)
    ax.plot(*np.asarray(poses)[:, :2].T, color="tab:blue", lw=0.8, label="estimate")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title or "scans reprojected with the estimated poses")
    if map_loc is not None:
        ax = axes[0, 1]
        ax.imshow(map_image(map_loc), origin="lower", extent=grid.extent(), interpolation="nearest")
        ax.plot(*np.asarray(poses)[:, :2].T, color="w", lw=0.5)
        ax.set_aspect("equal")
        ax.set_title(f"map belief: mean ({map_kind(map_loc)})")
    return _save(fig, path_png)


def plot_navigation(
    maze,
    env,
    result,
    executed: np.ndarray,
    goal,
    path_png,
    title: str = "",
    inferred=None,
) -> Path:
    """``result``: a :class:`~pyro_slam.planning.PlanResult`. Left: the plan over the map belief
    (predicted nearest range per position); right: the executed trajectory in the simulator
    with the true walls. ``inferred``: the goal inferred from an observation target (drawn as a
    cross; ``goal`` is then the true target)."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 5))
    n = 80
    xs = (np.arange(n) + 0.5) / n * maze.side
    X, Y = np.meshgrid(xs, xs)
    z = torch.as_tensor(
        np.stack([X.ravel(), Y.ravel(), np.zeros(n * n)], -1), dtype=torch.get_default_dtype()
    )
    with torch.no_grad():
        img = env.scan(z).min(-1).values.reshape(n, n).numpy()
    ax = axes[0]
    ax.imshow(img, origin="lower", extent=(0, maze.side, 0, maze.side), cmap="gray")
    if len(result.visited):
        ax.plot(*result.visited[:, :2].T, ".", ms=2, color="tab:orange", alpha=0.4)
    ax.plot(*result.path[:, :2].T, "-", color="tab:blue", lw=2, label="plan")
    ax.set_title(f"plan in {env.name} belief ({result.expansions} expansions)")
    ax = axes[1]
    _walls(ax, maze.walls)
    ax.plot(*result.path[:, :2].T, "--", color="tab:blue", lw=1, label="plan")
    ax.plot(*executed[:, :2].T, "-", color="tab:green", lw=2, label="executed")
    err = float(np.hypot(*(executed[-1, :2] - np.asarray(goal)[:2])))
    ax.set_title(f"executed in simulator: final error {err:.3f}")
    for ax in axes:
        ax.plot(*result.path[0, :2], "o", color="k")
        ax.plot(*np.asarray(goal)[:2], "*", color="tab:red", ms=14)
        ax.add_patch(plt.Circle(np.asarray(goal)[:2], 0.05, fill=False, color="tab:red"))
        if inferred is not None:
            ax.plot(*np.asarray(inferred)[:2], "x", color="tab:purple", ms=12, mew=3)
        ax.set_xlim(0, maze.side)
        ax.set_ylim(0, maze.side)
        ax.set_aspect("equal")
    axes[1].legend(loc="upper right", fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, path_png)
