"""The primitive table (stillbox_gen.shapes.SHAPES) is the one place a kind is defined: every
other list of kinds (config, schema, docs/FORMAT.md) derives from it or is checked against it,
and every entry, an added one included, passes the same geometric checks."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from stillbox_gen import config, schema, shapes

ROOT = Path(__file__).resolve().parents[1]
DIMS = {"sphere": [2.0, 2.0, 2.0], "plane": [2.0, 1.4, 0.0]}  # others: a generic box
KINDS = list(shapes.SHAPES)


def _dims(kind: str) -> list[float]:
    return DIMS.get(kind, [2.0, 1.6, 1.2] if kind in ("cube", "slab") else [2.0, 2.0, 0.6])


def test_config_schema_and_format_doc_list_the_table():
    assert tuple(KINDS) == config.SHAPE_KINDS
    assert tuple(k for k in KINDS if shapes.SHAPES[k].random) == config.PRIMITIVE_KINDS
    enum = schema.SCENE_RECORD["properties"]["primitives"]["items"]["properties"]["kind"]["enum"]
    assert enum == KINDS
    row = next(
        line for line in (ROOT / "docs/FORMAT.md").read_text().splitlines()
        if line.startswith("| `primitives` |")
    )  # fmt: skip
    listed = re.search(r"kind in ([a-z, ]+);", row).group(1).split(", ")
    assert listed == KINDS, "docs/FORMAT.md's primitives row must name every shape, in order"


@pytest.mark.parametrize("kind", KINDS)
def test_mesh_vertices_lie_on_the_signed_distance_surface(kind):
    """Every vertex of the inscribed mesh is on the exact surface (distance 0), and every face
    indexes existing vertices: the mesh Blender renders and the rejection test agree."""
    verts, faces = shapes.mesh(kind, _dims(kind), segments=16)
    d = shapes.signed_distance(kind, _dims(kind), verts)
    np.testing.assert_allclose(d, 0.0, atol=1e-9)
    used = sorted({i for f in faces for i in f})
    assert used == list(range(len(verts))), "every vertex used, no index out of range"
    assert all(len(f) >= 3 for f in faces)


@pytest.mark.parametrize("kind", KINDS)
def test_inside_points_are_negative_and_far_points_positive(kind):
    """The local origin of a solid is inside (< 0; a torus's centre and a plane are not solid
    there); a point 20 m along x, 10 extents away, is outside by about 19 m."""
    dims = _dims(kind)
    far = np.array([[20.0, 0.0, 0.0]])
    assert shapes.signed_distance(kind, dims, far)[0] == pytest.approx(19.0, abs=0.2)
    if kind not in ("plane", "torus"):
        assert shapes.signed_distance(kind, dims, np.zeros((1, 3)))[0] < 0


@pytest.mark.parametrize("kind", KINDS)
def test_random_dimensions_have_the_drawn_largest_extent(kind):
    """A random primitive's largest extent is the size drawn, whatever its kind, and the first
    draw is the shared aspect (the order of draws does not depend on the kind)."""
    for seed in range(20):
        rng = np.random.default_rng(seed)
        size = float(rng.uniform(0.1, 2.0))
        dims = shapes.random_dimensions(rng, kind, size)
        assert len(dims) == 3 and all(type(v) is float for v in dims)
        assert max(dims) == pytest.approx(size, rel=1e-12)
        assert min(dims) >= 0
    with pytest.raises(ValueError, match="unknown primitive kind 'blob'"):
        shapes.random_dimensions(np.random.default_rng(0), "blob", 1.0)
