"""Primitive shapes: conventions, distance functions and triangle meshes (pure numpy).

Every primitive is described by ``kind`` and ``dimensions`` = its axis-aligned bounding box
(dx, dy, dz) in metres in its own local frame, centred on the local origin:

* cube, slab: a box of those dimensions.
* sphere: a sphere of diameter dx (dx = dy = dz).
* cylinder: axis local z, radius dx / 2, height dz.
* cone: axis local z, base of radius dx / 2 at z = -dz/2, apex at z = +dz/2.
* torus: around local z, major radius R = (dx - dz) / 2, minor radius r = dz / 2.

The signed distances are exact (negative inside), except that the rendered meshes are inscribed
polyhedra of the curved shapes, so a point the function calls outside is outside the mesh too.
"""

from __future__ import annotations

import numpy as np


def _box2d(p: np.ndarray, half: np.ndarray) -> np.ndarray:
    q = np.abs(p) - half
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    inside = np.minimum(q.max(axis=-1), 0.0)
    return outside + inside


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=-1)


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
    if kind in ("cube", "slab"):
        return _box2d(p, np.array([dx, dy, dz]) / 2)
    if kind == "sphere":
        return np.linalg.norm(p, axis=-1) - dx / 2
    rho = np.linalg.norm(p[:, :2], axis=-1)
    if kind == "cylinder":
        return _box2d(np.stack([rho, p[:, 2]], axis=-1), np.array([dx / 2, dz / 2]))
    if kind == "cone":
        return _cone2d(rho, p[:, 2], dx / 2, dz)
    if kind == "torus":
        major, minor = (dx - dz) / 2, dz / 2
        return np.hypot(rho - major, p[:, 2]) - minor
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


def mesh(kind: str, dimensions, segments: int = 32) -> tuple[np.ndarray, list[tuple[int, ...]]]:
    """Vertices (N, 3) in metres and polygon faces (outward, counter-clockwise) of a primitive."""
    dx, dy, dz = (float(v) for v in dimensions)
    n = segments
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=-1)
    if kind in ("cube", "slab"):
        v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        return v * np.array([dx, dy, dz]) / 2, faces
    if kind == "sphere":
        rings = n // 2
        theta = np.linspace(0, np.pi, rings + 1)[1:-1]
        v = [[0, 0, -1]]
        for t in theta[::-1]:
            v += [[np.sin(t) * c, np.sin(t) * s, np.cos(t)] for c, s in ring]
        v += [[0, 0, 1]]
        v = np.array(v) * dx / 2
        body = [tuple(1 + k for k in f) for f in _grid_faces(rings - 1, n, False)]
        last = 1 + (rings - 2) * n
        bottom = [(0, 1 + (j + 1) % n, 1 + j) for j in range(n)]
        top = [(len(v) - 1, last + j, last + (j + 1) % n) for j in range(n)]
        return v, bottom + body + top
    if kind in ("cylinder", "cone"):
        r, h = dx / 2, dz
        base = np.column_stack([ring * r, np.full(n, -h / 2)])
        if kind == "cylinder":
            top = np.column_stack([ring * r, np.full(n, h / 2)])
            v = np.vstack([base, top])
            sides = [(j, (j + 1) % n, n + (j + 1) % n, n + j) for j in range(n)]
            return v, sides + [tuple(range(n - 1, -1, -1)), tuple(range(n, 2 * n))]
        v = np.vstack([base, [[0, 0, h / 2]]])
        sides = [(j, (j + 1) % n, n) for j in range(n)]
        return v, sides + [tuple(range(n - 1, -1, -1))]
    if kind == "torus":
        major, minor = (dx - dz) / 2, dz / 2
        m = max(8, n // 2)
        phi = np.linspace(0, 2 * np.pi, m, endpoint=False)
        v = [
            [(major + minor * np.cos(p)) * c, (major + minor * np.cos(p)) * s, minor * np.sin(p)]
            for c, s in ring
            for p in phi
        ]
        faces = [(a, d, c, b) for a, b, c, d in _grid_faces(n, m, True)]
        return np.array(v), faces
    raise ValueError(f"unknown primitive kind {kind!r}")
