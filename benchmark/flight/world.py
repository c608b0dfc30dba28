"""The truth of a scene: its obstacles as analytic primitives, clearance and swept collisions.

A :class:`World` holds the primitives of a :class:`~stillbox_gen.scene.SceneSpec` with the
renderer's conventions (stillbox_gen/blender/build.py): a primitive's mesh is
:func:`stillbox_gen.shapes.mesh` of its ``kind`` and ``dimensions`` in its local frame, placed
by ``world = R(rotation) @ local + location``; the walls are the inside of the axis-aligned box
of half-extents ``half_extents`` around ``center``. Distances are the exact signed distances of
:func:`stillbox_gen.shapes.signed_distance` (the rendered curved meshes are inscribed in them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stillbox_gen import camera, shapes
from stillbox_gen.record import SceneSpec

#: Metres: largest spacing of the samples along a swept segment (smaller for a small radius).
MAX_SWEEP_SPACING = 0.05
#: Metres: spacing used for a point (radius 0), where a surface of no thickness could be missed.
POINT_SWEEP_SPACING = 0.005


@dataclass(frozen=True)
class Obstacle:
    """One primitive: ``kind`` and ``dimensions`` (dx, dy, dz) as in shapes.py, ``location``
    (world, m) and ``rotation`` (3x3, local -> world)."""

    kind: str
    dimensions: np.ndarray
    location: np.ndarray
    rotation: np.ndarray

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (m, < 0 inside) of world points (N, 3)."""
        local = (points - self.location) @ self.rotation  # R^T (p - t), row by row
        return shapes.signed_distance(self.kind, self.dimensions, local)

    @property
    def bounding_radius(self) -> float:
        """Radius (m) of a sphere around ``location`` that holds the whole primitive."""
        return float(np.linalg.norm(self.dimensions) / 2)


@dataclass(frozen=True)
class SweptResult:
    """Along a segment: ``min_clearance`` (m, of the sphere's surface; < 0 inside something),
    ``collided`` (some sample within the radius) and ``first_hit`` (fraction of the segment at
    the first such sample, None if none)."""

    min_clearance: float
    collided: bool
    first_hit: float | None


@dataclass(frozen=True)
class World:
    """Obstacles and walls of one scene (world frame, +Z up, metres)."""

    obstacles: tuple[Obstacle, ...]
    box_center: np.ndarray
    box_half_extents: np.ndarray

    @staticmethod
    def from_scene(scene: SceneSpec) -> World:
        """The primitives and walls of a sampled scene."""
        obstacles = tuple(
            Obstacle(
                p.kind,
                np.asarray(p.dimensions, float),
                np.asarray(p.location, float),
                camera.quat_to_matrix(p.rotation),
            )
            for p in scene.primitives
        )
        box = scene.box
        return World(obstacles, np.asarray(box.center, float), np.asarray(box.half_extents, float))

    def wall_clearance(self, points: np.ndarray) -> np.ndarray:
        """Distance (m) from points (N, 3) to the nearest wall, < 0 outside the box."""
        return -shapes.signed_distance("cube", 2 * self.box_half_extents, points - self.box_center)

    def clearance(self, points: np.ndarray, radius: float = 0.0) -> np.ndarray:
        """Signed clearance (m) of spheres of ``radius`` centred at points (N, 3): distance from
        the sphere's surface to the nearest obstacle or wall, < 0 when they overlap."""
        points = np.atleast_2d(np.asarray(points, float))
        best = self.wall_clearance(points)
        for obstacle in self.obstacles:
            best = np.minimum(best, obstacle.signed_distance(points))
        return best - radius

    def swept(self, a: np.ndarray, b: np.ndarray, radius: float) -> SweptResult:
        """A sphere of ``radius`` moved in a straight line from a to b (world, m).

        Samples lie at most h = min(MAX_SWEEP_SPACING, radius) apart (POINT_SWEEP_SPACING for
        radius 0), so no step tunnels through an object: every position of the segment is
        within h/2 of a sample, and distances are 1-Lipschitz, so a position touching an
        object (clearance < 0) has a sample of clearance < h/2 <= radius, i.e. in collision."""
        a, b = np.asarray(a, float), np.asarray(b, float)
        spacing = min(MAX_SWEEP_SPACING, radius) if radius > 0 else POINT_SWEEP_SPACING
        n = max(2, int(np.ceil(np.linalg.norm(b - a) / spacing)) + 1)
        t = np.linspace(0.0, 1.0, n)
        c = self.clearance(a + t[:, None] * (b - a), radius)
        hits = np.flatnonzero(c < 0)
        first = float(t[hits[0]]) if len(hits) else None
        return SweptResult(float(c.min()), bool(len(hits)), first)
