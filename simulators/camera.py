"""First-person grayscale camera by ray casting (one ray per image column, "Wolfenstein" style).

Image rows run top to bottom, columns left to right; column ``c`` looks along
``heading + fov/2 - (c + 0.5) fov / width``. A wall at perpendicular depth ``d`` spans
``horizon - f (wall_height - eye_height) / d`` to ``horizon + f eye_height / d`` rows
(``f = (width / 2) / tan(fov / 2)`` pixels), so its image height is ~ 1/d. Pixels blend wall,
ceiling and floor by fractional row coverage. Walls are shaded by a fixed directional light
(so the four wall faces N/S/E/W differ in brightness) and dimmed with distance, as are floor and
ceiling; all values lie in [0, 1]. Heights are in corridor widths.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from simulators.raycast import raycast

_LIGHT = np.array([np.cos(np.pi / 3), np.sin(np.pi / 3)])  # unit light direction (world frame)
DISTRACTOR_ALBEDO = 0.95
CEILING_ALBEDO = 0.8
FLOOR_ALBEDO = 0.4


@dataclass(frozen=True)
class CameraConfig:
    width: int = 32
    height: int = 24
    fov: float = np.pi / 2
    wall_height: float = 1.0  # corridor widths
    eye_height: float = 0.5  # corridor widths
    fog: float = 2.0  # corridor widths; brightness ~ 1 / (1 + depth / (fog w))

    @property
    def focal(self) -> float:
        """Focal length in pixels."""
        return (self.width / 2) / np.tan(self.fov / 2)

    @property
    def column_offsets(self) -> np.ndarray:
        """Ray angle of each column relative to the heading, left to right ``[width]``."""
        return self.fov / 2 - (np.arange(self.width) + 0.5) * self.fov / self.width

    def to_dict(self) -> dict:
        return {
            k: float(v) if isinstance(v, float | np.floating) else v
            for k, v in asdict(self).items()
        }


def face_albedo(segments: np.ndarray) -> np.ndarray:
    """Lambert-like brightness of both faces of each segment ``[S, 4]`` -> ``[S, 2]``.

    Face 0 is the side the left normal ``(-ey, ex)`` points to, face 1 the other side.
    """
    e = segments[:, 2:] - segments[:, :2]
    n = np.stack([-e[:, 1], e[:, 0]], -1) / np.linalg.norm(e, axis=-1, keepdims=True)
    lit = n @ _LIGHT  # [S]
    return np.stack([0.55 + 0.35 * lit, 0.55 - 0.35 * lit], -1)


class Camera:
    """Renders images and depth of a set of segments (maze walls first, then distractors).

    Args:
        walls: maze wall segments ``[W, 4]``.
        corridor_width: world units per corridor width (sets heights and fog).
        distractors: extra segments ``[D, 4]`` drawn with a uniform bright albedo.
        config: image geometry.
    """

    def __init__(self, walls, corridor_width: float, distractors=None, config=CameraConfig()):  # noqa: B008
        walls = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
        distractors = np.zeros((0, 4)) if distractors is None else np.asarray(distractors)
        self.segments = np.concatenate([walls, distractors.reshape(-1, 4)])  # [S, 4]
        self.albedo = face_albedo(self.segments)  # [S, 2]
        self.albedo[len(walls) :] = DISTRACTOR_ALBEDO
        self.w = float(corridor_width)
        self.config = config
        lo, hi = self.segments.reshape(-1, 2).min(0), self.segments.reshape(-1, 2).max(0)
        self.max_range = 2.0 * float(np.linalg.norm(hi - lo)) + 1.0

    def _cast(self, poses):
        """Per-column perpendicular depth ``[N, C]``, hit segment ``[N, C]``, ray angles."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        offsets = self.config.column_offsets  # [C]
        angles = poses[:, 2:3] + offsets  # [N, C]
        dist, idx = raycast(self.segments, poses[:, :2], angles, self.max_range, return_index=True)
        return dist * np.cos(offsets), idx, angles

    def _row_geometry(self, depth):
        """Wall top / bottom rows ``[N, 1, C]`` and floor-or-ceiling depth per row ``[H, 1]``."""
        cfg = self.config
        f, h0 = cfg.focal, cfg.height / 2
        above, below = (cfg.wall_height - cfg.eye_height) * self.w, cfg.eye_height * self.w
        top = h0 - f * above / depth[:, None, :]
        bottom = h0 + f * below / depth[:, None, :]
        y = np.arange(cfg.height)[:, None] + 0.5 - h0  # [H, 1] pixel offset from horizon
        plane = np.where(y < 0, above, below) * f / np.abs(y)  # [H, 1] ceiling / floor depth
        return top, bottom, plane, y

    def column_depth(self, poses) -> np.ndarray:
        """Perpendicular (z-) depth of the wall seen in each column ``[N, C]``."""
        return self._cast(poses)[0]

    def depth(self, poses) -> np.ndarray:
        """Depth image ``[N, H, C]``: z-depth of walls, floor or ceiling seen by each pixel."""
        depth, _, _ = self._cast(poses)
        top, bottom, plane, _ = self._row_geometry(depth)
        rows = np.arange(self.config.height)[:, None] + 0.5  # [H, 1] row centres
        on_wall = (rows >= top) & (rows <= bottom)  # [N, H, C]
        return np.where(on_wall, depth[:, None, :], plane)

    def render(self, poses) -> np.ndarray:
        """Grayscale images ``[N, H, C]`` in [0, 1] for poses ``[N, 3]`` (or one pose ``[3]``)."""
        depth, idx, angles = self._cast(poses)
        top, bottom, plane, y = self._row_geometry(depth)
        rows = np.arange(self.config.height)[:, None]  # [H, 1]
        coverage = np.clip(np.minimum(rows + 1, bottom) - np.maximum(rows, top), 0.0, 1.0)
        fog = self.config.fog * self.w
        wall = self._wall_albedo(idx, angles) / (1.0 + depth / fog)  # [N, C]
        background = np.where(y < 0, CEILING_ALBEDO, FLOOR_ALBEDO) / (1.0 + plane / fog)  # [H, 1]
        img = coverage * wall[:, None, :] + (1.0 - coverage) * background
        return np.clip(img, 0.0, 1.0).astype(np.float32)

    def _wall_albedo(self, idx, angles) -> np.ndarray:
        """Albedo of the face each ray hits ``[N, C]``; faces are told apart by the ray side."""
        seg = self.segments[idx]  # [N, C, 4]
        ex, ey = seg[..., 2] - seg[..., 0], seg[..., 3] - seg[..., 1]
        # The ray sees face 0 (left normal side) when it travels against the left normal.
        face = (np.cos(angles) * -ey + np.sin(angles) * ex > 0).astype(np.int64)
        return np.take_along_axis(self.albedo[idx], face[..., None], -1)[..., 0]
