"""benchmark/flight/obstacles.py: depth maps of a plane and a sphere, computed analytically,
give points on that plane and sphere, in the camera frame and in the world."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmark.flight.dynamics import camera_pose
from benchmark.flight.obstacles import (
    PointMemory,
    SensingConfig,
    camera_points,
    to_world,
    voxel_filter,
)

W = H = 32
F = 16.0  # 90 deg FOV at 32 px
K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1]])


def pixel_grid():
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    return (u - K[0, 2]) / F, (v - K[1, 2]) / F  # ray (x, y, 1) per pixel


def sphere_depth(centre: np.ndarray, radius: float) -> np.ndarray:
    """Planar depth of a sphere (camera frame): nearest root s of |s d - c| = r, d = (x, y, 1);
    the planar depth is s itself (d has z = 1). Misses at 1e10."""
    x, y = pixel_grid()
    d = np.stack([x, y, np.ones_like(x)], -1)
    a = (d * d).sum(-1)
    b = -2 * (d @ centre)
    c = centre @ centre - radius**2
    disc = b * b - 4 * a * c
    s = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
    return np.where(disc >= 0, s, 1e10)


def test_a_fronto_parallel_plane_gives_points_on_it():
    depth = np.full((H, W), 7.0)
    pts = camera_points(depth, K, stride=1, max_range=15.0)
    assert len(pts) == H * W
    assert pts[:, 2] == pytest.approx(7.0)
    x, _ = pixel_grid()
    assert pts[:, 0] == pytest.approx((x * 7.0).ravel())
    assert np.abs(pts[:, 0]).max() == pytest.approx(7.0 * 15.5 / 16)  # 90 deg: |x| <= z


def test_depth_beyond_the_range_or_invalid_is_no_obstacle():
    depth = np.full((H, W), 7.0)
    depth[:, : W // 2] = 20.0  # beyond 15 m
    depth[0, -1], depth[1, -1], depth[2, -1] = np.nan, 0.0, np.inf
    pts = camera_points(depth, K, stride=1, max_range=15.0)
    assert len(pts) == H * W // 2 - 3
    assert (pts[:, 0] > 0).all()  # only the right half
    # every other row and column: columns 16, 18, ..., 30 (the invalid column 31 is skipped)
    assert len(camera_points(depth, K, stride=2, max_range=15.0)) == (H // 2) * (W // 4)


def test_a_sphere_seen_from_a_turned_camera_gives_world_points_on_it():
    """Sphere of radius 2 m at 10 m ahead of a level camera at (1, 2, 3), yaw 30 deg."""
    yaw = math.radians(30)
    pose = camera_pose(np.array([1.0, 2.0, 3.0]), yaw)
    centre_cam = np.array([1.0, -0.5, 10.0])
    depth = sphere_depth(centre_cam, 2.0)
    pts_cam = camera_points(depth, K, stride=1, max_range=15.0)
    assert len(pts_cam) > 20  # about pi (16 * 2 / 10)^2 pixels
    assert np.linalg.norm(pts_cam - centre_cam, axis=1) == pytest.approx(2.0)
    world = to_world(pts_cam, pose)
    centre_world = pose[:3, :3] @ centre_cam + pose[:3, 3]
    # by hand: forward (cos, sin, 0) * 10, right (sin, -cos, 0) * 1, down (0, 0, -1) * -0.5
    c, s = math.cos(yaw), math.sin(yaw)
    assert centre_world == pytest.approx([1 + 10 * c + s, 2 + 10 * s - c, 3.5])
    assert np.linalg.norm(world - centre_world, axis=1) == pytest.approx(2.0)


def test_voxel_filter_keeps_one_point_per_cube():
    pts = np.array([[0.01, 0.01, 0.01], [0.05, 0.05, 0.05], [0.5, 0, 0], [-0.01, 0, 0]])
    kept = voxel_filter(pts, 0.2)
    assert kept.tolist() == [pts[0].tolist(), pts[2].tolist(), pts[3].tolist()]


def test_memory_keeps_keyframes_by_distance_moved():
    """Keyframes every 0.3 m at most 2 kept, plus the current frame; at rest, frames seen
    while coming are not forgotten. The wall at depth d from x is at world x + d (yaw 0)."""
    mem = PointMemory(SensingConfig(stride=4, keyframes=2, keyframe_spacing=0.3))

    def wall_xs():
        return np.unique(np.round(mem.points()[:, 0], 6)).tolist()

    for x, d in [(0.0, 3.0), (0.1, 4.9), (0.5, 5.5), (1.0, 8.0)]:
        mem.add(np.full((H, W), d), K, camera_pose(np.array([x, 0.0, 0.0]), 0.0))
    # keyframes at x = 0 (wall 3), 0.5 (wall 6), 1.0 (wall 9): the first dropped; 0.1 not kept
    assert wall_xs() == [6.0, 9.0]
    for _ in range(30):  # at rest, seeing a wall at 10
        mem.add(np.full((H, W), 9.0), K, camera_pose(np.array([1.0, 0.0, 0.0]), 0.0))
    assert wall_xs() == [6.0, 9.0, 10.0]
