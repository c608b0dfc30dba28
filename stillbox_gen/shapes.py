"""Primitive shapes: one table, :data:`SHAPES`, holds everything the generator needs of a kind
(pure numpy; adding a shape is one entry there).

Every primitive is described by ``kind`` and ``dimensions`` = its axis-aligned bounding box
(dx, dy, dz) in metres in its own local frame, centred on the local origin. Each entry says what
its dimensions mean (``conventions``, the words of docs/FORMAT.md), its exact signed distance
(negative inside; the rejection test of overlapping or too-near objects), its triangle-or-polygon
mesh (what Blender renders), how random scenes draw its dimensions, and whether Blender shades
it smooth.

The signed distances are exact, except that the rendered meshes are inscribed polyhedra of the
curved shapes, so a point the function calls outside is outside the mesh too.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable

import numpy as np

from . import portable

Dims = tuple[float, float, float]  # (dx, dy, dz), metres
Faces = tuple[tuple[int, ...], ...]


@dataclasses.dataclass(frozen=True)
class Shape:
    """One primitive kind.

    ``conventions``: what (dx, dy, dz) mean; ``distance(d, p)``: signed distance (m, < 0 inside)
    from local points ``p`` (N, 3) to the shape of dimensions ``d``; ``vertices(d, n)``: its mesh
    vertices (V, 3) in metres with ``n`` segments around a curved axis; ``faces(n)``: the mesh's
    polygons (outward, counter-clockwise) as vertex indices, the same for any dimensions;
    ``draw(rng, size, a)``: the dimensions of a random one whose largest extent is ``size`` m
    (``a``: an aspect uniform in [0.5, 1) drawn before, for every kind, so that the order of
    draws does not depend on the kind); ``smooth``: Blender shades it smooth (keeping edges
    sharper than 45 degrees sharp) rather than flat; ``random``: random scenes draw it by
    default (config.PRIMITIVE_KINDS, the ``objects.kinds`` default)."""

    conventions: str
    distance: Callable[[Dims, np.ndarray], np.ndarray]
    vertices: Callable[[Dims, int], np.ndarray]
    faces: Callable[[int], Faces]
    draw: Callable[[np.random.Generator, float, float], list[float]]
    smooth: bool
    random: bool = True


# ---------------------------------------------------------------- distances


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


def _box_distance(d: Dims, p: np.ndarray) -> np.ndarray:
    """A box; a plane is a box of no thickness, with nothing inside."""
    return _box2d(p, np.array(d) / 2)


def _sphere_distance(d: Dims, p: np.ndarray) -> np.ndarray:
    return portable.row_norms(p) - d[0] / 2


def _cylinder_distance(d: Dims, p: np.ndarray) -> np.ndarray:
    rho = portable.row_norms(p[:, :2])
    return _box2d(np.stack([rho, p[:, 2]], axis=-1), np.array([d[0] / 2, d[2] / 2]))


def _cone_distance(d: Dims, p: np.ndarray) -> np.ndarray:
    return _cone2d(portable.row_norms(p[:, :2]), p[:, 2], d[0] / 2, d[2])


def _torus_distance(d: Dims, p: np.ndarray) -> np.ndarray:
    major, minor = (d[0] - d[2]) / 2, d[2] / 2
    rho = portable.row_norms(p[:, :2])
    return portable.row_norms(np.stack([rho - major, p[:, 2]], axis=-1)) - minor


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
def _unit_circle(n: int) -> np.ndarray:
    """(cos, sin) of the angles 2 pi j / n, j = 0 .. n-1, (n, 2): the same bits on every CPU
    (numpy's own cos and sin depend on the SIMD level)."""
    angles = [2.0 * math.pi * j / n for j in range(n)]
    return np.array([[portable.cos(a), portable.sin(a)] for a in angles])


def _box_faces(n: int) -> Faces:
    return ((0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3))


def _box_vertices(d: Dims, n: int) -> np.ndarray:
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    return v * np.array(d) / 2


def _plane_faces(n: int) -> Faces:
    return ((0, 1, 3, 2),)


def _plane_vertices(d: Dims, n: int) -> np.ndarray:
    """Corners (-,-), (+,-), (-,+), (+,+): face (0, 1, 3, 2) faces +z."""
    v = np.array([[x, y, 0.0] for y in (-1, 1) for x in (-1, 1)], float)
    return v * np.array([d[0], d[1], 0.0]) / 2


@functools.cache
def _sphere_faces(n: int) -> Faces:
    rings = n // 2
    body = [tuple(1 + k for k in f) for f in _grid_faces(rings - 1, n, False)]
    last, top_pole = 1 + (rings - 2) * n, 2 + (rings - 1) * n - 1
    bottom = [(0, 1 + (j + 1) % n, 1 + j) for j in range(n)]
    top = [(top_pole, last + j, last + (j + 1) % n) for j in range(n)]
    return tuple(bottom + body + top)


def _sphere_vertices(d: Dims, n: int) -> np.ndarray:
    ring = _unit_circle(n)
    # polar angles pi - 2 pi j / n, j = 1 .. n/2 - 1, bottom ring first: -cos, sin of the circle
    cos_t, sin_t = -ring[1 : n // 2, 0][:, None], ring[1 : n // 2, 1][:, None]
    rings = np.stack([sin_t * ring[:, 0], sin_t * ring[:, 1], np.repeat(cos_t, n, 1)], -1)
    v = np.vstack([[[0.0, 0.0, -1.0]], rings.reshape(-1, 3), [[0.0, 0.0, 1.0]]])
    return v * d[0] / 2


@functools.cache
def _cylinder_faces(n: int) -> Faces:
    sides = [(j, (j + 1) % n, n + (j + 1) % n, n + j) for j in range(n)]
    return tuple(sides + [tuple(range(n - 1, -1, -1)), tuple(range(n, 2 * n))])


def _base_ring(d: Dims, n: int) -> np.ndarray:
    """The n vertices of the circle of radius dx / 2 at z = -dz / 2."""
    return np.column_stack([_unit_circle(n) * (d[0] / 2), np.full(n, -d[2] / 2)])


def _cylinder_vertices(d: Dims, n: int) -> np.ndarray:
    top = np.column_stack([_unit_circle(n) * (d[0] / 2), np.full(n, d[2] / 2)])
    return np.vstack([_base_ring(d, n), top])


@functools.cache
def _cone_faces(n: int) -> Faces:
    return tuple([(j, (j + 1) % n, n) for j in range(n)] + [tuple(range(n - 1, -1, -1))])


def _cone_vertices(d: Dims, n: int) -> np.ndarray:
    return np.vstack([_base_ring(d, n), [[0, 0, d[2] / 2]]])


def _torus_sections(n: int) -> int:
    """Segments around the tube of a torus with n segments around its axis."""
    return max(8, n // 2)


@functools.cache
def _torus_faces(n: int) -> Faces:
    return tuple((a, d, c, b) for a, b, c, d in _grid_faces(n, _torus_sections(n), True))


def _torus_vertices(d: Dims, n: int) -> np.ndarray:
    major, minor = (d[0] - d[2]) / 2, d[2] / 2
    ring, minor_ring = _unit_circle(n), _unit_circle(_torus_sections(n))
    arm = (major + minor * minor_ring[:, 0])[None, :]  # distance from the axis, per angle
    z = np.broadcast_to(minor * minor_ring[:, 1], (n, len(minor_ring)))
    v = np.stack([arm * ring[:, :1], arm * ring[:, 1:], z], -1)
    return v.reshape(-1, 3)


# ---------------------------------------------------------------- random dimensions


def _draw_cube(rng: np.random.Generator, size: float, a: float) -> list[float]:
    d = rng.uniform(0.5, 1.0, size=3)
    return list(size * d / d.max())


def _draw_slab(rng: np.random.Generator, size: float, a: float) -> list[float]:
    return [size, size * a, size * rng.uniform(0.03, 0.1)]


def _draw_sphere(rng: np.random.Generator, size: float, a: float) -> list[float]:
    return [size] * 3


def _draw_round(rng: np.random.Generator, size: float, a: float) -> list[float]:
    """A cylinder or cone: squat (height a x size) or tall (diameter a x size), even odds."""
    if rng.random() < 0.5:
        return [size, size, size * a]
    return [size * a, size * a, size]


def _draw_torus(rng: np.random.Generator, size: float, a: float) -> list[float]:
    ratio = rng.uniform(0.15, 0.5)  # minor / major radius
    major = size / 2 / (1 + ratio)
    return [size, size, 2 * major * ratio]


def _draw_plane(rng: np.random.Generator, size: float, a: float) -> list[float]:
    return [size, size * a, 0.0]


#: every primitive kind; the order of the ``random`` ones is the default draw's (do not reorder:
#: a scene's kind is an index into config.PRIMITIVE_KINDS)
SHAPES: dict[str, Shape] = {
    "cube": Shape(
        "a box of those dimensions",
        _box_distance, _box_vertices, _box_faces, _draw_cube, smooth=False,
    ),
    "sphere": Shape(
        "a sphere of diameter dx (dx = dy = dz)",
        _sphere_distance, _sphere_vertices, _sphere_faces, _draw_sphere, smooth=True,
    ),
    "cone": Shape(
        "axis local z, base of radius dx / 2 at z = -dz / 2, apex at z = +dz / 2",
        _cone_distance, _cone_vertices, _cone_faces, _draw_round, smooth=True,
    ),
    "torus": Shape(
        "around local z, major radius (dx - dz) / 2, minor radius dz / 2",
        _torus_distance, _torus_vertices, _torus_faces, _draw_torus, smooth=True,
    ),
    "cylinder": Shape(
        "axis local z, radius dx / 2, height dz",
        _cylinder_distance, _cylinder_vertices, _cylinder_faces, _draw_round, smooth=True,
    ),
    "slab": Shape(
        "a thin box of those dimensions",
        _box_distance, _box_vertices, _box_faces, _draw_slab, smooth=False,
    ),
    "plane": Shape(
        "the rectangle dx by dy in the local xy plane (dz = 0) facing local +z, one two-sided "
        "polygon with no inside (its signed distance is never negative)",
        _box_distance, _plane_vertices, _plane_faces, _draw_plane, smooth=False, random=False,
    ),
}  # fmt: skip


def shape(kind: str) -> Shape:
    """The table entry of ``kind`` (ValueError naming an unknown one)."""
    try:
        return SHAPES[kind]
    except KeyError:
        raise ValueError(f"unknown primitive kind {kind!r}") from None


def signed_distance(kind: str, dimensions, p: np.ndarray) -> np.ndarray:
    """Signed distance (metres, < 0 inside) from local-frame points p (N, 3) to the shape."""
    d = tuple(float(v) for v in dimensions)
    return shape(kind).distance(d, p)


def mesh(kind: str, dimensions, segments: int = 32) -> tuple[np.ndarray, list[tuple[int, ...]]]:
    """Vertices (N, 3) in metres and polygon faces (outward, counter-clockwise) of a primitive."""
    s = shape(kind)
    d = tuple(float(v) for v in dimensions)
    return s.vertices(d, segments), list(s.faces(segments))


def random_dimensions(rng: np.random.Generator, kind: str, size: float) -> list[float]:
    """Local bounding box (plain floats, metres) of a random primitive of ``kind`` whose largest
    extent is ``size``: one aspect uniform in [0.5, 1) first, then the kind's own draws."""
    a = rng.uniform(0.5, 1.0)
    return [float(v) for v in shape(kind).draw(rng, size, a)]
