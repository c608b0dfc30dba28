"""Turn a SceneSpec dict into Blender data (the only module, with render.py, that imports bpy).

Nothing here draws random numbers: every value comes from the scene description.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix, Quaternion, Vector

from .. import camera, photos, shapes

_PATTERN_NODES = {
    "noise": ("ShaderNodeTexNoise", "Fac"),
    "voronoi": ("ShaderNodeTexVoronoi", "Distance"),
    "wave": ("ShaderNodeTexWave", "Fac"),
    "gradient_stripes": ("ShaderNodeTexWave", "Fac"),
    "checker": ("ShaderNodeTexChecker", "Fac"),
    "brick": ("ShaderNodeTexBrick", "Fac"),
    "magic": ("ShaderNodeTexMagic", "Fac"),
}

# Texture-node Scale that makes one pattern period about one unit of the Mapping node, so that
# MaterialSpec.scale is features per metre for every pattern (Blender's wave bands repeat every
# 2*pi/10 units, magic's first term every 2*pi/5).
_UNIT_SCALE = {"wave": 0.628, "gradient_stripes": 0.628, "magic": 1.256}


# Materials are copied from per-process templates, one per node structure, named with this
# prefix and kept across scenes: Material.copy() takes about 0.04 ms where creating and linking
# the nodes from Python took 2-4 ms, about 20 materials per scene.
TEMPLATE_PREFIX = "~template"


def clear_scene() -> None:
    """Remove the previous scene's data; render settings, material templates and loaded photo
    textures stay."""
    data = bpy.data
    materials = [m for m in data.materials if not m.name.startswith(TEMPLATE_PREFIX)]
    doomed = [*data.objects, *data.meshes, *materials, *data.lights, *data.cameras]
    doomed += [*data.worlds, *data.actions]
    if doomed:
        data.batch_remove(doomed)


def make_material(
    name: str, spec: dict, textures_dir: str | None, footprint: tuple[float, float], ambient=None
):
    """Principled BSDF whose base colour follows the MaterialSpec (object-space, metric mapping).

    ``ambient`` (linear RGB, strength included) adds an emission of base colour x ambient: the
    noise-free ambient term of "direct" shading, in place of sampled world light.
    ``footprint`` = (typical distance of the surface in metres, focal length in pixels) sets the
    resolution of a photo texture.
    """
    emits = ambient is not None and spec["metallic"] == 0  # metals only reflect
    structure = (spec["kind"], spec["pattern"], len(spec["positions"]), emits, ambient is not None)
    template_name = f"{TEMPLATE_PREFIX} " + " ".join(map(str, structure))
    template = bpy.data.materials.get(template_name) or _material_nodes(template_name, *structure)
    mat = template.copy()
    mat.name = name
    emission = ambient if emits else None
    _set_material_values(mat.node_tree.nodes, spec, textures_dir, footprint, emission)
    return mat


def _material_nodes(name: str, kind: str, pattern, stops: int, emits: bool, gated: bool):
    """A material with the nodes and links of one structure (values are set per material by
    _set_material_values). Nodes are named for that: bsdf, mapping, texture, tint, ramp, ambient."""
    mat = bpy.data.materials.new(name)
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes.get("Principled BSDF") or nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.name = "bsdf"
    colour = None
    if kind != "plain":
        coords = nodes.new("ShaderNodeTexCoord")
        mapping = nodes.new("ShaderNodeMapping")
        mapping.name = "mapping"
        links.new(coords.outputs["Object"], mapping.inputs["Vector"])
        if kind == "image":
            tex = nodes.new("ShaderNodeTexImage")
            tex.projection = "BOX"
            tex.projection_blend = 0.2
            tint = _multiply(nodes, links, tex.outputs["Color"], "tint")
            colour = tint.outputs["Result"]
        else:
            tex, output = _pattern_node(nodes, pattern)
            ramp = nodes.new("ShaderNodeValToRGB")
            ramp.name = "ramp"
            while len(ramp.color_ramp.elements) < stops:
                ramp.color_ramp.elements.new(0.5)
            links.new(tex.outputs[output], ramp.inputs["Fac"])
            colour = ramp.outputs["Color"]
        tex.name = "texture"
        links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
        links.new(colour, bsdf.inputs["Base Color"])
    if emits:
        mat.cycles.emission_sampling = "NONE"  # no light-tree build; same image
        bsdf.inputs["Emission Strength"].default_value = 1.0
        if colour is not None:
            tinted = _multiply(nodes, links, colour, "ambient")
            links.new(tinted.outputs["Result"], bsdf.inputs["Emission Color"])
    if gated:
        _only_camera_and_mirror_rays(nodes, links, bsdf)
    return mat


def _multiply(nodes, links, colour, name: str):
    """A colour Mix node (multiply, factor 1) named ``name`` with ``colour`` as its A input."""
    mix = nodes.new("ShaderNodeMix")
    mix.name = name
    mix.data_type, mix.blend_type = "RGBA", "MULTIPLY"
    mix.inputs["Factor"].default_value = 1.0
    links.new(colour, mix.inputs["A"])
    return mix


def _set_material_values(nodes, spec: dict, textures_dir, footprint, emission) -> None:
    """Set the values of a MaterialSpec on a copy of its structure's template (make_material);
    ``emission``: the ambient colour of an emitting surface, None for the others.

    Values are written by _set_inputs and _ramp_stops, which skip Blender's node-tree update,
    except the last one, an assignment: its update tags the material as changed for Cycles.
    Without it Cycles, whose data persists across scenes, can keep the shader of a previous
    scene's material that had the same address (frames then changed from run to run).
    """
    bsdf = {"Metallic": spec["metallic"]}
    if spec["kind"] == "plain":
        bsdf["Base Color"] = (*spec["colors"][0], 1.0)
        if emission is not None:
            rgb = [c * a for c, a in zip(spec["colors"][0], emission, strict=True)]
            bsdf["Emission Color"] = (*rgb, 1.0)
    _set_inputs(nodes["bsdf"], bsdf)
    if spec["kind"] != "plain":
        _set_texture_values(nodes, spec, textures_dir, footprint, emission)
    nodes["bsdf"].inputs["Roughness"].default_value = spec["roughness"]


def _set_texture_values(nodes, spec: dict, textures_dir, footprint, emission) -> None:
    """Values of the mapping, texture, tint or ramp and ambient nodes (_set_material_values)."""
    mapping = {"Location": spec["offset"], "Rotation": spec["rotation"]}
    _set_inputs(nodes["mapping"], mapping | {"Scale": (spec["scale"],) * 3})
    tex = nodes["texture"]
    if spec["kind"] == "image":
        tex.image = _photo(spec["image"], textures_dir, 1.0 / spec["scale"], footprint)
        _set_inputs(nodes["tint"], {"B_Color": (*spec["colors"][0], 1.0)})
    else:
        _pattern_values(tex, spec["pattern"], spec["detail"])
        _ramp_stops(nodes["ramp"].color_ramp.elements, spec["positions"], spec["colors"])
    if emission is not None:
        _set_inputs(nodes["ambient"], {"B_Color": (*emission, 1.0)})


# Node bl_idname -> (length of the flat array of its input values, socket identifier -> slice).
_INPUT_LAYOUTS: dict[str, tuple[int, dict[str, slice]]] = {}


def _set_inputs(node, values: dict) -> None:
    """Set the default values of some input sockets of ``node`` (socket identifier -> float or
    vector/colour sequence) with one foreach_set of all its inputs.

    Assigning a socket's default_value runs Blender's node-tree update, about 30 us each;
    foreach_set runs none (_set_material_values runs it once). Every input of the nodes written
    here holds floats, so the inputs' values form one float32 array; the unchanged ones are
    written back as read.
    """
    layout = _INPUT_LAYOUTS.get(node.bl_idname)
    if layout is None:
        slices, end = {}, 0
        for socket in node.inputs:
            start, end = end, end + np.size(socket.default_value)
            slices[socket.identifier] = slice(start, end)
        layout = _INPUT_LAYOUTS[node.bl_idname] = (end, slices)
    size, slices = layout
    flat = np.empty(size, np.float32)
    node.inputs.foreach_get("default_value", flat)
    for identifier, value in values.items():
        flat[slices[identifier]] = value
    node.inputs.foreach_set("default_value", flat)


def _ramp_stops(elements, positions: list[float], colours: list) -> None:
    """Set the ramp's stops to ``positions`` (ascending, 0-1) with ``colours`` (linear RGB).

    Two foreach_set calls write all stops in place (Blender does not re-sort them in between, so
    no stop has to avoid passing its neighbours) and run no node-tree update; assigning each
    stop's position and colour would run that update, about 30 us, twice per stop.
    """
    elements.foreach_set("position", positions)
    elements.foreach_set("color", [v for rgb in colours for v in (*rgb, 1.0)])


def _pattern_node(nodes, pattern: str):
    """The texture node of a pattern, with its detail-independent settings; (node, output)."""
    node_type, output = _PATTERN_NODES[pattern]
    tex = nodes.new(node_type)
    if "Scale" in tex.inputs:  # the Mapping node carries the scale (features per metre)
        tex.inputs["Scale"].default_value = _UNIT_SCALE.get(pattern, 1.0)
    if pattern == "wave":
        tex.inputs["Detail"].default_value = 1.0
    elif pattern == "gradient_stripes":
        tex.wave_profile = "SAW"
    elif pattern == "checker":
        tex.inputs["Color1"].default_value = (1, 1, 1, 1)
        tex.inputs["Color2"].default_value = (0, 0, 0, 1)
    elif pattern == "brick":
        tex.inputs["Brick Width"].default_value = 1.0
        tex.inputs["Row Height"].default_value = 0.5
    return tex, output


# The texture input that follows MaterialSpec.detail (0-1): (socket, value at 0, rise to 1).
_DETAIL_INPUTS = {
    "noise": ("Detail", 0.0, 2.0),
    "voronoi": ("Randomness", 0.5, 0.5),
    "wave": ("Distortion", 0.0, 4.0),
    "gradient_stripes": ("Distortion", 0.0, 2.0),
    "brick": ("Mortar Size", 0.05, 0.07),
}


def _pattern_values(tex, pattern: str, detail: float) -> None:
    """The settings of a pattern's texture node that follow MaterialSpec.detail (0-1)."""
    if pattern == "magic":
        tex.turbulence_depth = 1 + int(detail * 2)
    elif pattern in _DETAIL_INPUTS:
        socket, low, rise = _DETAIL_INPUTS[pattern]
        _set_inputs(tex, {socket: low + rise * detail})


