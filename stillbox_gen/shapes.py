"""Primitive shapes: conventions, distance functions and triangle meshes (pure numpy).

Every primitive is described by ``kind`` and ``dimensions`` = its axis-aligned bounding box
(dx, dy, dz) in metres in its own local frame, centred on the local origin:

* cube, slab: a box of those dimensions.
* sphere: a sphere of diameter dx (dx = dy = dz).
* cylinder: axis local z, radius dx / 2, height dz.
* cone: axis local z, base of radius dx / 2 at z = -dz/2, apex at z = +dz/2.
* torus: around local z, major radius R = (dx - dz) / 2, minor radius r = dz / 2.
* plane: the rectangle dx by dy in the local xy plane (dz = 0), facing local +z; it has no
  inside (its signed distance is never negative). One two-sided polygon.

The signed distances are exact (negative inside), except that the rendered meshes are inscribed
polyhedra of the curved shapes, so a point the function calls outside is outside the mesh too.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from . import portable


def _box2d(p: np.ndarray, half: np.ndarray) -> np.ndarray:
    q = np.abs(p) - half
    outside = portable.row_norms(np.maximum(q, 0.0))
    inside = np.minimum(q.max(axis=-1), 0.0)
    return outside + inside


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(portable.transform_rows([ab], p - a)[:, 0] / portable.dot(ab, ab), 0.0, 1.0)
    return portable.row_norms(p - (a + t[:, None] * ab))


def _cone2d(rho: np.ndarray, z: np.ndarray, r: float, h: float) -> np.ndarray:
    """Signed distance in the (rho, z) half-plane to the triangle (0,-h/2), (r,-h/2), (0,h/2)."""
    p = np.stack([rho, z], axis=-1)
    a, b, c = np.array([0.0, -h / 2]), np.array([r, -h / 2]), np.array([0.0, h / 2])
    # the axis edge (c, a) is not a surface: with rho >= 0 the base or the slant is always nearer
    d = np.minimum(_segment_distance(p, a, b), _segment_distance(p, b, c))
    # inside: above the base, left of the slanted edge (rho >= 0 always)
    inside = (z >= -h / 2) & (rho * h + (z - h / 2) * r <= 0)
    return np.where(inside, -d, d)


def signed_distance(kind: str, dimensions: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Signed distance (metres, < 0 inside) from local-frame points p (N, 3) to the shape."""
    dx, dy, dz = (float(v) for v in dimensions)
    if kind in ("cube", "slab", "plane"):  # a plane: a box of no thickness, nothing inside
        return _box2d(p, np.array([dx, dy, dz]) / 2)
    if kind == "sphere":
        return portable.row_norms(p) - dx / 2
    rho = portable.row_norms(p[:, :2])
    if kind == "cylinder":
        return _box2d(np.stack([rho, p[:, 2]], axis=-1), np.array([dx / 2, dz / 2]))
    if kind == "cone":
        return _cone2d(rho, p[:, 2], dx / 2, dz)
    if kind == "torus":
        major, minor = (dx - dz) / 2, dz / 2
        return portable.row_norms(np.stack([rho - major, p[:, 2]], axis=-1)) - minor
    raise ValueError(f"unknown primitive kind {kind!r}")


# ---------------------------------------------------------------- meshes


def _grid_faces(rows: int, cols: int, wrap_rows: bool) -> list[tuple[int, ...]]:
    faces = []
    for i in range(rows if wrap_rows else rows - 1):
        for j in range(cols):
            a, b = i * cols + j, i * cols + (j + 1) % cols
            c, d = ((i + 1) % rows) * cols + (j + 1) % cols, ((i + 1) % rows) * cols + j
            faces.append((a, b, c, d))
    return faces


