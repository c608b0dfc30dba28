"""Frames in and depth out for ``stillbox-bench infer``: a user's video or folder of frames, the
camera's displacement between frames, and the depth files, colour maps and preview video.

- Frames: a video file (anything OpenCV reads) or a folder of images sorted by name, read one at
  a time, as (H, W, 3) uint8 RGB.
- Geometry: a frame is centre-cropped to the field of view the network was trained with and
  resized to the network's input size (:func:`crop_box`), so a pixel covers the same angle as in
  training.
- Motion: the camera positions (m) of every frame, from a constant speed or a poses CSV;
  d(t, δ) = |p_t − p_{t−δ}| (m) is the displacement between frames t − δ and t.

Errors are FieldError (benchmark.core.errors) of one line naming the InferOptions field
(``input``, ``poses``, ``fps`` …) and the file; the command line names the flags.
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from stillbox_gen.camera import focal_from_fov

from ..core.errors import FieldError, Ref  # noqa: E402

# FFmpeg's own messages about a broken video ("Sample size ... is too large") would precede the
# one-line error that names the file; OpenCV reads this when it opens a video (user's value kept)
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET

#: image files read from a folder of frames (case-insensitive), in name order
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: colour map of the depth PNGs and the preview: near is bright, far is dark (as benchmark plots)
COLORMAP = "magma_r"


# ---------------------------------------------------------------- frames in


class FrameSource:
    """Frames of a video file or of a folder of images, read one at a time.

    ``count``: number of frames (a video's container metadata, else counted by decoding);
    ``fps``: the video's frame rate (frames/s; None for a folder or when the file does not say);
    ``width``, ``height``: frame size (pixels). Opening checks that the first frame decodes.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.exists():
            raise FieldError("input", f"no such file or folder '{self.path}'")
        self.files: list[Path] | None = None
        self.fps: float | None = None
        if self.path.is_dir():
            self.files = sorted(
                p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS
            )
            if not self.files:
                exts = ", ".join(IMAGE_EXTENSIONS)
                raise FieldError("input", f"no image files ({exts}) in folder '{self.path}'")
            self.count = len(self.files)
            first = self._read_image(self.files[0])
        else:
            cap = cv2.VideoCapture(str(self.path))
            ok, frame = cap.read() if cap.isOpened() else (False, None)
            if not ok:
                cap.release()
                raise FieldError("input", f"'{self.path}' is not a readable video")
            fps = cap.get(cv2.CAP_PROP_FPS)
            self.fps = float(fps) if fps > 0 and math.isfinite(fps) else None
            self.count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            if self.count <= 0:
                self.count = 1 + sum(1 for _ in iter(cap.grab, False))
            cap.release()
            first = frame[..., ::-1]
        self.height, self.width = first.shape[:2]

    def _read_image(self, path: Path) -> np.ndarray:
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise FieldError("input", f"cannot read image '{path}'")
        if self.files and path != self.files[0] and img.shape[:2] != (self.height, self.width):
            raise FieldError(
                "input",
                f"'{path}' is {img.shape[1]}x{img.shape[0]}, the first frame "
                f"{self.width}x{self.height}",
            )
        return img[..., ::-1]

    def __iter__(self) -> Iterator[np.ndarray]:
        """The ``count`` frames, (H, W, 3) uint8 RGB, in order. A video that decodes fewer
        frames than its container lists (garbled or cut) is a FieldError on ``input`` with
        both counts, when the first frame that fails is reached."""
        if self.files is not None:
            for p in self.files:
                yield np.ascontiguousarray(self._read_image(p))
            return
        cap = cv2.VideoCapture(str(self.path))
        try:
            for k in range(self.count):
                ok, frame = cap.read()
                if not ok:
                    raise FieldError(
                        "input",
                        f"'{self.path}' decodes {k} of the {self.count} frames its container "
                        f"lists (frame {k} fails): garbled or cut; re-encode it",
                    )
                yield np.ascontiguousarray(frame[..., ::-1])
        finally:
            cap.release()


# ---------------------------------------------------------------- camera geometry


@dataclass(frozen=True)
class Crop:
    """A centred crop box of a video frame (pixels) and its focal-length factor.

    ``factor`` = f_train / f_video-after-crop: 1 when the video covers the training field of view;
    below 1 when the video is narrower, and then depths from lateral motion come out ``factor``
    times the true depth.
    """

    x: int
    y: int
    width: int
    height: int
    factor: float


def focal_px(width: int, fov_deg: float | None = None, focal: float | None = None) -> float:
    """Focal length (pixels) of a camera ``width`` pixels wide: ``focal`` when given, else
    from the horizontal field of view ``fov_deg`` (degrees)."""
    if focal is not None:
        return float(focal)
    return focal_from_fov(fov_deg, width)


def crop_box(
    frame_w: int, frame_h: int, out_w: int, out_h: int, f_video: float, f_train: float
) -> Crop:
    """The centred region of a ``frame_w``×``frame_h`` video frame (focal ``f_video`` px) that,
    resized to ``out_w``×``out_h``, has the training camera's angular resolution (``f_train``: the
    training focal length in pixels of a frame ``out_w`` wide).

    Crop size = (out_w, out_h)·f_video/f_train. When it does not fit in the frame (a video
    narrower than the training field of view in one axis), the largest centred crop of the
    output's aspect ratio, and ``factor`` < 1 says by how much the scale differs.
    """
    w, h = out_w * f_video / f_train, out_h * f_video / f_train
    factor = 1.0
    if round(w) > frame_w or round(h) > frame_h:
        factor = min(frame_w / w, frame_h / h)
        w, h = w * factor, h * factor
    cw, ch = min(frame_w, max(1, round(w))), min(frame_h, max(1, round(h)))
    return Crop((frame_w - cw) // 2, (frame_h - ch) // 2, cw, ch, factor)


def prepare_frame(frame: np.ndarray, crop: Crop, out_w: int, out_h: int) -> np.ndarray:
    """Crop (``crop``) and resize (area interpolation) an RGB frame to out_w×out_h, uint8."""
    region = frame[crop.y : crop.y + crop.height, crop.x : crop.x + crop.width]
    if region.shape[:2] == (out_h, out_w):
        return np.ascontiguousarray(region)
    return cv2.resize(region, (out_w, out_h), interpolation=cv2.INTER_AREA)


# ---------------------------------------------------------------- camera motion


def constant_speed_positions(speed: float, fps: float, frames: int) -> np.ndarray:
    """Positions (frames, 3) in metres of a camera moving at ``speed`` m/s along x, one frame
    every 1/``fps`` s: d(t, δ) = speed·δ/fps."""
    p = np.zeros((frames, 3))
    p[:, 0] = speed * np.arange(frames) / fps
    return p


def read_poses(
    path: str | Path, frames: int, fps: float | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Camera positions (frames, 3) in metres from a CSV, and its ``t`` column (s) if any.

    Columns (header row, any order, extra columns ignored): ``x,y,z`` positions (m), or
    ``vx,vy,vz`` velocities (m/s) integrated with the trapezoid rule from position 0 at times
    ``t`` (s, increasing) or frame/``fps``. One row per frame.
    """
    where = f" {path}"
    try:
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as e:
        raise FieldError("poses", f"cannot read it ({e.__class__.__name__})", where=where) from None
    if not rows:
        raise FieldError("poses", "empty file, expected a header row", where=where)
    header = [c.strip() for c in rows[0]]
    kind = "xyz" if {"x", "y", "z"} <= set(header) else None
    kind = kind or ("v" if {"vx", "vy", "vz"} <= set(header) else None)
    if kind is None:
        raise FieldError(
            "poses", f"header must have columns x,y,z or vx,vy,vz, got {header}", where=where
        )
    names = ["x", "y", "z"] if kind == "xyz" else ["vx", "vy", "vz"]
    has_t = "t" in header
    cols = [header.index(n) for n in names + (["t"] if has_t else [])]
    body = rows[1:]
    if len(body) != frames:
        raise FieldError(
            "poses", f"{len(body)} rows for {frames} frames; give one row per frame", where=where
        )
    values = np.array([_row(where, r, n + 2, header, cols) for n, r in enumerate(body)])
    if has_t and len(values) > 1 and not (np.diff(values[:, 3]) > 0).all():
        row = int(np.argmin(np.diff(values[:, 3]) > 0)) + 3
        raise FieldError("poses", f"row {row}, column 't': times must increase", where=where)
    times = values[:, 3] if has_t else None
    if kind == "xyz":
        return values[:, :3], times
    if not has_t and fps is None:
        raise FieldError(
            "fps", "needed to integrate the velocities of ", Ref("poses"), " (no 't' column)"
        )
    t = times if times is not None else np.arange(frames) / fps
    v = values[:, :3]
    steps = (v[1:] + v[:-1]) / 2 * np.diff(t)[:, None]
    return np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)]), times


def _row(where: str, row: list[str], line: int, header: list[str], cols: list[int]) -> list[float]:
    """The numbers of ``cols`` in one CSV row (``line``: its line number in the file)."""
    out = []
    for c in cols:
        text = row[c].strip() if c < len(row) else ""
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise FieldError(
                "poses", f"row {line}, column '{header[c]}': not a number '{text}'", where=where
            )
        out.append(value)
    return out


# ---------------------------------------------------------------- outputs


def colour_lut(name: str = COLORMAP) -> np.ndarray:
    """(256, 3) uint8 RGB of a matplotlib colour map."""
    import matplotlib

    return np.round(matplotlib.colormaps[name](np.linspace(0, 1, 256))[:, :3] * 255).astype(
        np.uint8
    )


def colourise(depth: np.ndarray, max_depth: float, lut: np.ndarray) -> np.ndarray:
    """(H, W) depth (m) → (H, W, 3) uint8 RGB on the fixed range 0..``max_depth`` m (the same
    mapping for every frame, so a video does not flicker); farther values take the last colour."""
    index = np.clip(np.nan_to_num(depth, nan=max_depth) / max_depth * 255, 0, 255)
    return lut[np.round(index).astype(np.int64)]


def write_depth(path: Path, depth: np.ndarray) -> None:
    """A float32 depth map (m) as ``.npy`` or ``.exr`` (single channel "Y", the dataset's own
    depth format, stillbox_gen.formats), chosen by ``path``'s suffix."""
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    if path.suffix == ".exr":
        from stillbox_gen.formats import write_depth_exr

        write_depth_exr(path, depth)
    else:
        np.save(path, depth)


def write_png(path: Path, rgb: np.ndarray) -> None:
    """An (H, W, 3) uint8 RGB image as PNG."""
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise OSError(f"cannot write '{path}'")


class PreviewWriter:
    """An MP4 (codec mp4v) of frames side by side: the network's input frame | its depth colours."""

    def __init__(self, path: Path, fps: float, width: int, height: int):
        self.path, self.size = path, (2 * width, height)
        self.writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, self.size)
        if not self.writer.isOpened():
            raise OSError(f"cannot write video '{path}' (no mp4v encoder?)")

    def write(self, rgb: np.ndarray, colours: np.ndarray) -> None:
        self.writer.write(np.ascontiguousarray(np.concatenate([rgb, colours], axis=1)[..., ::-1]))

    def close(self) -> None:
        self.writer.release()
