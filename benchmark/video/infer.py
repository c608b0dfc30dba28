"""``stillbox-bench infer``: depth maps of a user's own stabilised video (thesis chapter 6).

For every frame t ≥ 1 the network sees n pairs (I_{t−δ_i}, I_t), one batch, with the frame shifts
δ_i chosen by :class:`benchmark.core.multishift.ShiftPlanner` from the depth of the previous
frames; each output is scaled by its pair's displacement d(t, δ_i) (eq. 6.1) and the n maps are
fused (eq. 6.3): benchmark.engine.frame_depth. The depth belongs to frame t (the later frame of
each pair); frame 0 has no earlier frame and gets none. The options, the network and the footage
are checked and opened by benchmark.engine.footage_job.prepare (frames centre-cropped to the
training field of view and resized to the network's input size: core.footage.crop_box).

Outputs (``--out``, written in a temporary sibling folder and renamed at the end, so an error
leaves nothing half written): ``depth/NNNNNN.npy|exr`` (float32 metres, NNNNNN = frame index),
``depth_png/NNNNNN.png`` (colour map, 0..max_depth m), ``preview.mp4`` (frame | depth colours),
``frames.csv`` (one row per frame) and ``summary.json``.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import time
from collections import Counter, deque
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from stillbox_gen.formats import temp_path

from ..core import footage
from ..core.multishift import ShiftPlanner, displacements
from ..engine.footage_job import InferOptions, Job
from ..engine.frame_depth import frame_depth, network_outputs

FIRST_FRAME = "frame 0 has no earlier frame: no depth for it"
CSV_COLUMNS = ("frame", "status", "shifts", "displacements_m", "d_opt_m", "mean_depth_m")


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
