"""Obstacle points from a depth map: the controller's only view of the scene.

A planar depth map (H, W) in metres (distance along the optical axis, as the renderer's Z pass
and every depth network here), the intrinsics K (pixels, OpenCV pixel centres) and the camera's
OpenCV camera-to-world pose give 3-D points: in the camera frame (x right, y down, z forward)
and in the world frame (+Z up). Pixels are taken every ``stride`` rows and columns; depths that
are not finite, not positive or beyond ``max_range`` (misses, sky, the far saturation of a
network) are no obstacle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stillbox_gen import camera

from ..core.metrics import SENSING_RANGE


@dataclass(frozen=True)
class SensingConfig:
    """``max_range`` (m): farther depths are ignored; ``stride`` (pixels) between samples;
    ``voxel`` (m): the memory keeps one point per cube of this side; ``keyframes``: how many
    past frames' points are kept, a frame being kept when the camera has moved
    ``keyframe_spacing`` (m) since the last kept one (the camera looks ahead only: obstacles
    being passed leave its view, and a drone at rest must not forget what it saw coming)."""

    max_range: float = SENSING_RANGE
    stride: int = 2
    voxel: float = 0.2
    keyframes: int = 20
    keyframe_spacing: float = 0.3


def camera_points(depth: np.ndarray, K: np.ndarray, stride: int, max_range: float) -> np.ndarray:
    """Points (N, 3) in the camera frame (m) of the sampled pixels with 0 < depth <= max_range."""
    d = np.asarray(depth, float)
    pts = camera.backproject(d, np.asarray(K, float))[::stride, ::stride].reshape(-1, 3)
    z = pts[:, 2]
    return pts[np.isfinite(z) & (z > 0) & (z <= max_range)]


def to_world(points_cam: np.ndarray, cam2world: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) in the world frame: R p + t."""
    return points_cam @ cam2world[:3, :3].T + cam2world[:3, 3]


def voxel_filter(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point (the first) per occupied cube of side ``voxel`` metres."""
    if len(points) == 0:
        return points
    keys = np.floor(points / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return points[np.sort(first)]


class PointMemory:
    """World points of the current frame and of the last ``cfg.keyframes`` keyframes."""

    def __init__(self, cfg: SensingConfig) -> None:
        self.cfg = cfg
        self.keyframes: list[tuple[np.ndarray, np.ndarray]] = []  # (camera position, points)
        self.current = np.empty((0, 3))

    def add(self, depth: np.ndarray, K: np.ndarray, cam2world: np.ndarray) -> np.ndarray:
        """Adds a frame's points; returns them (world, (N, 3))."""
        pts = camera_points(depth, K, self.cfg.stride, self.cfg.max_range)
        self.current = voxel_filter(to_world(pts, cam2world), self.cfg.voxel)
        position = cam2world[:3, 3]
        last = self.keyframes[-1][0] if self.keyframes else None
        if last is None or np.linalg.norm(position - last) >= self.cfg.keyframe_spacing:
            self.keyframes = [*self.keyframes, (position, self.current)][-self.cfg.keyframes :]
        return self.current

    def points(self) -> np.ndarray:
        """Every kept point (world, (N, 3))."""
        return voxel_filter(
            np.concatenate([self.current, *(p for _, p in self.keyframes)]), self.cfg.voxel
        )
