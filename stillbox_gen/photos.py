"""Photographs shipped with the dependencies, used as textures when no ``--textures`` is given.

The bpy wheel carries eight CC0 photographic panoramas from Poly Haven (1024x512 float EXR, in
``bpy/<version>/datafiles/studiolights/world/``). Random crops, rotations and scales of them (drawn
in scene.py like any texture mapping) give many distinct photo textures. They are high dynamic
range light probes, so each is turned into a reflectance map in [0, 1] by a fixed tone curve.

No bpy import here: the folder is found through the installed package's location.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import numpy as np

BUNDLED_PHOTOS = (
    "city.exr",
    "courtyard.exr",
    "forest.exr",
    "interior.exr",
    "night.exr",
    "studio.exr",
    "sunrise.exr",
    "sunset.exr",
)
BUNDLED_SOURCE = (
    "bpy datafiles/studiolights/world: 8 CC0 panoramas by Greg Zaal (Poly Haven), 1024x512"
)
MIDDLE_GREY = 0.25  # reflectance the geometric-mean luminance of a photo is mapped to


def bundled_folder() -> Path:
    """Folder of the bundled panoramas inside the installed bpy package."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError("the bpy package is not installed")
    root = Path(next(iter(spec.submodule_search_locations)))
    found = sorted(root.glob("*/datafiles/studiolights/world"))
    if not found:
        raise FileNotFoundError(f"no datafiles/studiolights/world folder under {root}")
    return found[-1]


def tone_map(hdr: np.ndarray) -> np.ndarray:
    """Linear HDR RGB (H, W, 3) -> linear reflectance in [0, 1], float32.

    Exposure puts the geometric-mean luminance at MIDDLE_GREY; a Reinhard curve x / (1 + x),
    rescaled so that it passes through (MIDDLE_GREY, MIDDLE_GREY), compresses the highlights
    (sun, lamps) instead of clipping them.
    """
    rgb = np.nan_to_num(np.maximum(hdr.astype(np.float64), 0.0))
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
    key = float(np.exp(np.mean(np.log(lum + 1e-4))))
    x = rgb * (MIDDLE_GREY / key)
    y = x / (1.0 + x) * (1.0 + MIDDLE_GREY)
    return np.clip(y, 0.0, 1.0).astype(np.float32)


def load_bundled(name: str) -> np.ndarray:
    """A bundled panorama as a tone-mapped linear RGB reflectance map (H, W, 3), top row first."""
    if name not in BUNDLED_PHOTOS:
        raise ValueError(f"unknown bundled photo {name!r}")
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    import cv2

    path = bundled_folder() / name
    bgr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if bgr is None:
        raise FileNotFoundError(f"cannot read bundled photo {path}")
    return tone_map(bgr[..., :3][..., ::-1])
