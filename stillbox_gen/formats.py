"""On-disk format of a StillBox-gen dataset (documented in docs/FORMAT.md): names, records, I/O.

Layout under the dataset root::

    dataset.json            generator, versions, parameters, counts ("complete": true when done)
    manifest.parquet        one row per frame (schema: MANIFEST_SCHEMA)
    <chunk>/                integer-named folders of CHUNK_SIZE scenes (chunk = index // 200)
        metadata.json       {"args": {...}, "scenes": [record, ...]} (original StillBox keys kept)
        RGB_<s>_<f>.png     8-bit sRGB frames, s = scene index in the chunk, f = frame
        depth_<s>_<f>.exr   float32 planar depth in metres, single channel "Y", ZIP compressed
        .records/<s>.json   per-scene record; its presence marks the scene complete

Every path read from a dataset (a record's file names, the manifest's paths) goes through
:func:`resolve_inside`, so a crafted dataset cannot make a reader open or write a file outside it.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path, PurePosixPath

import numpy as np

from .config import ConfigError

CHUNK_SIZE = 200
FORMAT_VERSION = 1
NO_SURFACE_DEPTH = 1e10  # what Cycles writes where a ray hits nothing within max_distance
DEPTH_CONVENTION = (
    "planar depth z along the camera optical axis (OpenCV +z), metres, float32, one value per "
    "pixel sampled at the pixel centre, not clipped; pixels whose ray meets no surface within "
    f"args.max_distance hold {NO_SURFACE_DEPTH:g}"
)


def canonical_json(obj) -> str:
    """Deterministic JSON text (sorted keys, no whitespace) used for hashing."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def chunk_name(index: int) -> str:
    return str(index // CHUNK_SIZE)


def local_index(index: int) -> int:
    return index % CHUNK_SIZE


def rgb_name(local: int, frame: int, ext: str = "png") -> str:
    return f"RGB_{local:04d}_{frame:02d}.{ext}"


def depth_name(local: int, frame: int, ext: str = "exr") -> str:
    return f"depth_{local:04d}_{frame:02d}.{ext}"


RECORDS_DIR = ".records"
METADATA_JSON = "metadata.json"


def record_name(index: int) -> str:
    """``<chunk>/.records/<s>.json``, relative to the dataset root."""
    return f"{chunk_name(index)}/{RECORDS_DIR}/{local_index(index):04d}.json"


def record_path(root: Path, index: int) -> Path:
    return Path(root) / record_name(index)


# Files ``stillbox-gen stats`` writes into the dataset root by default (not part of the format)
STATS_FILES = ("stats.json", "stats.png")


def scene_files(record: dict) -> list[str]:
    """Every file name of a scene in its chunk folder (frames, depth, legacy copies), sorted."""
    names = [*record["rgb"], *record["depth_exr"], *record["imgs"], *record["depth"]]
    return sorted(set(names))


# ---------------------------------------------------------------- paths read from a dataset


class UnsafePathError(ConfigError):
    """A path read from a dataset that would lead outside the dataset folder."""


def resolve_inside(root: Path, relpath: str, what: str, folder: str = "") -> Path:
    """``root / folder / relpath``, checked to stay inside ``root`` before anything is opened.

    ``relpath`` comes from a dataset file (a record's file name, relative to its chunk
    ``folder``; a manifest path, relative to the root): it must be a relative path without
    ``..`` components, and no symlink on its way may lead outside ``root`` (links are read, no
    file is opened). Raises UnsafePathError starting with ``what`` (the record or row it comes
    from).
    """
    root = Path(root)
    if not isinstance(relpath, str) or not relpath or "\x00" in relpath:
        raise UnsafePathError(f"{what}: {relpath!r} is not a file name")
    pure = PurePosixPath(relpath)
    if pure.is_absolute():
        raise UnsafePathError(f"{what}: absolute path '{relpath}' leaves the dataset folder")
    if ".." in pure.parts:
        raise UnsafePathError(f"{what}: path '{relpath}' has '..' and leaves the dataset folder")
    path = root / folder / relpath
    try:  # reads symlinks, opens nothing
        real, base = Path(os.path.realpath(path)), Path(os.path.realpath(root))
    except (OSError, RuntimeError) as e:  # a symlink loop
        raise UnsafePathError(f"{what}: cannot resolve '{relpath}' ({e})") from None
    if not real.is_relative_to(base):
        raise UnsafePathError(
            f"{what}: '{relpath}' leads through a symlink to '{real}', outside the dataset folder"
        )
    return path


# ---------------------------------------------------------------- checksums


def file_sha256(path: Path) -> str:
    """SHA-256 hex digest of a file's bytes."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def scene_checksums(folder: Path, record: dict) -> dict[str, str]:
    """{file name: SHA-256} of every file of a scene (:func:`scene_files`) found in ``folder``;
    stored in the record as ``sha256``."""
    return {name: file_sha256(Path(folder) / name) for name in scene_files(record)}


# ---------------------------------------------------------------- atomic writes


def atomic_write_text(path: Path, text: str) -> None:
    """Write via a temporary name in the same folder, fsync, then rename."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def atomic_write_json(path: Path, obj, indent: int | None = None) -> None:
    atomic_write_text(path, json.dumps(obj, indent=indent, allow_nan=False) + "\n")


def remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


# ---------------------------------------------------------------- depth EXR


def write_depth_exr(path: Path, depth: np.ndarray) -> None:
    """Single-channel float32 EXR (channel "Y", so OpenCV reads it as a grey image), ZIP."""
    import OpenEXR

    depth = np.ascontiguousarray(depth, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"Y": depth}).write(str(path))


