"""``stillbox-bench infer``: depth maps of a user's own stabilised video (thesis chapter 6).

For every frame t ≥ 1 the network sees n pairs (I_{t−δ_i}, I_t), one batch, with the frame shifts
δ_i chosen by :class:`benchmark.video.multishift.ShiftPlanner` from the depth of the previous
frames; each output is scaled by its pair's displacement d(t, δ_i) (eq. 6.1) and the n maps are
fused (eq. 6.3). The depth belongs to frame t (the later frame of each pair); frame 0 has no earlier
frame and gets none. Frames are centre-cropped to the training field of view and resized to the
network's input size (benchmark.video.footage.crop_box).

Outputs (``--out``, written in a temporary sibling folder and renamed at the end, so an error
leaves nothing half written): ``depth/NNNNNN.npy|exr`` (float32 metres, NNNNNN = frame index),
``depth_png/NNNNNN.png`` (colour map, 0..max_depth m), ``preview.mp4`` (frame | depth colours),
``frames.csv`` (one row per frame) and ``summary.json``.
"""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from stillbox_gen.arguments import unwritable
from stillbox_gen.conventions import MAX_DEPTH
from stillbox_gen.formats import temp_path
from stillbox_gen.layout import enclosing_dataset

from ..core.data import normalise
from ..core.errors import FieldError, Ref
from ..core.metrics import upsample_to
from . import footage
from .export import onnx_depth_network
from .multishift import (
    BETA_MAX,
    BETA_MEAN,
    BETA_MIN,
    EMA_LAMBDA,
    MAX_SHIFTS,
    DepthScale,
    ShiftPlanner,
    displacements,
    fuse,
)
from .network import depth_network

MIN_MAX_SHIFT = 8  # smallest default --max-shift (frames)
MAX_MAX_SHIFT = 1000  # largest default --max-shift (frames kept in memory)
#: largest side (pixels) of the network input (--res): the preview puts frame and depth side
#: by side, 2·W wide, within the mp4v encoder's 8191 px; DepthNet's forward pass at 2048x2048
#: takes 0.8 GB and 4 s on one CPU thread (a frame's --shifts 4 pairs: about 3 GB)
MAX_RES = 2048
FIRST_FRAME = "frame 0 has no earlier frame: no depth for it"
CSV_COLUMNS = ("frame", "status", "shifts", "displacements_m", "d_opt_m", "mean_depth_m")


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


class Outputs:
    """The files of one inference, written into ``folder``."""

    def __init__(self, folder: Path, job: Job, depth_format: str, max_depth: float):
        self.folder, self.suffix, self.max_depth = folder, f".{depth_format}", max_depth
        (folder / "depth").mkdir(parents=True)
        (folder / "depth_png").mkdir()
        self.lut = footage.colour_lut()
        self.preview = footage.PreviewWriter(folder / "preview.mp4", job.fps, *job.size)
        self.csv_file = open(folder / "frames.csv", "w", newline="")  # noqa: SIM115 - closed by close()
        self.csv = csv.writer(self.csv_file)
        self.csv.writerow(CSV_COLUMNS)

    def row(self, t: int, status: str, shifts=(), d=(), d_opt=(), mean: float | None = None):
        """One frames.csv row; lists are ';'-separated (shifts in frames, the rest in metres)."""
        join = ";".join
        mean_text = "" if mean is None else f"{mean:.4f}"
        self.csv.writerow(
            [t, status, join(map(str, shifts)), join(f"{v:.6g}" for v in d),
             join(f"{v:.6g}" for v in d_opt), mean_text]
        )  # fmt: skip

    def frame(self, t: int, rgb: np.ndarray, depth: np.ndarray) -> None:
        """Depth file, colour PNG and preview frame of frame t."""
        footage.write_depth(self.folder / "depth" / f"{t:06d}{self.suffix}", depth)
        colours = footage.colourise(depth, self.max_depth, self.lut)
        footage.write_png(self.folder / "depth_png" / f"{t:06d}.png", colours)
        self.preview.write(rgb, colours)

    def close(self) -> None:
        self.preview.close()
        self.csv_file.close()


@torch.no_grad()
def network_outputs(
    model: torch.nn.Module,
    clamp: tuple[float, float] | None,
    device: torch.device,
    frames: Sequence[np.ndarray],
    shifts: list[int],
) -> torch.Tensor:
    """Network outputs (n, H, W) at the frames' resolution (m, for the nominal displacement) of
    the pairs (frame t − δ, frame t), δ in ``shifts``; ``frames[-1]`` is frame t, ``frames[-1 - δ]``
    frame t − δ ((H, W, 3) uint8 RGB). One batch; clamped to ``clamp`` (a clamped network's range,
    m) when given."""
    current = normalise(frames[-1])
    x = np.stack([np.concatenate([normalise(frames[-1 - s]), current]) for s in shifts])
    out = model(torch.from_numpy(x).to(device))[0]
    if clamp is not None:
        out = out.clamp(*clamp)
    h, w = frames[-1].shape[:2]
    return upsample_to(out, h, w).float().cpu()  # .cpu() waits for a GPU


@dataclass
class FrameDepth:
    """One frame's fused depth: the shifts used (frames), their displacements d* (m), the
    targets d_opt they were chosen for (m), the depth (H, W) m and its saturated pixels."""

    shifts: list[int]
    displacements: list[float]
    targets: list[float]
    depth: torch.Tensor
    saturated: torch.Tensor
    network_s: float  # seconds spent in the network


