"""The scene build's fast paths (stillbox_gen/blender/build.py) against Blender's public API.

Meshes are written through the attribute API and material values with foreach_set, both much
faster than Mesh.from_pydata and socket assignments (issue 26); here each is compared, in a real
Blender process, with what the slow public calls make of the same input: same vertices, faces,
edges, sharp faces and corner normals for every primitive kind, and the same value on every
node input and ramp stop for materials of every kind and pattern.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

pytestmark = pytest.mark.render

SCRIPT = r"""
import itertools, math, sys
import bpy
import numpy as np
from stillbox_gen import config, photos, shapes
from stillbox_gen.blender import build

def pydata_mesh(kind, dims, inward):
    verts, faces = shapes.mesh(kind, dims)
    if inward:
        faces = [tuple(reversed(f)) for f in faces]
    me = bpy.data.meshes.new("reference")
    me.from_pydata(verts.tolist(), [], faces)
    if shapes.shape(kind).smooth:
        me.shade_smooth()
        me.set_sharp_from_angle(angle=math.radians(45))
    else:
        me.shade_flat()
    return me

def mesh_facts(me):
    co = np.empty(3 * len(me.vertices)); me.vertices.foreach_get("co", co)
    faces = [tuple(p.vertices) for p in me.polygons]
    edges = sorted(tuple(sorted(e.vertices)) for e in me.edges)
    sharp = [p.use_smooth for p in me.polygons]
    normals = np.array([n.vector[:] for n in me.corner_normals])
    return co, faces, edges, sharp, normals

bad = []
for kind in config.SHAPE_KINDS:
    for inward in (False, True):
        dims = [2.0, 2.0, 0.0 if kind == "plane" else 1.5]
        if kind == "sphere":
            dims = [2.0, 2.0, 2.0]
        fast = build.make_mesh_object("fast", kind, dims, inward).data
        ref = pydata_mesh(kind, dims, inward)
        for name, a, b in zip(("co", "faces", "edges", "smooth", "normals"),
                              mesh_facts(fast), mesh_facts(ref)):
            if name in ("co", "normals"):  # positions exact; normals as computed from them
                same = np.allclose(a, b, rtol=0, atol=0 if name == "co" else 1e-6)
            else:  # lists of faces (triangles and quads), edges, smooth flags
                same = a == b
            if not same:
                bad.append(f"{kind} inward={inward}: {name} differ")

def slow_values(mat, spec, emission):
    # the per-socket assignments that build._set_material_values replaces
    nodes = mat.node_tree.nodes
    bsdf = nodes["bsdf"]
    bsdf.inputs["Roughness"].default_value = spec["roughness"]
    bsdf.inputs["Metallic"].default_value = spec["metallic"]
    if spec["kind"] == "plain":
        bsdf.inputs["Base Color"].default_value = (*spec["colors"][0], 1.0)
        if emission is not None:
            rgb = [c * a for c, a in zip(spec["colors"][0], emission)]
            bsdf.inputs["Emission Color"].default_value = (*rgb, 1.0)
        return
    m = nodes["mapping"]
    m.inputs["Location"].default_value = spec["offset"]
    m.inputs["Rotation"].default_value = spec["rotation"]
    m.inputs["Scale"].default_value = (spec["scale"],) * 3
    tex = nodes["texture"]
    if spec["kind"] == "image":
        nodes["tint"].inputs["B"].default_value = (*spec["colors"][0], 1.0)
    detail = {"noise": ("Detail", 0.0, 2.0), "voronoi": ("Randomness", 0.5, 0.5),
              "wave": ("Distortion", 0.0, 4.0), "gradient_stripes": ("Distortion", 0.0, 2.0),
              "brick": ("Mortar Size", 0.05, 0.07)}
    if spec["pattern"] in detail:
        socket, low, rise = detail[spec["pattern"]]
        tex.inputs[socket].default_value = low + rise * spec["detail"]
    elif spec["pattern"] == "magic":
        tex.turbulence_depth = 1 + int(spec["detail"] * 2)
    if spec["kind"] == "procedural":
        els = nodes["ramp"].color_ramp.elements
        for i, (p, c) in enumerate(zip(spec["positions"], spec["colors"])):
            els[i].position, els[i].color = p, (*c, 1.0)
    if emission is not None:
        nodes["ambient"].inputs["B"].default_value = (*emission, 1.0)

def node_facts(mat):
    out = {}
    for node in mat.node_tree.nodes:
        for s in node.inputs:
            if hasattr(s, "default_value"):
                out[(node.name, s.identifier)] = np.array(s.default_value, dtype=float).ravel()
        if node.name == "ramp":
            for i, e in enumerate(node.color_ramp.elements):
                out[("ramp", i)] = np.array([e.position, *e.color])
        if node.name == "texture" and hasattr(node, "turbulence_depth"):
            out[("texture", "depth")] = np.array([node.turbulence_depth])
    return out

rng = np.random.default_rng(3)
cases = [("plain", None), ("image", None)] + [("procedural", p) for p in build._PATTERN_NODES]
for (kind, pattern), stops in itertools.product(cases, (2, 3, 4)):
    for emission in (None, [0.2, 0.3, 0.4]):
        pos = sorted(rng.uniform(0, 1, stops).tolist())
        spec = {"kind": kind, "pattern": pattern, "positions": pos,
                "colors": rng.uniform(0, 1, (stops, 3)).tolist(),
                "roughness": 0.37, "metallic": 0.0, "scale": 1.7, "detail": 0.6,
                "offset": [1.0, -2.0, 3.0], "rotation": [0.1, 0.2, 0.3],
                "image": photos.BUNDLED_PHOTOS[0] if kind == "image" else None}
        fast = build.make_material("fast", spec, None, (10.0, 50.0), emission)
        ref = build.make_material("ref", spec, None, (10.0, 50.0), emission)
        slow_values(ref, spec, emission)
        a, b = node_facts(fast), node_facts(ref)
        for key in b:
            if not np.allclose(a[key], b[key], rtol=0, atol=1e-7):
                bad.append(f"material {kind}/{pattern} emission={emission is not None}: {key}")
print("\n".join(bad) if bad else "ok", file=sys.stderr)
"""


def test_fast_meshes_and_material_values_equal_the_public_api_s():
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stderr.strip().splitlines()[-1] == "ok", proc.stderr[-3000:]
