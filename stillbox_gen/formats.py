"""File formats of a StillBox-gen dataset (docs/FORMAT.md): depth EXR, 8-bit sRGB frames, JSON
written atomically, SHA-256 checksums, and the check that a path read from a dataset stays inside
it. Where each file lives is stillbox_gen.layout; writing whole datasets is stillbox_gen.writer,
reading them stillbox_gen.dataset.

Every path read from a dataset (a record's file names, the manifest's paths) goes through
:func:`resolve_inside`, so a crafted dataset cannot make a reader open or write a file outside it.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path, PurePosixPath
from typing import BinaryIO

import numpy as np

from .errors import DatasetError

# OpenCV decodes and encodes EXR files only when OPENCV_IO_ENABLE_OPENEXR is set (off by default
# since OpenCV 4.5.2, for security: opencv/opencv#21326). OpenCV reads the variable at its first
# EXR file, not when cv2 is imported, so setting it here, when the file formats are loaded (before
# any EXR is read: cv2 is imported inside functions), enables it for every later use, in this
# process and in the workers it spawns: read_exr_image (the panoramas bundled with bpy) and tests
# reading depth maps with cv2. The dataset's depth maps are read and written with OpenEXR itself.
os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")

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


# ---------------------------------------------------------------- paths read from a dataset


class UnsafePathError(DatasetError):
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


# ---------------------------------------------------------------- atomic writes


TEMP_INFIX = ".tmp-"  # a file or folder being written: .<name>.tmp-<pid> (temp_path)


def temp_path(path: Path) -> Path:
    """Where ``path`` (a file or a folder) is written before it is renamed to its name: the
    hidden ``.<name>.tmp-<pid>`` beside it, one per process (two writers never share one)."""
    path = Path(path)
    return path.with_name(f".{path.name}{TEMP_INFIX}{os.getpid()}")


def atomic_write(path: Path, write: Callable[[BinaryIO], None], sync_folder: bool = False) -> None:
    """``write(f)`` into :func:`temp_path` of ``path``, fsync it, rename it over ``path`` (then
    fsync the folder when ``sync_folder``): a kill or power cut leaves the old file or the new
    one, never half of one. On any failure the temporary file is deleted; an OSError names
    ``path`` (e.g. a full disk, see :func:`is_disk_full`)."""
    path = Path(path)
    tmp = temp_path(path)
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        tmp.unlink(missing_ok=True)
        if isinstance(e, OSError) and e.filename is None:  # a failed write() names no file
            raise OSError(e.errno, e.strerror, str(path)) from e
        raise
    if sync_folder:
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """:func:`atomic_write` of ``data``."""
    atomic_write(path, lambda f: f.write(data))


def atomic_write_text(path: Path, text: str) -> None:
    """:func:`atomic_write_bytes` of ``text`` in UTF-8."""
    atomic_write_bytes(path, text.encode())


def atomic_write_json(path: Path, obj, indent: int | None = None) -> None:
    atomic_write_text(path, json.dumps(obj, indent=indent, allow_nan=False) + "\n")


# ---------------------------------------------------------------- a full disk

#: errno values of a write refused for lack of space: the disk is full, or the user's quota is
DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
PROBE_NAME = ".space-probe"  # written and deleted by check_space


def is_disk_full(e: BaseException) -> bool:
    """True for an OSError meaning no space is left (:data:`DISK_FULL_ERRNOS`)."""
    return isinstance(e, OSError) and e.errno in DISK_FULL_ERRNOS


def check_space(folder: Path, nbytes: int) -> None:
    """Raise the OSError of a full disk (naming ``folder``) when ``nbytes`` bytes cannot be
    written into ``folder`` now: a probe file is written, fsynced and deleted. For writers that
    do not report errno (Blender's EXR output, OpenCV's imwrite), after one of their writes
    failed."""
    probe = Path(folder) / PROBE_NAME
    try:
        with open(probe, "wb") as f:
            f.write(bytes(nbytes))
            f.flush()
            os.fsync(f.fileno())
    except OSError as e:
        if is_disk_full(e):
            raise OSError(e.errno, e.strerror, str(folder)) from None
        raise
    finally:
        probe.unlink(missing_ok=True)


#: how a generator run goes on after a full disk (the end of :func:`disk_full_message`)
RESUME_SCENES = "finished scenes are kept: free space, then re-run the same command to resume"


def disk_full_message(e: OSError, then: str = RESUME_SCENES) -> str:
    """One line for a full disk: what could not be written, and how to go on (``then``)."""
    where = f" writing '{e.filename}'" if e.filename else ""
    return f"disk full{where} ({e.strerror}); {then}"


def remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


# ---------------------------------------------------------------- frames and depth


def read_rgb(path: Path) -> np.ndarray:
    """An 8-bit frame (PNG or JPEG) as (H, W, 3) uint8 in RGB order (sRGB values, 0-255).
    DatasetError naming the file when it is missing or does not decode."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(f"cannot read image '{path}'")
    return img[..., ::-1].copy()


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


