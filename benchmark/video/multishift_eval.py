"""``stillbox-bench eval-multishift``: frame-shift strategies scored on generated sequences.

The thesis' Fig. 6.6 analogue. Each test sequence (e.g. ``stillbox-gen --frames 30
--rotation-noise 0.0331``: the orientation noise of thesis 6.4) is run frame by frame as
``stillbox-bench infer`` runs a video (benchmark.engine.frame_depth), once per depth
checkpoint and strategy:

- ``nominal``: always the shift whose displacement is closest to the network's d0 (DepthNet's
  3 frames), the pairs it was trained on;
- ``n=1``: the optimal shift of thesis 6.2 (eq. 6.2), chosen from the previous frame's depth;
- ``n=2``, ``n=3``, …: n pairs per frame, one per k-means cluster of the previous depth, fused
  by eq. 6.3 (thesis 6.3).

The planner starts afresh on each sequence at frame 1; frames t ≥ ``max_shift`` are scored (every
strategy has every shift there, and has seen earlier frames), the same frames for every strategy,
against the frame's ground-truth depth: MAE, MRE, MLE (benchmark.core.metrics: per image, then
the mean over images) overall and per band of ground-truth depth (BANDS; a band's metrics are per
image over its pixels, averaged over the images that have some), plus the network's time per
frame (the n pairs are one batch). Displacements come from the camera positions of each frame.
"""

from __future__ import annotations

import csv
import json
import math
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from stillbox_gen.dataset import Scene

from ..core import metrics, runfolder
from ..core.data import read_dataset, read_scenes
from ..core.errors import FieldError, Ref
from ..core.multishift import (
    BETA_MAX,
    BETA_MEAN,
    BETA_MIN,
    EMA_LAMBDA,
    MAX_SHIFTS,
    MULTISHIFT_MAX_SHIFT,
    ShiftPlanner,
    closest_shift,
    displacements,
)
from ..core.runfolder import RESULTS_CSV, RESULTS_JSON, RESULTS_MD
from ..engine.frame_depth import frame_depth, network_outputs
from ..engine.network import depth_network
from ..engine.runner import check_frame_size, frame_size

BANDS = metrics.DEPTH_BANDS  # ground-truth depth, metres
SCORES = ("mae", "mre", "mle")
DEFAULT_SHIFT_COUNTS = (1, 2, 3)
FIGURE = "mre_vs_time.png"


@dataclass(frozen=True)
class Strategy:
    """``n``: pairs per frame (0: the fixed nominal shift)."""

    n: int

    @property
    def label(self) -> str:
        return "nominal" if self.n == 0 else f"n={self.n}"


def strategies(counts: tuple[int, ...]) -> list[Strategy]:
    """The nominal shift, then n = each of ``counts`` (1..MAX_SHIFTS)."""
    bad = [n for n in counts if not 1 <= n <= MAX_SHIFTS]
    if bad or not counts:
        raise FieldError("counts", f"each n must be in 1..{MAX_SHIFTS}, got {counts}")
    return [Strategy(0), *(Strategy(n) for n in sorted(set(counts)))]


def check_arguments(max_shift: int, beta_mean: float, limit: int | None) -> None:
    """FieldError unless ``max_shift`` >= 1 (frames), BETA_MIN < ``beta_mean`` < BETA_MAX and
    ``limit`` (sequences) is None or >= 1."""
    if max_shift < 1:
        raise FieldError("max_shift", f"must be at least 1, got {max_shift}")
    if not BETA_MIN < beta_mean < BETA_MAX:
        raise FieldError("beta_mean", f"must be in ({BETA_MIN}, {BETA_MAX}), got {beta_mean}")
    if limit is not None and limit < 1:
        raise FieldError("limit", f"must be at least 1, got {limit}")


def sequences(data: Path, split: str, max_shift: int, limit: int | None) -> list[Scene]:
    """The split's scenes (first ``limit``); FieldError on ``data`` when they are too short for
    ``max_shift`` (the first scored frame) or absent."""
    scenes = read_scenes(data, split, limit)
    if not scenes:
        raise FieldError("data", f"no scene in the {split} split", where=f" {data}")
    frames = min(s.frames for s in scenes)
    if frames <= max_shift:
        raise FieldError(
            "data", f"scenes of {frames} frames; ", Ref("max_shift"), f" {max_shift} needs more "
            "(generate them with stillbox-gen --frames 30)", where=f" {data}",
        )  # fmt: skip
    return scenes


