"""Footage and a depth network, checked and opened before anything is written (``infer``'s
options, read by ``finetune`` too).

:func:`prepare` checks an :class:`InferOptions` (units: m, m/s, frames/s, degrees, pixels,
frames), loads the checkpoint's depth network (or an ONNX file of ``stillbox-bench export``) with
its depth scale and training camera (benchmark.engine.network), opens the footage
(benchmark.core.footage: a video file or a folder of frames), reads or makes the camera positions
(metres, one row per frame) and fits the crop: frames are centre-cropped to the training field of
view and resized to the network's input size (core.footage.crop_box). Errors are one-line
FieldErrors naming the InferOptions field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from stillbox_gen.arguments import unwritable
from stillbox_gen.conventions import MAX_DEPTH
from stillbox_gen.layout import enclosing_dataset

from ..core import footage
from ..core.errors import FieldError, Ref
from ..core.multishift import BETA_MAX, BETA_MEAN, BETA_MIN, EMA_LAMBDA, MAX_SHIFTS, DepthScale
from .export import onnx_depth_network
from .network import depth_network

MIN_MAX_SHIFT = 8  # smallest default --max-shift (frames)
MAX_MAX_SHIFT = 1000  # largest default --max-shift (frames kept in memory)
#: largest side (pixels) of the network input (--res): the preview puts frame and depth side
#: by side, 2·W wide, within the mp4v encoder's 8191 px; DepthNet's forward pass at 2048x2048
#: takes 0.8 GB and 4 s on one CPU thread (a frame's --shifts 4 pairs: about 3 GB)
MAX_RES = 2048


@dataclass
class InferOptions:
    """The command line's options (units: m, m/s, frames/s, degrees, pixels, frames)."""

    ckpt: Path
    input: Path
    out: Path
    speed: float | None = None
    fps: float | None = None
    poses: Path | None = None
    fov: float | None = None
    focal: float | None = None
    res: tuple[int, int] | None = None
    train_fov: float | None = None
    shifts: int = 1
    fixed_shift: int | None = None
    max_shift: int | None = None
    ema: float = EMA_LAMBDA
    beta_mean: float = BETA_MEAN
    depth_format: str = "npy"
    max_depth: float = MAX_DEPTH
    device: str = "auto"
    quiet: bool = False


@dataclass
class Job:
    """Everything checked and opened, before anything is written."""

    source: footage.FrameSource
    model: torch.nn.Module
    scale: DepthScale
    info: dict
    positions: np.ndarray  # (frames, 3) metres
    fps: float  # frames/s of the preview
    crop: footage.Crop
    size: tuple[int, int]  # network input (width, height), pixels
    max_shift: int
    device: torch.device
    focals: dict = field(default_factory=dict)  # video and training focal lengths, pixels
    warning: str | None = None


def _positive(name: str, value: float | None) -> None:
    if value is not None and not (value > 0 and math.isfinite(value)):
        raise FieldError(name, f"must be a positive number, got {value}")


def check_options(o: InferOptions, out: bool = True) -> None:
    """The numeric options and (``out``) the ``out`` folder (FieldError naming the InferOptions
    field); reads no file."""
    if (o.speed is None) == (o.poses is None):
        raise FieldError(
            "speed", "give either ", Ref("speed"), " M/S or ", Ref("poses"), " CSV (exactly one)"
        )
    for name in ("speed", "fps", "focal", "max_depth"):
        _positive(name, getattr(o, name))
    for name in ("fov", "train_fov"):
        fov = getattr(o, name)
        if fov is not None and not 0 < fov < 180:
            raise FieldError(name, f"must be in (0, 180) degrees, got {fov}")
    if o.fov is not None and o.focal is not None:
        raise FieldError("focal", "give ", Ref("fov"), " or ", Ref("focal"), ", not both")
    if not 1 <= o.shifts <= MAX_SHIFTS:
        raise FieldError("shifts", f"must be in 1..{MAX_SHIFTS}, got {o.shifts}")
    if o.fixed_shift is not None and (o.fixed_shift < 1 or o.shifts != 1):
        raise FieldError(
            "fixed_shift", "must be at least 1, with ", Ref("shifts"), " 1 (one pair a frame)"
        )
    if o.max_shift is not None and o.max_shift < 1:
        raise FieldError("max_shift", f"must be at least 1, got {o.max_shift}")
    if not 0 <= o.ema < 1:
        raise FieldError("ema", f"must be in [0, 1), got {o.ema}")
    if not BETA_MIN < o.beta_mean < BETA_MAX:
        raise FieldError("beta_mean", f"must be in ({BETA_MIN}, {BETA_MAX}), got {o.beta_mean}")
    if o.train_fov is not None and o.res is None:
        raise FieldError("train_fov", "give ", Ref("res"), " WxH too (the training frame size)")
    if out and o.out.exists() and (not o.out.is_dir() or any(o.out.iterdir())):
        raise FieldError("out", f"'{o.out}' exists and is not an empty folder")
    dataset = enclosing_dataset(o.out) if out else None
    if dataset is not None:
        raise FieldError("out", f"'{o.out}' is inside the dataset '{dataset}'; write elsewhere")
    if out and (problem := unwritable(o.out)):
        raise FieldError("out", problem)