@functools.cache
def _faces(kind: str, n: int) -> tuple[tuple[int, ...], ...]:
    """Faces of a primitive's mesh with ``n`` segments (they do not depend on its dimensions)."""
    if kind in ("cube", "slab"):
        return ((0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3))
    if kind == "plane":
        return ((0, 1, 3, 2),)
    if kind == "sphere":
        rings = n // 2
        body = [tuple(1 + k for k in f) for f in _grid_faces(rings - 1, n, False)]
        last, top_pole = 1 + (rings - 2) * n, 2 + (rings - 1) * n - 1
        bottom = [(0, 1 + (j + 1) % n, 1 + j) for j in range(n)]
        top = [(top_pole, last + j, last + (j + 1) % n) for j in range(n)]
        return tuple(bottom + body + top)
    if kind == "cylinder":
        sides = [(j, (j + 1) % n, n + (j + 1) % n, n + j) for j in range(n)]
        return tuple(sides + [tuple(range(n - 1, -1, -1)), tuple(range(n, 2 * n))])
    if kind == "cone":
        return tuple([(j, (j + 1) % n, n) for j in range(n)] + [tuple(range(n - 1, -1, -1))])
    if kind == "torus":
        return tuple((a, d, c, b) for a, b, c, d in _grid_faces(n, max(8, n // 2), True))
    raise ValueError(f"unknown primitive kind {kind!r}")


@functools.cache
def _unit_circle(n: int) -> np.ndarray:
    """(cos, sin) of the angles 2 pi j / n, j = 0 .. n-1, (n, 2): the same bits on every CPU
    (numpy's own cos and sin depend on the SIMD level)."""
    angles = [2.0 * math.pi * j / n for j in range(n)]
    return np.array([[portable.cos(a), portable.sin(a)] for a in angles])


def mesh(kind: str, dimensions, segments: int = 32) -> tuple[np.ndarray, list[tuple[int, ...]]]:
    """Vertices (N, 3) in metres and polygon faces (outward, counter-clockwise) of a primitive."""
    dx, dy, dz = (float(v) for v in dimensions)
    n = segments
    faces = list(_faces(kind, n))
    ring = _unit_circle(n)
    if kind in ("cube", "slab"):
        v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        return v * np.array([dx, dy, dz]) / 2, faces
    if kind == "plane":  # corners (-,-), (+,-), (-,+), (+,+): face (0, 1, 3, 2) faces +z
        v = np.array([[x, y, 0.0] for y in (-1, 1) for x in (-1, 1)], float)
        return v * np.array([dx, dy, 0.0]) / 2, faces
    if kind == "sphere":
        # polar angles pi - 2 pi j / n, j = 1 .. n/2 - 1, bottom ring first: -cos, sin of the circle
        cos_t, sin_t = -ring[1 : n // 2, 0][:, None], ring[1 : n // 2, 1][:, None]
        rings = np.stack([sin_t * ring[:, 0], sin_t * ring[:, 1], np.repeat(cos_t, n, 1)], -1)
        v = np.vstack([[[0.0, 0.0, -1.0]], rings.reshape(-1, 3), [[0.0, 0.0, 1.0]]])
        return v * dx / 2, faces
    if kind in ("cylinder", "cone"):
        r, h = dx / 2, dz
        base = np.column_stack([ring * r, np.full(n, -h / 2)])
        if kind == "cylinder":
            return np.vstack([base, np.column_stack([ring * r, np.full(n, h / 2)])]), faces
        return np.vstack([base, [[0, 0, h / 2]]]), faces
    if kind == "torus":
        major, minor = (dx - dz) / 2, dz / 2
        minor_ring = _unit_circle(max(8, n // 2))
        arm = (major + minor * minor_ring[:, 0])[None, :]  # distance from the axis, per angle
        z = np.broadcast_to(minor * minor_ring[:, 1], (n, len(minor_ring)))
        v = np.stack([arm * ring[:, :1], arm * ring[:, 1:], z], -1)
        return v.reshape(-1, 3), faces
    raise ValueError(f"unknown primitive kind {kind!r}")