class Tally:
    """Per-image scores of one (checkpoint, strategy), and its time and shifts."""

    def __init__(self) -> None:
        self.scores: dict[str, list[torch.Tensor]] = {}
        self.network_s, self.frames, self.pairs = 0.0, 0, 0
        self.shifts: Counter = Counter()  # frame shift -> pairs that used it

    def add(self, pred: torch.Tensor, gt: torch.Tensor) -> None:
        for key, (lo, hi) in [("all", (0.0, math.inf)), *((band_key(b), b) for b in BANDS)]:
            inside = (gt >= lo) & (gt < hi) if key != "all" else torch.ones_like(gt, dtype=bool)
            masked = torch.where(inside, gt, torch.full_like(gt, math.nan))
            m = metrics.image_metrics(pred[None], masked[None])
            for name in (*SCORES, "valid_pixels"):
                self.scores.setdefault(f"{key}/{name}", []).append(m[name])

    def summary(self) -> dict:
        out: dict = {}
        for key in ["all", *map(band_key, BANDS)]:
            per_image = {n: torch.cat(self.scores[f"{key}/{n}"]) for n in (*SCORES, "valid_pixels")}
            agg = metrics.aggregate(per_image)
            out.update({f"{key}/{n}": agg[n] for n in SCORES})
            out[f"{key}/images"] = agg["images"]
        ms = 1000 * self.network_s / max(1, self.frames)
        out.update(frames=self.frames, pairs_per_frame=self.pairs / max(1, self.frames))
        out["shifts_used"] = " ".join(f"{k}:{v}" for k, v in sorted(self.shifts.items()))
        out.update(network_ms_per_frame=ms, fps=1000 / ms if ms > 0 else math.inf)
        return out


def band_key(band: tuple[float, float]) -> str:
    return f"{band[0]:g}-{band[1]:g}m"


def run_sequence(
    net: tuple, scale, strategy: Strategy, scene: Scene, frames: list, depths: list,
    max_shift: int, tally: Tally, ema: float = EMA_LAMBDA, beta_mean: float = BETA_MEAN,
) -> None:  # fmt: skip
    """One strategy over one sequence; frames t ≥ max_shift are added to ``tally`` (``ema``,
    ``beta_mean``: the planner's, multishift.ShiftPlanner)."""
    path = scene.cam2world[:, :3, 3]  # camera positions, metres
    nominal = closest_shift(scale.d0, displacements(path, max_shift, max_shift))
    fixed = nominal if strategy.n == 0 else None
    planner = ShiftPlanner(max(1, strategy.n), scale, ema, fixed, beta_mean)
    for t in range(1, scene.frames):
        available = displacements(path, t, max_shift)
        window = frames[max(0, t - max_shift) : t + 1]
        est = frame_depth(planner, available, lambda s, w=window: network_outputs(*net, w, s))
        if est is None or t < max_shift:
            continue
        tally.add(est.depth, torch.from_numpy(depths[t]))
        tally.network_s += est.network_s
        tally.frames += 1
        tally.pairs += len(est.shifts)
        tally.shifts.update(est.shifts)


def evaluate_multishift(
    checkpoints: list[Path],
    data: Path,
    split: str,
    counts: tuple[int, ...],
    max_shift: int,
    device: torch.device,
    ema: float = EMA_LAMBDA,
    beta_mean: float = BETA_MEAN,
    limit: int | None = None,
    progress: bool = True,
) -> list[dict]:
    """Rows of scores, one per (checkpoint, strategy); see the module doc. The arguments are
    checked and every checkpoint loaded before any frame is read (a one-line ValueError;
    FieldError naming the argument)."""
    check_arguments(max_shift, beta_mean, limit)
    plan = strategies(counts)
    nets = []
    for ckpt in checkpoints:
        model, scale, info = depth_network(ckpt, "ckpt")
        nets.append((ckpt, (model.to(device), info["clamp"], device), scale, info))
    scenes = sequences(data, split, max_shift, limit)
    size = frame_size(scenes)
    for ckpt, (model, _, _), _, info in nets:  # eval's own check: FieldError naming --data
        camera = {"width": info["width"], "height": info["height"]}
        check_frame_size({"camera": camera}, model, size, data, ckpt)
    tallies = {(i, s.n): Tally() for i in range(len(nets)) for s in plan}
    for scene in tqdm(scenes, desc="sequences", unit="scene", disable=not progress):
        frames = [scene.load_rgb(f) for f in range(scene.frames)]
        depths = [scene.load_depth(f) for f in range(scene.frames)]
        for i, (_, net, scale, _) in enumerate(nets):
            for s in plan:
                tally = tallies[i, s.n]
                run_sequence(net, scale, s, scene, frames, depths, max_shift, tally, ema, beta_mean)
    rows = []
    for i, (ckpt, _, scale, info) in enumerate(nets):
        for s in plan:
            row = {"model": info["model_name"], "checkpoint": str(ckpt), "strategy": s.label}
            row.update(d0_m=scale.d0, theta_max_m=scale.theta_max, scenes=len(scenes))
            rows.append({**row, **tallies[i, s.n].summary()})
    return rows