def read_depth(path: Path) -> np.ndarray:
    """:func:`read_depth_exr` of a dataset's file: DatasetError naming the file when it is
    missing or unreadable."""
    try:
        return read_depth_exr(path)
    except Exception as e:  # noqa: BLE001 - any reader failure is the dataset's file
        raise DatasetError(f"cannot read depth '{path}' ({e})") from None


def read_exr_image(path: Path) -> np.ndarray | None:
    """An EXR image as OpenCV reads it (float32, BGR or BGRA channel order), None when it cannot
    be read."""
    import cv2

    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


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


# ---------------------------------------------------------------- optical flow and masks

#: Middlebury .flo: the float32 magic number 202021.25 ("PIEH" in little-endian bytes), then
#: int32 width and height, then float32 (u, v) per pixel, row by row (u right, v down, pixels).
FLO_MAGIC = 202021.25
#: Middlebury's "unknown flow": values above 1e9 mean no flow; stillbox-gen writes this there.
FLO_UNKNOWN = 1e10


def flo_bytes(flow: np.ndarray) -> bytes:
    """The Middlebury .flo bytes of an (H, W, 2) flow in pixels (NaN written as FLO_UNKNOWN)."""
    flow = np.asarray(flow)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow must be (H, W, 2), got {flow.shape}")
    h, w = flow.shape[:2]
    data = np.nan_to_num(flow.astype("<f4"), nan=FLO_UNKNOWN)
    head = np.array([FLO_MAGIC], "<f4").tobytes() + np.array([w, h], "<i4").tobytes()
    return head + np.ascontiguousarray(data).tobytes()


def write_flo(path: Path, flow: np.ndarray) -> None:
    """Write an (H, W, 2) flow (pixels, channel 0 x right, 1 y down) as Middlebury .flo,
    atomically (:func:`atomic_write`)."""
    atomic_write_bytes(path, flo_bytes(flow))


def read_flo(path: Path) -> np.ndarray:
    """An (H, W, 2) float32 flow from a Middlebury .flo file, values as stored (Middlebury's
    unknown flow is above 1e9). DatasetError naming the file when it is missing, its magic
    number is not 202021.25 or its size disagrees with its header."""
    return decode_flo(read_file(path, "flow"), str(path))


def decode_flo(data: bytes, where: str) -> np.ndarray:
    """:func:`read_flo` of a .flo file's bytes; ``where`` names it in a DatasetError."""
    if len(data) < 12 or np.frombuffer(data[:4], "<f4")[0] != np.float32(FLO_MAGIC):
        raise DatasetError(f"'{where}': not a .flo file (magic number is not {FLO_MAGIC})")
    w, h = (int(v) for v in np.frombuffer(data[4:12], "<i4"))
    if w < 1 or h < 1 or len(data) != 12 + 8 * w * h:
        raise DatasetError(f"'{where}': {len(data)} bytes, not a {w}x{h} .flo file")
    return np.frombuffer(data[12:], "<f4").reshape(h, w, 2).astype(np.float32)


def read_file(path: Path, what: str) -> bytes:
    """The bytes of a dataset's file; DatasetError ("cannot read <what> '<path>' (...)") when
    it cannot be read."""
    try:
        return Path(path).read_bytes()
    except OSError as e:
        raise DatasetError(f"cannot read {what} '{path}' ({e.strerror})") from None


# KITTI's 16-bit flow PNG (--flow-format kitti-png), as the KITTI 2015 devkit writes it: three
# uint16 channels in the file's order R, G, B = u, v, valid; u and v (pixels, x right, y down)
# stored as round(flow * 64) + 2**15, valid 1 or 0 (u = v = 0 where 0). OpenCV's arrays are in
# B, G, R order: valid is channel 0 there, u channel 2.
KITTI_SCALE = 64  # steps per pixel: the flow is stored to 1/64 px (rounded: within 1/128 px)
KITTI_OFFSET = 2**15


