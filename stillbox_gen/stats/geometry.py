"""Scene geometry of ``stillbox-gen stats``: where each pixel's ray leaves the box of walls,
which pixels are walls, the true flow of a frame pair and the photometric residuals after
warping with it. Pixel rays and projection are stillbox_gen.camera's."""

from __future__ import annotations

import numpy as np

from ..camera import pixel_grid, pixel_rays, project

WALL_RTOL = 1e-3  # wall test: |depth - box depth| <= WALL_RTOL * box depth + WALL_ATOL
WALL_ATOL = 1e-3  # metres
OCCLUSION_RTOL = 0.02  # visible in frame j: |depth_j(p') - z_j| <= OCCLUSION_RTOL * z_j


def box_depth(
    K: np.ndarray,
    cam2world: np.ndarray,
    center: np.ndarray,
    half_extents: np.ndarray,
    width: int,
    height: int,
) -> np.ndarray:
    """Planar depth (H, W), metres, at which each pixel's ray leaves an axis-aligned box.

    ``cam2world`` is the OpenCV camera-to-world 4x4 pose, ``center`` and ``half_extents`` the
    box in world metres. The camera is assumed inside the box, so the ray's exit distance is
    ``t = min over axes of (face - origin) / direction``; with the direction ``K^-1 [u, v, 1]``
    (z = 1 in camera axes), t is also the planar depth.
    """
    m = np.asarray(cam2world, dtype=np.float64)
    c, h = np.asarray(center, dtype=np.float64), np.asarray(half_extents, dtype=np.float64)
    d = pixel_rays(K, width, height) @ m[:3, :3].T  # world directions, (H, W, 3)
    o = m[:3, 3]
    face = np.where(d > 0, c + h, c - h)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d != 0, (face - o) / d, np.inf)
    return t.min(axis=-1)


def wall_mask(depth: np.ndarray, wall_depth: np.ndarray) -> np.ndarray:
    """Boolean (H, W): pixels whose depth (metres) is the box's, within WALL_RTOL + WALL_ATOL."""
    return np.abs(depth - wall_depth) <= WALL_RTOL * np.abs(wall_depth) + WALL_ATOL


def true_flow(
    depth_i: np.ndarray, K: np.ndarray, cam2world_i: np.ndarray, cam2world_j: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Where frame i's pixels land in frame j: (flow (H, W, 2) in pixels, z_j (H, W) in metres).

    Each pixel is back-projected with its planar depth (metres), moved into frame j's camera by
    ``inv(cam2world_j) @ cam2world_i`` and projected with K; ``flow[..., 0]`` is horizontal (x),
    ``flow[..., 1]`` vertical (y), and ``z_j`` the point's planar depth in frame j. Pixels whose
    point is not in front of camera j (z_j <= 0) get NaN flow.
    """
    K = np.asarray(K, dtype=np.float64)
    h, w = depth_i.shape
    pts = pixel_rays(K, w, h) * depth_i.astype(np.float64)[..., None]  # camera i, metres
    rel = np.linalg.inv(np.asarray(cam2world_j, dtype=np.float64)) @ np.asarray(
        cam2world_i, dtype=np.float64
    )
    pj = pts @ rel[:3, :3].T + rel[:3, 3]
    z = pj[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = project(pj, K)
    xy[z <= 0] = np.nan
    u, v = pixel_grid(w, h)
    return xy - np.stack([u, v], axis=-1), z


def warp_residuals(
    img_i: np.ndarray,
    img_j: np.ndarray,
    depth_j: np.ndarray,
    flow: np.ndarray,
    z_j: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel photometric residuals of a pair, in grey levels (0-255), on frame i's grid.

    Returns ``(unwarped, warped, valid)``: ``|I_j - I_i|`` and ``|I_j(p + flow) - I_i(p)|``
    (I_j sampled bilinearly), each averaged over the channels, and the boolean mask where the
    warped value is meaningful: the point is in front of camera j, lands inside frame j
    (0 <= x <= W - 1, 0 <= y <= H - 1) and is not occluded there (depth_j, bilinearly
    sampled, within OCCLUSION_RTOL of z_j).
    """
    import cv2

    a = img_i.astype(np.float32)
    b = img_j.astype(np.float32)
    unwarped = np.abs(b - a).reshape(*a.shape[:2], -1).mean(axis=-1)
    h, w = depth_j.shape
    u, v = pixel_grid(w, h)
    x, y = u + flow[..., 0], v + flow[..., 1]
    valid = np.isfinite(x) & np.isfinite(y) & (z_j > 0)
    valid &= (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    mx = np.where(valid, x, -1).astype(np.float32)
    my = np.where(valid, y, -1).astype(np.float32)
    sampled = cv2.remap(b, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    dj = cv2.remap(
        depth_j.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    valid &= np.abs(dj - z_j) <= OCCLUSION_RTOL * np.abs(z_j)
    warped = np.abs(sampled - a).reshape(*a.shape[:2], -1).mean(axis=-1)
    return unwarped, warped, valid