def markdown(rows: list[dict], info: dict) -> str:
    """The results as two Markdown tables: overall, then MRE per band."""
    lines = [
        f"# Frame-shift strategies on {info['data']} ({info['split']} split, {info['scenes']} "
        f"sequences of {info['frames_per_scene']} frames; frames t ≥ {info['max_shift']} scored, "
        f"{rows[0]['frames'] if rows else 0} per strategy)",
        "",
        "| model | strategy | pairs/frame | MAE (m) | MRE | MLE | network ms/frame | shifts used |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['model']} | {r['strategy']} | {r['pairs_per_frame']:.2f} | {r['all/mae']:.3f} "
            f"| {r['all/mre']:.3f} | {r['all/mle']:.3f} | {r['network_ms_per_frame']:.2f} "
            f"| {r['shifts_used']} |"
        )
    heads = [band_key(b) for b in BANDS]
    lines += ["", "MAE (m) / MRE per band of ground-truth depth:", ""]
    lines.append("| model | strategy | " + " | ".join(heads) + " |")
    lines.append("|---|---|" + "---|" * len(heads))
    for r in rows:
        cells = [f"{r[f'{h}/mae']:.2f} / {r[f'{h}/mre']:.3f}" for h in heads]
        lines.append(f"| {r['model']} | {r['strategy']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_results(out: Path, rows: list[dict], info: dict) -> str:
    """results.csv, results.json, results.md and the MRE-vs-time figure into ``out``; returns
    the Markdown."""
    runfolder.make_folder(out)
    with open(out / RESULTS_CSV, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (out / RESULTS_JSON).write_text(json.dumps({**info, "rows": rows}, indent=2) + "\n")
    md = markdown(rows, info)
    (out / RESULTS_MD).write_text(md)
    _figure(rows, out / FIGURE)
    return md


def _figure(rows: list[dict], path: Path) -> None:
    """MRE against the network's time per frame, one line per checkpoint (thesis Fig. 6.6)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for ckpt in dict.fromkeys(r["checkpoint"] for r in rows):
        mine = [r for r in rows if r["checkpoint"] == ckpt]
        x = [r["network_ms_per_frame"] for r in mine]
        y = [r["all/mre"] for r in mine]
        ax.plot(x, y, "o-", label=mine[0]["model"])
        for r, xi, yi in zip(mine, x, y, strict=True):
            ax.annotate(r["strategy"], (xi, yi), textcoords="offset points", xytext=(4, 4))
    ax.set_xlabel("network time per frame (ms, this machine)")
    ax.set_ylabel("MRE")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run(
    checkpoints: list[Path],
    data: Path,
    out: Path,
    split: str = "test",
    counts: tuple[int, ...] = DEFAULT_SHIFT_COUNTS,
    max_shift: int = MULTISHIFT_MAX_SHIFT,
    device: torch.device | None = None,
    ema: float = EMA_LAMBDA,
    beta_mean: float = BETA_MEAN,
    limit: int | None = None,
    progress: bool = True,
) -> tuple[list[dict], str]:
    """Score and write the results (``out`` is created only after every check); returns the
    rows and the Markdown."""
    device = device or torch.device("cpu")
    t0 = time.perf_counter()
    rows = evaluate_multishift(
        checkpoints, data, split, counts, max_shift, device, ema, beta_mean, limit, progress
    )
    ds = read_dataset(data)
    info = {
        "data": str(data),
        "split": split,
        "scenes": rows[0]["scenes"],
        "frames_per_scene": ds.info.get("frames_per_scene"),
        "max_shift": max_shift,
        "ema": ema,
        "beta_mean": beta_mean,
        "bands_m": [list(b) for b in BANDS],
        "device": str(device),
        "seconds": round(time.perf_counter() - t0, 1),
    }
    return rows, write_results(out, rows, info)