def read_depth_exr(path: Path) -> np.ndarray:
    """Depth map (H, W) float32 in metres from a file written by :func:`write_depth_exr`."""
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        if "Y" not in channels:
            raise ValueError(f"{path}: no 'Y' channel (has {sorted(channels)})")
        return np.array(channels["Y"].pixels, dtype=np.float32)


def read_multilayer_exr(path: Path) -> dict[str, np.ndarray]:
    """All channels of a (possibly multi-part) EXR, by full channel name."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=False) as f:
        return {name: ch.pixels for part in f.parts for name, ch in part.channels.items()}


def linear_to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """8-bit sRGB of linear RGB (the 'Standard' view transform, no exposure, no look)."""
    x = np.clip(rgb, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


# ---------------------------------------------------------------- metadata records


def scene_record(spec: dict, image_format: str, legacy: bool) -> dict:
    """The metadata.json entry of one scene, built from its SceneSpec dict.

    Original StillBox keys first (imgs, depth, speed, time_step, length, orientation), then ours;
    ``sha256`` (:func:`scene_checksums`) is added last, once the files are written.
    """
    cam = spec["camera"]
    local, n = local_index(spec["index"]), len(cam["cam2world"])
    rgb = [rgb_name(local, f, image_format) for f in range(n)]
    exr = [depth_name(local, f) for f in range(n)]
    c2w = [np.array(m) for m in cam["cam2world"]]
    w2c = [np.linalg.inv(m) for m in c2w]
    displacement = float(np.linalg.norm(cam["speed"]) * cam["time_step"])
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
    }


def chunk_args(cfg_dict: dict, generator: str) -> dict:
    """The ``args`` block of every metadata.json: original keys plus every generator parameter."""
    from .camera import fov_from_focal

    cam = cfg_dict["camera"]
    focal = cam["focal_px"]
    fov = cam["fov_deg"] if focal is None else fov_from_focal(focal, cam["width"])
    return {
        "fov": fov,
        "resolution": [cam["width"], cam["height"]],
        "frames": cam["frames"],
        "displacement": cam["displacement"],
        "max_distance": cfg_dict["render"]["max_distance"],
        "depth_convention": DEPTH_CONVENTION,
        "generator": generator,
        "format_version": FORMAT_VERSION,
        "config": cfg_dict,
    }
