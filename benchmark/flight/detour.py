"""The controller's cost-to-go: the length of a short way to the goal around the seen points.

From a position x (world, m) the way is straight to the goal when the segment x-goal keeps
``corridor`` metres from every obstacle point; else through one via-point: a point beside the
nearest obstacle point across the straight line (from the drone to the goal), offset sideways
(horizontally, across that line) or vertically by a few metres, such that x-via and via-goal
both keep clear. Length |x - via| + |via - goal|; with no clear way, |x - goal| + BLOCKED (m).
A cheap stand-in for a path planner: it ranks the controller's candidates by which side of an
obstacle leads on to the goal, beyond the horizon.
"""

from __future__ import annotations

import numpy as np

BLOCKED = 30.0  # metres added when neither the straight way nor a via-point is clear
LATERAL_OFFSETS = (2.0, 3.5, 5.0, 7.0, 9.0, 12.0)  # metres, on both sides
VERTICAL_OFFSETS = (2.0, 4.0)  # metres, above and below
CHUNK = 64  # segments per batch (memory: CHUNK x points x 3 floats)


def segment_distances(a: np.ndarray, b: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Least distance (m) from points (P, 3) to each segment a-b, a and b (S, 3); inf if P = 0."""
    out = np.full(len(a), np.inf)
    if len(points) == 0:
        return out
    for i in range(0, len(a), CHUNK):
        sa, sb = a[i : i + CHUNK, None], b[i : i + CHUNK, None]
        ab = sb - sa
        t = ((points[None] - sa) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12)
        near = sa + np.clip(t, 0.0, 1.0)[..., None] * ab
        out[i : i + CHUNK] = np.linalg.norm(points[None] - near, axis=-1).min(axis=1)
    return out


def via_points(position: np.ndarray, goal: np.ndarray, points: np.ndarray, corridor: float):
    """Via-points (V, 3) beside the nearest point within ``corridor`` of the segment
    position-goal, at that point's distance along it; (0, 3) when the segment is clear."""
    u = goal - position
    length = float(np.linalg.norm(u))
    if len(points) == 0 or length < 1e-9:
        return np.empty((0, 3))
    u = u / length
    along = (points - position) @ u
    lateral = np.linalg.norm(points - position - along[:, None] * u, axis=1)
    across = (along > 0) & (along < length) & (lateral <= corridor)
    if not across.any():
        return np.empty((0, 3))
    centre = position + along[across].min() * u
    side = np.cross(u, [0.0, 0.0, 1.0])
    side = side / max(float(np.linalg.norm(side)), 1e-9)
    up = np.cross(side, u)
    offsets = [s * o * side for o in LATERAL_OFFSETS for s in (-1, 1)]
    offsets += [s * o * up for o in VERTICAL_OFFSETS for s in (-1, 1)]
    return centre + np.array(offsets)


def cost_to_go(
    xs: np.ndarray, goal: np.ndarray, vias: np.ndarray, points: np.ndarray, corridor: float
) -> np.ndarray:
    """Length (m) of the shortest clear way from each of xs (C, 3) to the goal (see above)."""
    direct = np.linalg.norm(xs - goal, axis=1)
    best = np.where(
        segment_distances(xs, np.broadcast_to(goal, xs.shape), points) > corridor, direct, np.inf
    )
    if len(vias):
        goal_side = segment_distances(vias, np.broadcast_to(goal, vias.shape), points) > corridor
        for v, ok in zip(vias, goal_side, strict=True):
            if not ok:
                continue
            first = segment_distances(xs, np.broadcast_to(v, xs.shape), points) > corridor
            way = np.linalg.norm(xs - v, axis=1) + np.linalg.norm(v - goal)
            best = np.where(first, np.minimum(best, way), best)
    return np.where(np.isfinite(best), best, direct + BLOCKED)