def _motion(o: InferOptions, source: footage.FrameSource) -> tuple[np.ndarray, float]:
    """Camera positions (frames, 3) m and the frame rate (frames/s) of the preview."""
    fps = o.fps or source.fps
    if o.speed is not None:
        if fps is None:
            raise FieldError(
                "fps", "needed with ", Ref("speed"), " (the input does not give its frame rate)"
            )
        return footage.constant_speed_positions(o.speed, fps, source.count), fps
    positions, times = footage.read_poses(o.poses, source.count, fps)
    if fps is None and times is not None and len(times) > 1:
        fps = 1.0 / float(np.median(np.diff(times)))
    if fps is None:
        raise FieldError(
            "fps", "needed for a folder of frames (no 't' column in ", Ref("poses"), ")"
        )
    return positions, fps


def default_max_shift(positions: np.ndarray, d0: float) -> int:
    """Twice the shift whose displacement reaches d0 (m) at the median speed, at least
    MIN_MAX_SHIFT, at most MAX_MAX_SHIFT: the far target d_opt = θ_max/(α·β_mean) is 2·d0."""
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    steps = steps[steps > 0]
    if not len(steps):
        return MIN_MAX_SHIFT
    return int(min(MAX_MAX_SHIFT, max(MIN_MAX_SHIFT, 2 * math.ceil(d0 / np.median(steps)))))


def _geometry(o: InferOptions, info: dict, source: footage.FrameSource) -> tuple:
    """Network input size, crop box, focal lengths and the field-of-view warning (or None)."""
    w, h = o.res or (info["width"], info["height"])
    if w % 64 or h % 64 or not (64 <= w <= MAX_RES and 64 <= h <= MAX_RES):
        whose = (" (the training size of ", Ref("ckpt"), f" {o.ckpt}; give ", Ref("res"), ")")
        raise FieldError(
            "res",
            f"the network needs multiples of 64 pixels from 64 to {MAX_RES}, got {w}x{h}",
            *(() if o.res else whose),
        )
    f_train = footage.focal_px(w, info["fov_deg"])
    f_video = footage.focal_px(source.width, o.fov or info["fov_deg"], o.focal)
    crop = footage.crop_box(source.width, source.height, w, h, f_video, f_train)
    focals = {"video_focal_px": f_video, "train_focal_px_at_output": f_train}
    warning = None
    if crop.factor < 1:
        warning = (
            f"the video's field of view is narrower than the training one: its pixels are "
            f"{1 / crop.factor:.3g}x finer after the largest crop, so depths from lateral motion "
            f"are biased by a factor {crop.factor:.3g}"
        )
    return (w, h), crop, focals, warning


def _check_fixed_shift(o: InferOptions, frames: int) -> None:
    """``fixed_shift`` within what the input allows: below its ``frames`` frames and at most
    ``max_shift`` (FieldError). Frames t < shift still use shift t (all there is)."""
    shift = o.fixed_shift
    if shift is not None and shift >= frames:
        raise FieldError(
            "fixed_shift",
            f"{shift} frames, but '{o.input}' has {frames} frames (at most {frames - 1})",
        )
    if shift is not None and o.max_shift is not None and shift > o.max_shift:
        raise FieldError("fixed_shift", f"{shift} is above ", Ref("max_shift"), f" {o.max_shift}")


def prepare(o: InferOptions, out: bool = True) -> Job:
    """Check every option and input (the ``out`` folder too when ``out``), load the network: a
    one-line ValueError (FieldError naming the InferOptions field). Nothing is written."""
    from ..core.device import resolve_device

    check_options(o, out)
    exported = o.ckpt.suffix == ".onnx"  # an ONNX file of `stillbox-bench export` runs on the CPU
    device = resolve_device("cpu" if exported else o.device)
    camera = None
    if o.train_fov is not None:
        camera = {"width": o.res[0], "height": o.res[1], "fov_deg": o.train_fov}
    if not o.ckpt.is_file():
        raise FieldError("ckpt", f"no such file '{o.ckpt}'")
    load = onnx_depth_network if exported else depth_network
    model, scale, info = load(o.ckpt, "ckpt", camera)
    fixed = (info["width"], info["height"])
    if exported and o.res is not None and tuple(o.res) != fixed:
        raise FieldError("res", f"the ONNX file {o.ckpt} takes {fixed[0]}x{fixed[1]} frames only")
    source = footage.FrameSource(o.input)
    _check_fixed_shift(o, source.count)
    positions, fps = _motion(o, source)
    size, crop, focals, warning = _geometry(o, info, source)
    max_shift = o.max_shift or max(default_max_shift(positions, scale.d0), o.fixed_shift or 1)
    return Job(
        source, model.to(device), scale, info, positions, fps, crop, size, max_shift, device,
        focals, warning,
    )  # fmt: skip
