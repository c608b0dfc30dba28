"""Photo textures: the photographs shipped with bpy (used when no ``--textures`` is given), and
the pre-filtered resolution at which any photo is rendered.

The bpy wheel carries eight CC0 photographic panoramas from Poly Haven (1024x512 float EXR, in
``bpy/<version>/datafiles/studiolights/world/``). Random crops, rotations and scales of them (drawn
in scene.py like any texture mapping) give many distinct photo textures. They are high dynamic
range light probes, so each is turned into a reflectance map in [0, 1] by a fixed tone curve.

Cycles samples image textures without mip-maps: a photo whose texels are much smaller than a
pixel aliases (a few samples per pixel pick a few of its many texels). So each surface gets the
photo area-downsampled to about TEXELS_PER_PIXEL texels per pixel footprint at its distance
(:func:`prefiltered_width`), a static mip-map level chosen per surface.

No bpy import here: the folder is found through the installed package's location.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import sys
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
TEXELS_PER_PIXEL = 2.0  # texels across one pixel's footprint after pre-filtering
MIN_WIDTH = 8  # texels: the coarsest level kept


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


def prefiltered_width(
    full_width: int, photo_span_m: float, distance_m: float, focal_px: float
) -> int:
    """Width in texels of the pyramid level used for a photo spanning ``photo_span_m`` metres
    on a surface ``distance_m`` metres from the camera (focal length in pixels).

    A pixel covers distance / focal metres there; the level is the smallest of full_width,
    full_width / 2, ... that still gives TEXELS_PER_PIXEL texels per pixel.
    """
    wanted = TEXELS_PER_PIXEL * photo_span_m * focal_px / max(distance_m, 1e-3)
    width = full_width
    while width // 2 >= max(wanted, MIN_WIDTH):
        width //= 2
    return width


def object_distance(location, dimensions, camera_position) -> float:
    """Typical viewing distance of an object's surface: centre distance minus half its largest
    extent (its near side), at least 1 m. Metres."""
    centre = float(np.linalg.norm(np.subtract(location, camera_position)))
    return max(centre - max(dimensions) / 2.0, 1.0)


def wall_distance(center, half_extents, camera_position) -> float:
    """Typical viewing distance of the box's walls: mean distance from the camera to the six
    wall planes. Metres."""
    offset = np.subtract(camera_position, center)
    h = np.asarray(half_extents, dtype=float)
    return float(np.mean(np.concatenate([h - offset, h + offset])))


def downsample(image: np.ndarray, width: int) -> np.ndarray:
    """Area-average an (H, W, 3) image to ``width`` texels across (aspect kept)."""
    h, w = image.shape[:2]
    if width >= w:
        return image
    import cv2

    height = max(1, round(h * width / w))
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def srgb_to_linear(srgb8: np.ndarray) -> np.ndarray:
    """8-bit sRGB -> linear RGB in [0, 1], float32."""
    x = srgb8.astype(np.float32) / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def decode_user(path: Path) -> np.ndarray:
    """A photo file decoded whole to 8-bit BGR (H, W, 3); ValueError naming the file when it
    cannot be read or decoded.

    Decoded from memory: ``cv2.imread`` pads a JPEG whose data is cut off with grey (libjpeg
    only prints a warning), ``cv2.imdecode`` returns nothing for it, as for any cut PNG, WebP,
    BMP or TIFF.
    """
    import cv2

    try:
        data = np.fromfile(path, np.uint8)
    except OSError as e:
        raise ValueError(f"'{path}' cannot be read ({e.strerror})") from None
    try:
        bgr = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    except cv2.error:
        bgr = None
    if bgr is None:
        raise ValueError(f"'{path}' cannot be decoded (truncated or corrupt data)")
    return bgr


@contextlib.contextmanager
def quiet_stderr():
    """File descriptor 2 goes to /dev/null inside the block: the image libraries behind cv2
    print their own lines for a bad file ("Premature end of JPEG file", "libpng error: ...")."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def check_user(path: Path) -> None:
    """Decode a photo once, silently: ValueError naming the file when it is unusable."""
    with quiet_stderr():
        decode_user(path)


def load_user(path: Path) -> np.ndarray:
    """A photo from a --textures folder as linear RGB (H, W, 3), top row first."""
    return srgb_to_linear(decode_user(path)[..., ::-1])


def load_bundled(name: str) -> np.ndarray:
    """A bundled panorama as a tone-mapped linear RGB reflectance map (H, W, 3), top row first."""
    if name not in BUNDLED_PHOTOS:
        raise ValueError(f"unknown bundled photo {name!r}")
    from .formats import read_exr_image

    path = bundled_folder() / name
    bgr = read_exr_image(path)
    if bgr is None:
        raise FileNotFoundError(f"cannot read bundled photo {path}")
    return tone_map(bgr[..., :3][..., ::-1])