def _only_camera_and_mirror_rays(nodes, links, bsdf) -> None:
    """Shade a surface black for every ray but camera rays and mirror (singular) reflections.

    Under "direct" shading this removes all sampled light: the ambient emission of one surface
    no longer lights the others through BSDF-sampled rays, and rough glossy lobes no longer pick
    up sunlit surfaces at random. What is left (sun through one deterministic shadow ray, ambient
    emission, sharp mirror images) is the same whatever the noise seed.
    """
    output = next(n for n in nodes if n.type == "OUTPUT_MATERIAL")
    path = nodes.new("ShaderNodeLightPath")
    gate = nodes.new("ShaderNodeMath")
    gate.operation = "MAXIMUM"
    links.new(path.outputs["Is Camera Ray"], gate.inputs[0])
    links.new(path.outputs["Is Singular Ray"], gate.inputs[1])
    black = nodes.new("ShaderNodeEmission")
    black.inputs["Strength"].default_value = 0.0
    mix = nodes.new("ShaderNodeMixShader")
    links.new(gate.outputs["Value"], mix.inputs["Fac"])
    links.new(black.outputs["Emission"], mix.inputs[1])
    links.new(bsdf.outputs["BSDF"], mix.inputs[2])
    links.new(mix.outputs["Shader"], output.inputs["Surface"])


