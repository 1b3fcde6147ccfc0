"""Static plots of simulated traversals (matplotlib, Agg backend)."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from slamdata import Traversal, atomic_write  # noqa: E402


def plot_traversal(traversal: Traversal, path_png, scan_step: int | None = None) -> Path:
    """Draw walls, the true trajectory coloured by time and one LiDAR scan; save as PNG.

    Args:
        traversal: needs ``poses``; distractors are read from ``metadata["distractor_segments"]``.
        path_png: output file.
        scan_step: time step whose scan is drawn as rays (default: the middle step).
    Returns:
        the written path.
    """
    if traversal.poses is None:
        raise ValueError("plot_traversal needs a traversal with poses")
    poses = np.asarray(traversal.poses, dtype=np.float64)  # [T, 3]
    t = len(poses) // 2 if scan_step is None else int(scan_step)
    if not 0 <= t < len(poses):
        raise IndexError(f"scan_step {t} outside a traversal of {len(poses)} steps")
    fig, ax = plt.subplots(figsize=(6, 6))
    _segments(ax, traversal.walls, "k", 1.5)
    distractors = np.asarray(traversal.metadata.get("distractor_segments") or np.zeros((0, 4)))
    _segments(ax, distractors.reshape(-1, 4), "tab:red", 1.0)
    points = poses[:, None, :2]
    path = LineCollection(np.concatenate([points[:-1], points[1:]], 1), cmap="viridis", lw=1.0)
    path.set_array(np.arange(len(poses) - 1))
    ax.add_collection(path)
    fig.colorbar(path, ax=ax, fraction=0.046, pad=0.04, label="time step")
    x, y, h = poses[t]
    ranges = np.asarray(traversal.observations[t], dtype=np.float64)  # [B]
    angles = h + traversal.beam_angles
    ends = np.stack([x + ranges * np.cos(angles), y + ranges * np.sin(angles)], -1)
    rays = np.stack([np.broadcast_to([x, y], ends.shape), ends], 1)  # [B, 2, 2]
    ax.add_collection(LineCollection(rays, colors="tab:orange", lw=0.7))
    hit = ranges < traversal.max_range
    ax.plot(ends[hit, 0], ends[hit, 1], ".", color="tab:orange", ms=4)
    ax.plot([x], [y], "o", color="tab:red", ms=4)
    ax.set_aspect("equal")
    ax.autoscale()
    name = traversal.metadata.get("maze", {}).get("name", "")
    ax.set_title(f"{name} traversal, T={len(poses)}, scan at t={t}")
    path_png = Path(path_png)
    buf = io.BytesIO()
    fig.savefig(buf, dpi=120, bbox_inches="tight", format="png")
    plt.close(fig)
    atomic_write(path_png, lambda f: f.write(buf.getvalue()))
    return path_png


def _segments(ax, segments: np.ndarray, color: str, lw: float) -> None:
    if len(segments):
        ax.add_collection(LineCollection(segments.reshape(-1, 2, 2), colors=color, lw=lw))
