"""An analytic depth renderer of a World, without Blender: closes the loop in tests.

Rays through the pixel centres of K (OpenCV) from the camera pose meet the walls exactly (the
exit of the axis-aligned box) and the primitives by sphere tracing on their exact signed
distances (shapes.py), which supports every primitive kind. Depth is planar (along the optical
axis, as Cycles' Z pass); a ray that meets nothing within ``max_distance`` gets MISS_DEPTH.
A ray stops within HIT_TOLERANCE of a surface: exact to that but at the silhouette of a curved
surface of radius R, where a grazing ray stops up to sqrt(2 R HIT_TOLERANCE) early (nearer).
"""

from __future__ import annotations

import numpy as np

from .world import World

MISS_DEPTH = 1e10  # metres, what Cycles returns for a miss
HIT_TOLERANCE = 1e-3  # metres: a ray stops this near a surface
MAX_ITERATIONS = 200


def pixel_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Camera-frame directions (H, W, 3) through the pixel centres, with z = 1."""
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)


def box_exit(world: World, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Ray length (in units of dirs) to the walls from origins inside the box, (N,)."""
    lo = world.box_center - world.box_half_extents
    hi = world.box_center + world.box_half_extents
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(
            dirs > 0, (hi - origins) / dirs, np.where(dirs < 0, (lo - origins) / dirs, np.inf)
        )
    return t.min(axis=1)


def bounding_hits(world: World, origin: np.ndarray, unit: np.ndarray) -> np.ndarray:
    """(N, M) bool: ray n (unit direction) meets the bounding sphere of primitive m ahead."""
    out = np.zeros((len(unit), len(world.obstacles)), bool)
    for m, obstacle in enumerate(world.obstacles):
        oc = obstacle.location - origin
        along = unit @ oc
        miss2 = (oc @ oc) - along**2  # squared distance from the centre to the ray's line
        r = obstacle.bounding_radius
        out[:, m] = (miss2 <= r * r) & (along + r >= 0)
    return out


def primitive_distance(world: World, points: np.ndarray, near: np.ndarray) -> np.ndarray:
    """Least signed distance (m) from points (N, 3) to the primitives whose bounding sphere
    their ray meets (``near`` (N, M)); inf for none. Leaving the others out is safe: the ray
    never enters them, so a step past their distance cannot cross them."""
    best = np.full(len(points), np.inf)
    for m, obstacle in enumerate(world.obstacles):
        sel = np.flatnonzero(near[:, m])
        if len(sel):
            best[sel] = np.minimum(best[sel], obstacle.signed_distance(points[sel]))
    return best


def render_depth(
    world: World,
    K: np.ndarray,
    width: int,
    height: int,
    cam2world: np.ndarray,
    max_distance: float = 200.0,
) -> np.ndarray:
    """Planar depth (H, W) float32 in metres seen from the OpenCV pose ``cam2world``."""
    rays_cam = pixel_rays(np.asarray(K, float), width, height).reshape(-1, 3)
    dirs = rays_cam @ cam2world[:3, :3].T  # world, length |ray| with camera z = 1
    norms = np.linalg.norm(dirs, axis=1)
    unit = dirs / norms[:, None]
    origin = np.broadcast_to(cam2world[:3, 3], unit.shape)
    t_far = np.minimum(box_exit(world, origin, unit), max_distance * norms)  # metres along ray
    t = np.zeros(len(unit))
    active = np.ones(len(unit), bool)
    hit = np.zeros(len(unit), bool)
    near = bounding_hits(world, cam2world[:3, 3], unit)
    for _ in range(MAX_ITERATIONS):
        idx = np.flatnonzero(active)
        if len(idx) == 0:
            break
        d = primitive_distance(world, origin[idx] + t[idx, None] * unit[idx], near[idx])
        hit[idx[d < HIT_TOLERANCE]] = True
        t[idx] += np.maximum(d, 0.0)
        active[idx[(d < HIT_TOLERANCE) | (t[idx] >= t_far[idx])]] = False
    hit |= active  # still marching after MAX_ITERATIONS: grazing a surface
    t = np.where(hit, np.minimum(t, t_far), t_far)
    depth = t / norms  # planar: the camera-frame ray has z = 1
    seen = hit | (t_far < max_distance * norms)
    return (
        np.where(seen & (depth <= max_distance), depth, MISS_DEPTH)
        .reshape(height, width)
        .astype(np.float32)
    )


def shade(depth: np.ndarray) -> np.ndarray:
    """A grey RGB frame (H, W, 3) uint8, brighter nearer: a stand-in image for depth sources
    that ignore it."""
    grey = np.clip(255.0 * (1.0 - np.minimum(depth, 50.0) / 50.0), 0, 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=-1)