def frame_depth(
    planner: ShiftPlanner, available: np.ndarray, outputs: Callable[[list[int]], torch.Tensor]
) -> FrameDepth | None:
    """One step of the frame loop (thesis Fig. 6.4): the planner's shifts among ``available``
    (``available[k]`` = d(t, k + 1), m), the network ``outputs(shifts)`` (n, H, W), their fusion,
    and the planner's update. None when no shift has any motion (hovering: depth undefined)."""
    target = [planner.scale.d0] if planner.d_opt is None else [float(v) for v in planner.d_opt]
    if not (available > 0).any():
        return None
    shifts = [s for s in planner.plan(available) if available[s - 1] > 0]
    if not shifts:
        return None
    tick = time.perf_counter()
    out = outputs(shifts)
    network_s = time.perf_counter() - tick
    d = [float(available[s - 1]) for s in shifts]
    depth, saturated = fuse(out, d, planner.scale, planner.beta_mean)
    planner.update(depth, saturated)
    return FrameDepth(shifts, d, target, depth, saturated, network_s)


def run(job: Job, o: InferOptions) -> dict:
    """Depth of every frame of ``job`` into ``o.out``; returns the summary (also summary.json)."""
    tmp = temp_path(o.out)
    o.out.parent.mkdir(parents=True, exist_ok=True)
    try:
        summary = _loop(job, o, tmp)
        if o.out.exists():
            o.out.rmdir()  # an empty folder (checked by check_options)
        os.replace(tmp, o.out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return summary


def _loop(job: Job, o: InferOptions, folder: Path) -> dict:
    """The frame loop (see the module doc), writing into ``folder``."""
    planner = ShiftPlanner(o.shifts, job.scale, o.ema, o.fixed_shift, o.beta_mean)
    net = (job.model, job.info["clamp"], job.device)
    outputs = Outputs(folder, job, o.depth_format, o.max_depth)
    ring: deque = deque(maxlen=job.max_shift + 1)
    hist: Counter = Counter()
    stats = {"frames": 0, "with_depth": 0, "no_motion": 0, "network_s": 0.0}
    start = time.perf_counter()
    bar = tqdm(total=job.source.count, unit="frame", disable=o.quiet, desc="infer")
    try:
        for t, frame in enumerate(job.source):
            rgb = footage.prepare_frame(frame, job.crop, *job.size)
            ring.append(rgb)
            stats["frames"] += 1
            bar.update()
            if t == 0:
                outputs.row(0, "first frame (no earlier frame)")
                continue
            available = displacements(job.positions, t, len(ring) - 1)
            est = frame_depth(planner, available, lambda s: network_outputs(*net, ring, s))
            if est is None:
                stats["no_motion"] += 1
                outputs.row(t, "no motion")
                continue
            stats["network_s"] += est.network_s
            hist.update(est.shifts)
            stats["with_depth"] += 1
            outputs.frame(t, rgb, est.depth.numpy())
            mean = float(est.depth.mean())
            outputs.row(t, "depth", est.shifts, est.displacements, est.targets, mean)
    finally:
        bar.close()
        outputs.close()
    stats["loop_s"] = time.perf_counter() - start
    summary = _summary(job, o, stats, hist)
    with open(folder / "summary.json", "w") as f:
        json.dump(summary, f, indent=2)
        f.write("\n")
    return summary


def _summary(job: Job, o: InferOptions, stats: dict, hist: Counter) -> dict:
    n, net_s, loop_s = stats["with_depth"], stats["network_s"], stats["loop_s"]
    options = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(o).items()}
    return {
        "checkpoint": str(o.ckpt),
        "model": job.info["model_name"],
        "nominal_displacement_m": job.scale.d0,
        "theta_max_m": job.scale.theta_max,
        "depth_range_m": job.info["depth_range"],
        "clamp": job.info["clamp"],
        "input": str(o.input),
        "frames_in": stats["frames"],
        "frames_with_depth": n,
        "frames_without_motion": stats["no_motion"],
        "first_frame": FIRST_FRAME,
        "depth_of": "frame t, the later frame of each pair (I_{t-shift}, I_t)",
        "network_seconds": net_s,
        "loop_seconds": loop_s,
        "fps_network": n / net_s if net_s > 0 else None,
        "fps_loop": stats["frames"] / loop_s if loop_s > 0 else None,
        "shifts_histogram": {str(k): hist[k] for k in sorted(hist)},
        "max_shift": job.max_shift,
        "preview_fps": job.fps,
        "camera": {
            "video_size": [job.source.width, job.source.height],
            "output_size": list(job.size),
            "train_fov_deg": job.info["fov_deg"],
            **job.focals,
            "crop": {k: getattr(job.crop, k) for k in ("x", "y", "width", "height")},
            "fov_factor": job.crop.factor,
        },
        "options": options,
    }


def describe(summary: dict, out: Path) -> str:
    """The one-paragraph summary printed at the end."""
    s, cam = summary, summary["camera"]
    crop = cam["crop"]
    hist = ", ".join(f"{k}: {v}" for k, v in s["shifts_histogram"].items()) or "none"
    net = f"{s['fps_network']:.1f}" if s["fps_network"] else "-"
    loop = f"{s['fps_loop']:.1f}" if s["fps_loop"] else "-"
    return (
        f"{s['frames_with_depth']} of {s['frames_in']} frames with depth ({FIRST_FRAME}; "
        f"{s['frames_without_motion']} without motion). Frames cropped to {crop['width']}x"
        f"{crop['height']} at ({crop['x']}, {crop['y']}) and resized to "
        f"{cam['output_size'][0]}x{cam['output_size'][1]}; frame shifts used (shift: frames) "
        f"{hist}. Network {net} frames/s, whole loop {loop} frames/s. Outputs in {out}."
    )
