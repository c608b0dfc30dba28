"""JSON Schemas of metadata.json and dataset.json (the prose version is docs/FORMAT.md)."""

from __future__ import annotations

from .config import SHAPE_KINDS
from .layout import CHUNK_SIZE

_num = {"type": "number"}
_vec3 = {"type": "array", "items": _num, "minItems": 3, "maxItems": 3}
_quat = {"type": "array", "items": _num, "minItems": 4, "maxItems": 4}
_mat = {"type": "array", "items": {"type": "array", "items": _num}}
_mat4 = {**_mat, "minItems": 4, "maxItems": 4}
_names = {"type": "array", "items": {"type": "string", "pattern": r"^[^/_]+_\d+_\d+\.\w+$"}}
_frame = {"type": "integer", "minimum": 0}
# --flow: one entry per frame pair (stillbox_gen.layout.flow_entries)
_flow_entry = {
    "type": "object",
    "required": ["from", "to", "flow", "valid", "occluded"],
    "additionalProperties": False,
    "properties": {
        "from": _frame,
        "to": _frame,
        # Middlebury .flo, or KITTI's 16-bit PNG (--flow-format kitti-png)
        "flow": {"type": "string", "pattern": r"^flow_\d+_\d+_\d+\.(flo|png)$"},
        "valid": {"type": "string", "pattern": r"^valid_\d+_\d+_\d+\.png$"},
        "occluded": {"type": "string", "pattern": r"^occluded_\d+_\d+_\d+\.png$"},
    },
}

MATERIAL = {
    "type": "object",
    "required": [
        "kind",
        "pattern",
        "colors",
        "positions",
        "scale",
        "detail",
        "offset",
        "rotation",
        "roughness",
        "metallic",
        "image",
    ],
    "properties": {
        "kind": {"enum": ["procedural", "image", "plain"]},
        "scale": {"type": "number", "exclusiveMinimum": 0},
        "roughness": {"type": "number", "minimum": 0, "maximum": 1},
        "metallic": {"type": "number", "minimum": 0, "maximum": 1},
    },
}

SCENE_RECORD = {
    "type": "object",
    "required": [
        "imgs",
        "depth",
        "speed",
        "time_step",
        "length",
        "orientation",  # original keys
        "index",
        "scene_in_chunk",
        "seed",
        "rejected",
        "rgb",
        "depth_exr",
        "resolution",
        "K",
        "displacement",
        "cam2world",
        "world2cam",
        "primitives",
        "box",
        "light",
    ],
    "properties": {
        "imgs": _names,
        "depth": _names,
        "rgb": _names,
        "depth_exr": _names,
        "flow": {"type": "array", "items": _flow_entry},  # only in datasets made with --flow
        "speed": _vec3,
        "time_step": {"type": "number", "exclusiveMinimum": 0},
        "length": {"type": "integer", "minimum": 2},
        "orientation": {"type": "array", "items": _quat},
        "index": {"type": "integer", "minimum": 0},
        "scene_in_chunk": {"type": "integer", "minimum": 0, "maximum": 199},
        "seed": {"type": "integer", "minimum": 0},
        "rejected": {"type": "integer", "minimum": 0},
        "resolution": {
            "type": "array",
            "items": {"type": "integer", "minimum": 1},
            "minItems": 2,
            "maxItems": 2,
        },
        "K": {**_mat, "minItems": 3, "maxItems": 3},
        "displacement": {"type": "number", "exclusiveMinimum": 0},
        "cam2world": {"type": "array", "items": _mat4},
        "world2cam": {"type": "array", "items": _mat4},
        "primitives": {
            "type": "array",
            "items": {
                "type": "object",
                "required": ["kind", "dimensions", "location", "rotation", "material"],
                "properties": {
                    "kind": {"enum": list(SHAPE_KINDS)},
                    "dimensions": _vec3,
                    "location": _vec3,
                    "rotation": _quat,
                    "material": MATERIAL,
                },
            },
        },
        "box": {"type": "object", "required": ["center", "half_extents", "material"]},
        "light": {
            "type": "object",
            "required": ["sun_direction", "sun_strength", "ambient_strength"],
        },
    },
}

METADATA = {
    "type": "object",
    "required": ["args", "scenes"],
    "properties": {
        "args": {
            "type": "object",
            "required": [
                "fov",
                "resolution",
                "frames",
                "displacement",
                "max_distance",
                "depth_convention",
                "generator",
                "format_version",
                "config",
            ],
            "properties": {
                "fov": {"type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 180}
            },
        },
        "scenes": {"type": "array", "items": SCENE_RECORD, "minItems": 1, "maxItems": CHUNK_SIZE},
    },
}

DATASET = {
    "type": "object",
    "required": [
        "format_version",
        "complete",
        "versions",
        "preset",
        "seed",
        "fingerprint",
        "scenes",
        "frames",
        "rejected_scenes",
        "split_scenes",
        "render",
        "config",
        "run",
    ],
    "properties": {
        "complete": {"const": True},
        "scenes": {"type": "integer", "minimum": 1},
        "frames": {"type": "integer", "minimum": 2},
    },
}