def kitti_representable(flow: np.ndarray) -> np.ndarray:
    """(H, W) bool: where an (H, W, 2) flow (pixels) fits KITTI's 16 bits once rounded, both
    components in [−512, 511 + 63/64] px (NaN does not)."""
    with np.errstate(invalid="ignore"):
        steps = np.rint(np.asarray(flow, np.float64) * KITTI_SCALE) + KITTI_OFFSET
        return np.all((steps >= 0) & (steps <= 65535), axis=-1)


def kitti_flow_bytes(flow: np.ndarray, valid: np.ndarray) -> bytes:
    """The KITTI 16-bit PNG bytes of an (H, W, 2) flow in pixels and its (H, W) valid mask,
    which must hold only representable flow (:func:`kitti_representable`; ValueError
    otherwise): u and v rounded to 1/64 px, 0 where not valid."""
    import cv2

    flow, valid = np.asarray(flow, np.float64), np.asarray(valid, bool)
    if flow.ndim != 3 or flow.shape[2] != 2 or valid.shape != flow.shape[:2]:
        raise ValueError(
            f"flow must be (H, W, 2) and valid (H, W), got {flow.shape}, {valid.shape}"
        )
    if np.any(valid & ~kitti_representable(flow)):
        raise ValueError("flow beyond KITTI's range (about ±512 px) at a valid pixel")
    steps = np.where(valid[..., None], np.rint(np.nan_to_num(flow) * KITTI_SCALE), -KITTI_OFFSET)
    uv = (steps + KITTI_OFFSET).astype(np.uint16)
    bgr = np.stack([valid.astype(np.uint16), uv[..., 1], uv[..., 0]], axis=-1)
    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise ValueError("cannot encode a KITTI flow PNG")
    return buf.tobytes()


def write_kitti_flow(path: Path, flow: np.ndarray, valid: np.ndarray) -> None:
    """Write :func:`kitti_flow_bytes` atomically (:func:`atomic_write`)."""
    atomic_write_bytes(path, kitti_flow_bytes(flow, valid))


def decode_kitti_flow(data: bytes, where: str) -> tuple[np.ndarray, np.ndarray]:
    """``(flow, valid)`` of a KITTI flow PNG's bytes: (H, W, 2) float32 pixels, (value − 2**15)
    / 64 (where not valid, the stored 0 reads as −512), and the (H, W) bool valid channel.
    DatasetError naming ``where`` when it is no 3-channel 16-bit PNG or its valid channel holds
    other values than 0 and 1."""
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint16:
        raise DatasetError(f"cannot read flow '{where}' (not a 3-channel 16-bit KITTI flow PNG)")
    if not np.isin(img[..., 0], (0, 1)).all():
        raise DatasetError(f"'{where}': the valid channel of a KITTI flow PNG holds only 0 and 1")
    uv = img[..., 2:0:-1].astype(np.float32)  # B, G, R -> u (R), v (G)
    return (uv - KITTI_OFFSET) / KITTI_SCALE, img[..., 0] == 1


def decode_flow(data: bytes, where: str) -> tuple[np.ndarray, np.ndarray | None]:
    """A flow file's bytes by the extension of its name ``where``: ``(flow, None)`` of a .flo
    file (values as stored), ``(flow, valid channel)`` of a KITTI PNG (--flow-format)."""
    if where.endswith(".png"):
        return decode_kitti_flow(data, where)
    return decode_flo(data, where), None


def write_mask_png(path: Path, mask: np.ndarray) -> None:
    """Write an (H, W) boolean mask as an 8-bit grey PNG (255 true, 0 false), atomically."""
    import cv2

    ok, buf = cv2.imencode(".png", np.where(np.asarray(mask, bool), 255, 0).astype(np.uint8))
    if not ok:
        raise OSError(f"cannot encode '{path}'")
    atomic_write_bytes(path, buf.tobytes())


def read_mask_png(path: Path) -> np.ndarray:
    """An (H, W) boolean mask from :func:`write_mask_png`'s file. DatasetError naming the file
    when it is missing, does not decode or holds values other than 0 and 255."""
    try:
        data = Path(path).read_bytes()
    except OSError:
        data = b""
    return decode_mask_png(data, str(path))


def decode_mask_png(data: bytes, where: str) -> np.ndarray:
    """:func:`read_mask_png` of a mask file's bytes; ``where`` names it in a DatasetError."""
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if img is None or img.ndim != 2 or img.dtype != np.uint8:
        raise DatasetError(f"cannot read mask '{where}' (missing, or not an 8-bit grey PNG)")
    if not np.isin(img, (0, 255)).all():
        raise DatasetError(f"'{where}': a mask holds only 0 and 255")
    return img == 255