_PHOTOS: dict = {}  # (textures_dir, name) -> full-resolution linear RGB, per process


def _photo(name: str, textures_dir: str | None, span_m: float, footprint: tuple[float, float]):
    """Blender image of a photo pre-filtered for a surface (photos.prefiltered_width), made once
    per process and level and kept across scenes. ``footprint`` = (distance m, focal px)."""
    key = (textures_dir, name)
    if key not in _PHOTOS:
        if textures_dir is None:
            _PHOTOS[key] = photos.load_bundled(name)
        else:
            _PHOTOS[key] = photos.load_user(Path(textures_dir) / name)
    full = _PHOTOS[key]
    width = photos.prefiltered_width(full.shape[1], span_m, *footprint)
    label = f"{'bundled' if textures_dir is None else 'user'}:{name}:{width}"
    image = bpy.data.images.get(label)
    if image is None:
        rgb = photos.downsample(full, width)[::-1]  # Blender stores the bottom row first
        h, w = rgb.shape[:2]
        image = bpy.data.images.new(label, w, h, alpha=False, float_buffer=True)
        image.colorspace_settings.name = "Linear Rec.709"
        rgba = np.concatenate([rgb, np.ones((h, w, 1), np.float32)], axis=-1)
        image.pixels.foreach_set(np.ascontiguousarray(rgba).ravel())
        image.pack()  # keep the pixels: a generated image has no file to reload them from
    return image


def make_mesh_object(name: str, kind: str, dims, inward: bool = False):
    """A linked object with the mesh of a primitive (shapes.mesh; dims in metres), its faces
    flat-shaded, or smooth with edges sharper than 45 degrees kept sharp (the shape's ``smooth``);
    ``inward`` reverses the faces (the walls are seen from inside)."""
    verts, faces = shapes.mesh(kind, dims)
    smooth = shapes.shape(kind).smooth
    me = _mesh(name, verts, *_topology(kind, inward, faces, len(verts)), flat=not smooth)
    if smooth:
        me.set_sharp_from_angle(angle=math.radians(45))
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    return obj


