"""A scene in the two forms the generator writes and reads: the :class:`SceneSpec` (what Blender
renders; JSON-serialisable dataclasses, sampled by stillbox_gen.scene) and its record (the entry
of the scene in its chunk's metadata.json, docs/FORMAT.md), with the mapping both ways, defined
once here: :func:`scene_record` (spec -> record, written by stillbox_gen.writer) and
:func:`spec_from_record` (record -> spec, for re-rendering a dataset's scenes).

A record holds every field of the spec under its own name, but the camera's: the camera's
fields sit at the top level of the record, its ``width`` and ``height`` as ``resolution``
([width, height], pixels). Around them the record adds file names, the original StillBox keys and
derived values (``world2cam``, ``displacement``, later ``sha256``). Needs no Blender and no config.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from . import camera, portable
from .errors import ConfigError
from .layout import depth_name, flow_entries, local_index, rgb_name


@dataclass
class MaterialSpec:
    """Surface description. Colours are linear RGB in [0, 1]; ``scale`` in features per metre."""

    kind: str  # "procedural" | "image" | "plain"
    pattern: str | None  # one of config.PATTERNS for procedural, else None
    colors: list[list[float]]  # colour-ramp stops (procedural), one colour (plain), tint (image)
    positions: list[float]  # colour-ramp stop positions in [0, 1]
    scale: float  # texture features (or image tiles) per metre
    detail: float  # pattern-specific: noise detail, voronoi randomness, wave distortion...
    offset: list[float]  # texture-space offset in metres
    rotation: list[float]  # texture-space Euler XYZ rotation, radians (no axis-aligned stripes)
    roughness: float
    metallic: float
    image: str | None  # file name in the textures folder, for kind == "image"


@dataclass
class PrimitiveSpec:
    kind: str  # see shapes.py for the meaning of dimensions
    dimensions: list[float]  # local bounding box (dx, dy, dz), metres
    location: list[float]  # world, metres
    rotation: list[float]  # world orientation quaternion [w, x, y, z]
    material: MaterialSpec


@dataclass
class BoxSpec:
    """Axis-aligned box of walls seen from inside; walls cast no shadows."""

    center: list[float]
    half_extents: list[float]
    material: MaterialSpec


@dataclass
class LightSpec:
    sun_direction: list[float]  # unit vector along which sunlight travels (world)
    sun_strength: float  # W/m^2
    sun_color: list[float]
    ambient_color: list[float]  # world background colour (reaches inside: walls cast no shadow)
    ambient_strength: float


@dataclass
class CameraSpec:
    """Intrinsics and per-frame poses. Poses are OpenCV cam2world 4x4 (row-major lists)."""

    width: int
    height: int
    K: list[list[float]]
    time_step: float  # seconds between frames
    speed: list[float]  # m/s in the first frame's camera axes; frame i at i*speed*time_step
    orientation: list[list[float]]  # per frame [w,x,y,z] of R_cam0<-cam_i, or [] if none
    cam2world: list[list[list[float]]]
    near_clip: float
    far_clip: float


@dataclass
class SceneSpec:
    index: int  # global scene index in the dataset
    seed: int  # 63-bit seed of this scene (render noise is derived from it)
    rejected: int  # sampled scenes rejected before this one (camera path hit an object)
    camera: CameraSpec
    primitives: list[PrimitiveSpec]
    box: BoxSpec
    light: LightSpec

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> SceneSpec:
        prims = [
            PrimitiveSpec(**{**p, "material": MaterialSpec(**p["material"])})
            for p in d["primitives"]
        ]
        box = BoxSpec(**{**d["box"], "material": MaterialSpec(**d["box"]["material"])})
        return SceneSpec(
            index=d["index"],
            seed=d["seed"],
            rejected=d["rejected"],
            camera=CameraSpec(**d["camera"]),
            primitives=prims,
            box=box,
            light=LightSpec(**d["light"]),
        )


def scene_record(
    spec: dict, image_format: str, legacy: bool, flow: bool = False, flow_format: str = "flo"
) -> dict:
    """The metadata.json entry of one scene, built from its SceneSpec dict.

    Original StillBox keys first (imgs, depth, speed, time_step, length, orientation), then ours;
    with ``flow`` (--flow), ``flow`` lists the flow and mask files of each frame pair
    (stillbox_gen.layout.flow_entries, flow files in ``flow_format``); ``sha256`` ({file name:
    digest}) is added last, once the files are written.
    """
    cam = spec["camera"]
    local, n = local_index(spec["index"]), len(cam["cam2world"])
    rgb = [rgb_name(local, f, image_format) for f in range(n)]
    exr = [depth_name(local, f) for f in range(n)]
    w2c = [camera.invert_pose(m) for m in cam["cam2world"]]
    displacement = portable.norm(cam["speed"]) * cam["time_step"]
    return {
        "imgs": [rgb_name(local, f, "jpg") for f in range(n)] if legacy else rgb,
        "depth": [depth_name(local, f, "npy") for f in range(n)] if legacy else exr,
        "speed": cam["speed"],
        "time_step": cam["time_step"],
        "length": n,
        "orientation": cam["orientation"],
        "index": spec["index"],
        "scene_in_chunk": local,
        "seed": spec["seed"],
        "rejected": spec["rejected"],
        "rgb": rgb,
        "depth_exr": exr,
        "resolution": [cam["width"], cam["height"]],
        "K": cam["K"],
        "displacement": displacement,
        "cam2world": cam["cam2world"],
        "world2cam": [m.tolist() for m in w2c],
        "near_clip": cam["near_clip"],
        "far_clip": cam["far_clip"],
        "primitives": spec["primitives"],
        "box": spec["box"],
        "light": spec["light"],
        **({"flow": flow_entries(local, n, flow_format)} if flow else {}),
    }


def spec_from_record(rec: dict, frames: list[int] | None = None) -> dict:
    """The SceneSpec dict of a scene record (metadata.json entry), optionally keeping only the
    poses ``frames`` (rendered files are then numbered 0, 1, ... in that order): the inverse of
    :func:`scene_record`. ConfigError naming the missing keys of an incomplete record."""
    cam_keys = [f.name for f in fields(CameraSpec) if f.name not in ("width", "height")]
    top = [f.name for f in fields(SceneSpec) if f.name != "camera"]
    missing = [k for k in [*top, *cam_keys, "resolution"] if k not in rec]
    if missing:
        raise ConfigError(
            f"DATASET: scene {rec.get('index')}'s record lacks {', '.join(missing)} "
            "(written by another stillbox-gen version?)"
        )
    w, h = rec["resolution"]
    camera = {"width": w, "height": h, **{k: rec[k] for k in cam_keys}}
    if frames is not None:
        camera["cam2world"] = [rec["cam2world"][f] for f in frames]
        if camera["orientation"]:
            camera["orientation"] = [rec["orientation"][f] for f in frames]
    spec = {**{k: rec[k] for k in top}, "camera": camera}
    return SceneSpec.from_dict(spec).to_dict()