# (kind, inward, vertex count) -> _topology(): shapes.mesh's faces depend on the kind and its
# segment count only, and the segment count sets the vertex count
_TOPOLOGIES: dict = {}


def _topology(kind: str, inward: bool, faces: list, vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """(first corner of each face, vertex of each corner), int32, of a primitive's ``faces``,
    reversed when ``inward``; made once per process, kind and vertex count."""
    key = (kind, inward, vertices)
    if key not in _TOPOLOGIES:
        if inward:
            faces = [tuple(reversed(f)) for f in faces]
        sizes = np.array([len(f) for f in faces], np.int32)
        corners = np.fromiter(itertools.chain.from_iterable(faces), np.int32)
        _TOPOLOGIES[key] = (np.cumsum(sizes, dtype=np.int32) - sizes, corners)
    return _TOPOLOGIES[key]


def _mesh(name: str, verts: np.ndarray, starts: np.ndarray, corners: np.ndarray, flat: bool):
    """The mesh Mesh.from_pydata makes of vertices (N, 3) and faces (then shade_smooth unless
    ``flat``), from arrays (_topology). Positions and corner vertices are written through the
    attribute API: MeshVertex.co and MeshPolygon.vertices take 25-50 times longer."""
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(verts))
    me.loops.add(len(corners))
    me.polygons.add(len(starts))
    me.attributes["position"].data.foreach_set("vector", verts.astype(np.float32).ravel())
    me.polygons.foreach_set("loop_start", starts)
    me.attributes[".corner_vert"].data.foreach_set("value", corners)
    if flat:  # shade_flat
        sharp = me.attributes.new("sharp_face", "BOOLEAN", "FACE")
        sharp.data.foreach_set("value", np.ones(len(starts), bool))
    me.update(calc_edges=True)  # the edges, from the faces
    return me


def build_scene(spec: dict, textures_dir: str | None, shading: str = "direct"):
    """Create objects, box, lights and camera of a SceneSpec dict; returns the camera object.

    ``shading`` "direct": delta sun + per-material ambient emission, black world (see RenderConfig).
    "path": soft sun + world background light that reaches inside (walls cast no shadow).
    """
    scene = bpy.context.scene
    light = spec["light"]
    direct = shading == "direct"
    ambient = [c * light["ambient_strength"] for c in light["ambient_color"]] if direct else None
    focal = spec["camera"]["K"][0][0]
    start = [row[3] for row in spec["camera"]["cam2world"][0][:3]]
    for i, p in enumerate(spec["primitives"]):
        obj = make_mesh_object(f"prim{i:02d}_{p['kind']}", p["kind"], p["dimensions"])
        obj.location = p["location"]
        obj.rotation_mode = "QUATERNION"
        obj.rotation_quaternion = Quaternion(p["rotation"])
        footprint = (photos.object_distance(p["location"], p["dimensions"], start), focal)
        obj.data.materials.append(
            make_material(f"mat{i:02d}", p["material"], textures_dir, footprint, ambient)
        )

    box = spec["box"]
    walls = make_mesh_object("walls", "cube", [2 * h for h in box["half_extents"]], inward=True)
    walls.location = box["center"]
    walls.visible_shadow = False  # lets the sun and the sky light the inside
    footprint = (photos.wall_distance(box["center"], box["half_extents"], start), focal)
    walls.data.materials.append(
        make_material("walls", box["material"], textures_dir, footprint, ambient)
    )

    sun_data = bpy.data.lights.new("sun", type="SUN")
    sun_data.energy = light["sun_strength"]
    if direct:
        sun_data.angle = 0.0  # a delta light: one deterministic shadow ray per shading point
    sun_data.color = light["sun_color"]
    sun = bpy.data.objects.new("sun", sun_data)
    sun.rotation_mode = "QUATERNION"
    sun.rotation_quaternion = Vector(light["sun_direction"]).to_track_quat("-Z", "Y")
    scene.collection.objects.link(sun)

    world = bpy.data.worlds.new("sky")
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (*light["ambient_color"], 1.0)
    bg.inputs["Strength"].default_value = 0.0 if direct else light["ambient_strength"]
    scene.world = world

    cam_spec = spec["camera"]
    cam_data = bpy.data.cameras.new("camera")
    settings = camera.blender_camera_settings(
        np.array(cam_spec["K"]), cam_spec["width"], cam_spec["height"]
    )
    for key, value in settings.items():
        setattr(cam_data, key, value)
    cam_data.clip_start = cam_spec["near_clip"]
    cam_data.clip_end = cam_spec["far_clip"]
    cam = bpy.data.objects.new("camera", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    return cam


def set_camera_pose(cam, cam2world_cv) -> None:
    cam.matrix_world = Matrix(camera.opencv_to_blender_cam2world(np.array(cam2world_cv)).tolist())
