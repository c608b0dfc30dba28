"""One benchmark run per method: train (networks) and score, writing the run folder.

Networks (``depth`` and ``flow`` outputs) are trained by train.Trainer, then their best
checkpoint is scored; methods without a network (``oracle-flow``, ``constant``) are scored
directly. Either way the run folder gets ``config.json``, ``environment.json``,
``summary.json`` / ``summary.md``, ``per_sample.csv``, ``pixels.npz`` and ``plots/``, each written
once, through benchmark.core.runfolder (docs/RUNS.md). Errors a user can fix are raised as
ValueError with a one-line message.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from pathlib import Path

import numpy as np

from stillbox_gen.conventions import MAX_DEPTH, NOMINAL_SHIFT
from stillbox_gen.lock import folder_lock

from ..core import registry, runfolder
from ..core.checkpoint import load_checkpoint, load_weights, source_error
from ..core.config import EVAL_BATCH_SIZE, KEPT_ON_RESUME, TrainConfig, default
from ..core.contract import load_user_model
from ..core.data import (
    FrameStore,
    PairDataset,
    Scene,
    eval_firsts,
    load_scenes,
    nominal_displacement,
)
from ..core.device import resolve_device
from ..core.errors import FieldError
from . import report
from .evaluate import EvalResult, Method, evaluate
from .predictions import PredictionFiles
from .resume import resumed_settings
from .train import Trainer, environment

MEDIAN_FRAMES = 2000  # at most this many training frames (evenly spread) for the constant
PREDICTIONS_NAME = "predictions"  # summary.json's model of eval --predictions
ORACLE_FLOW_NOISE_PX = 0.05  # oracle-flow is also scored with this much flow noise (sensitivity)


def eval_split(
    data: Path,
    split: str,
    shift: int,
    progress: bool,
    ckpt: Path | None = None,
    rotations: bool = False,
) -> tuple[str, list, PairDataset]:
    """(split actually used, its scenes, eval-mode PairDataset); test falls back to val. A
    ``shift`` (frames) not below the scenes' frame count is a FieldError on ``shift`` (on
    ``ckpt`` when the shift is that checkpoint's), raised before any frame is read.
    ``rotations``: scenes with camera rotations are accepted (load_scenes)."""
    split, scenes = eval_scenes(data, split, shift, ckpt, rotations)
    return split, scenes, PairDataset(FrameStore(scenes, progress=progress), "eval", shift)


def eval_scenes(
    data: Path, split: str, shift: int, ckpt: Path | None = None, rotations: bool = False
) -> tuple[str, list[Scene]]:
    """:func:`eval_split`'s split and scenes, checked, before any frame is read."""
    scenes = load_scenes(data, split, rotations)
    if not scenes and split == "test":
        split, scenes = "val", load_scenes(data, "val", rotations)
    if not scenes:
        raise FieldError("data", f"'{data}' has no scenes in split '{split}'")
    frames = min(s.frames for s in scenes)
    if shift >= frames:
        text = f"{shift} is not below the {frames} frames of the scenes of '{data}'"
        if ckpt is not None:
            raise source_error("ckpt", ckpt, f"its 'shift' {text}")
        raise FieldError("shift", text)
    return split, scenes


def frame_size(scenes: list[Scene]) -> tuple[int, int]:
    """(H, W) of the scenes' frames (the first frame of the first scene)."""
    return tuple(scenes[0].load_rgb(0).shape[:2])


def check_frame_size(ck: dict, model, size: tuple[int, int], data: Path, ckpt: Path) -> None:
    """FieldError on ``data`` unless its frames, ``size`` (H, W) pixels, are those the
    checkpoint ``ck`` (read from ``ckpt``) was trained on (its ``camera``, when recorded) and
    that its network ``model`` reads (multiples of its ``min_multiple``): a network trained at
    another size would see its pixels, and so its depth, scaled."""
    h, w = size
    cam = ck.get("camera")
    if cam is not None and (cam["width"], cam["height"]) != (w, h):
        raise FieldError(
            "data", f"frames of {w}x{h} px, but the checkpoint '{ckpt}' was trained on "
            f"{cam['width']}x{cam['height']} px frames; score it on a dataset of that size "
            f"(stillbox-gen --res {cam['width']}x{cam['height']})", where=f" {data}",
        )  # fmt: skip
    multiple = getattr(model, "min_multiple", 1)
    if h % multiple or w % multiple:
        raise FieldError(
            "data", f"frames of {w}x{h} px; the network of '{ckpt}' needs sizes that are "
            f"multiples of {multiple} px (e.g. stillbox-gen --res {multiple})", where=f" {data}",
        )  # fmt: skip


def median_depth(scenes: list[Scene], max_frames: int = MEDIAN_FRAMES) -> tuple[float, int]:
    """Median ground-truth depth (clipped to MAX_DEPTH, as training targets) over every pixel of up
    to ``max_frames`` frames spread evenly over ``scenes``; returns (metres, frames used)."""
    frames = [(s, f) for s in scenes for f in range(len(s.depth))]
    if not frames:
        raise FieldError("data", "no training scenes to take the median depth from")
    pick = np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).astype(int))
    values = [np.clip(frames[i][0].load_depth(frames[i][1]), 0, MAX_DEPTH) for i in pick]
    return float(np.median(np.concatenate([v.reshape(-1) for v in values]))), len(pick)


def write_scores(
    out: Path,
    name: str,
    result: EvalResult,
    info: dict,
    extra: dict | None = None,
    md: str = "",
    kind: registry.Kind | None = None,
) -> dict:
    """The scores of method ``name`` (of ``kind``: report.summarize) into ``out``: plots, then
    per_sample.csv, pixels.npz, summary.json (``info``, the scores, then ``extra``) and
    summary.md (then ``md``), each written once. Returns the summary."""
    summary = {**report.summarize(name, result, info, kind), **(extra or {})}
    report.write_plots(out, name, result)
    markdown = report.summary_markdown(summary) + md
    runfolder.write_report(out, summary, markdown, result.per_sample, result.pixels)
    return summary


def score_checkpoint(
    ckpt: Path,
    data: Path,
    split: str,
    out: Path,
    device: str,
    batch_size: int,
    save_predictions: bool,
    progress: bool = True,
    extra: dict | None = None,
    split_data: tuple[str, list, PairDataset] | None = None,
    median_scaling: bool = False,
) -> dict:
    """Evaluate a checkpoint on a split and write summary.json/.md, per_sample.csv, plots/
    (``extra`` is added to the summary). The checkpoint, device and data are checked before
    ``out`` is created. ``split_data``: :func:`eval_split`'s answer for this split at the
    checkpoint's shift, when already read; ``median_scaling``: evaluate's."""
    if batch_size < 1:
        raise FieldError("batch_size", f"must be at least 1, got {batch_size}")
    dev = resolve_device(device)
    ck = load_checkpoint(ckpt, "ckpt")
    name = ck["model_name"]
    model = registry.build_model(name)
    load_weights(model, ck, "ckpt", ckpt, name)
    model.to(dev)
    shift = ck.get("shift", NOMINAL_SHIFT)
    if split_data is None or split_data[2].shift != shift:
        split, scenes = eval_scenes(data, split, shift, ckpt, rotations=True)  # pairs stabilised
        check_frame_size(ck, model, frame_size(scenes), data, ckpt)  # before reading frames
        split_data = (
            split,
            scenes,
            PairDataset(FrameStore(scenes, progress=progress), "eval", shift),
        )
    split, scenes, dataset = split_data
    depth_range = ck.get("depth_range", [0.0, MAX_DEPTH])
    clamp = registry.output_clamp(depth_range)
    method = Method(
        registry.MODELS[name].kind, model, ck["nominal_displacement"], depth_range=clamp
    )
    info = {
        "checkpoint": str(ckpt),
        "nominal_displacement": ck["nominal_displacement"],
        "depth_range": list(depth_range),
        "training_state": ck.get("state"),
    }
    return score_split(
        out, name, method, (data, split, scenes, dataset), dev, batch_size, info,
        save_predictions, median_scaling, extra,
    )  # fmt: skip


def score_split(
    out: Path,
    name: str,
    method: Method,
    split_data: tuple[Path, str, list[Scene], PairDataset],
    device,
    batch_size: int,
    info: dict,
    save_predictions: bool = False,
    median_scaling: bool = False,
    extra: dict | None = None,
) -> dict:
    """Score ``method`` (called ``name``) on the eval pairs of ``split_data`` (dataset folder,
    split, its scenes, their PairDataset) and write its report into ``out``, created here: after
    every check, before the evaluation's minutes. ``info`` goes into summary.json after what was
    scored; :func:`write_scores` does the rest."""
    data, split, scenes, dataset = split_data
    runfolder.make_folder(out)
    t0 = time.perf_counter()
    predictions = runfolder.predictions_dir(out) if save_predictions else None
    result = evaluate(
        method, dataset, device, batch_size, predictions_dir=predictions,
        median_scaling=median_scaling,
    )  # fmt: skip
    info = {
        "dataset": str(data),
        "split": split,
        "scenes": len(scenes),
        "shift": dataset.shift,
        **info,
        "median_scaling": median_scaling,
        "eval_seconds": round(time.perf_counter() - t0, 2),
    }
    return write_scores(out, name, result, info, extra, kind=method.kind)


def score_predictions(
    predictions: Path,
    data: Path,
    split: str,
    out: Path,
    batch_size: int,
    median_scaling: bool = False,
    progress: bool = True,
) -> dict:
    """Score another method's depth files (engine.predictions' layout) on the pairs
    (i, i + NOMINAL_SHIFT) of a split, as a registered network is scored, and write the same
    report into ``out``. Every file is checked before ``out`` is created."""
    if batch_size < 1:
        raise FieldError("batch_size", f"must be at least 1, got {batch_size}")
    split, scenes = eval_scenes(data, split, NOMINAL_SHIFT)
    frames = {s.index: len(s.depth) for s in scenes}
    needed = [(s.index, f + NOMINAL_SHIFT) for s in scenes for f in eval_firsts(s, NOMINAL_SHIFT)]
    files = PredictionFiles(predictions, frames, needed, frame_size(scenes))
    dataset = PairDataset(FrameStore(scenes, progress=progress), "eval", NOMINAL_SHIFT)
    method = Method(registry.PREDICTIONS, predictions=files)
    info = {"predictions": str(predictions), "prediction_format": files.ext}
    return score_split(
        out, PREDICTIONS_NAME, method, (data, split, scenes, dataset), resolve_device("cpu"),
        batch_size, info, median_scaling=median_scaling,
    )  # fmt: skip


def score_user_model(
    spec: str,
    data: Path,
    split: str,
    out: Path,
    device: str,
    batch_size: int,
    displacement: float | None = None,
    median_scaling: bool = False,
    save_predictions: bool = False,
    progress: bool = True,
) -> dict:
    """Score the network ``spec`` builds (core.contract: ``module:callable``) on the pairs
    (i, i + NOMINAL_SHIFT) of a split, as a registered depth network is scored. Its depth is
    taken to answer for ``displacement`` metres (default: NOMINAL_SHIFT frames of the split's
    median displacement per frame, what a network trained here answers for). The network and
    the data are checked before ``out`` is created."""
    if batch_size < 1:
        raise FieldError("batch_size", f"must be at least 1, got {batch_size}")
    if displacement is not None and not (displacement > 0 and math.isfinite(displacement)):
        raise FieldError("displacement", f"must be a positive number of metres, got {displacement}")
    dev = resolve_device(device)
    split, scenes = eval_scenes(data, split, NOMINAL_SHIFT)
    model = load_user_model(spec, *frame_size(scenes), dev)
    nominal = displacement or nominal_displacement(scenes, NOMINAL_SHIFT)
    dataset = PairDataset(FrameStore(scenes, progress=progress), "eval", NOMINAL_SHIFT)
    info = {"user_model": spec, "nominal_displacement": nominal}
    return score_split(
        out, spec, Method(registry.DEPTH, model, nominal), (data, split, scenes, dataset), dev,
        batch_size, info, save_predictions, median_scaling,
    )  # fmt: skip


def score_baseline(
    name: str,
    data: Path,
    out: Path,
    split: str = "test",
    device: str = default("device"),
    batch_size: int = EVAL_BATCH_SIZE,
    save_predictions: bool = False,
    shift: int = NOMINAL_SHIFT,
    progress: bool = True,
) -> dict:
    """Score a method without a network (oracle-flow, constant); writes the run folder."""
    spec = registry.MODELS[name]
    if spec.trainable:
        raise ValueError(f"{name}: a network; train it with 'run'")
    dev = resolve_device(device)
    info: dict = {"dataset": str(data)}
    method = Method(spec.kind)
    if spec.kind.scored_as is registry.Scoring.CONSTANT:
        method.constant, frames = median_depth(load_scenes(data, "train"))
        info["constant_depth"] = method.constant
        info["constant_rule"] = (
            f"median of the training split's ground-truth depth clipped to {MAX_DEPTH:g} m, over "
            f"every pixel of {frames} frames spread evenly over the split"
        )
    split, scenes, dataset = eval_split(data, split, shift, progress)
    runfolder.make_folder(out)  # after every check: a mistake leaves nothing behind
    config = {"model": name, "data": str(data), "split": split, "shift": shift, "device": device}
    runfolder.write_config(out, config)
    runfolder.write_environment(out, environment(dev))
    t0 = time.perf_counter()
    predictions = runfolder.predictions_dir(out) if save_predictions else None
    result = evaluate(method, dataset, dev, batch_size, predictions_dir=predictions)
    info.update(split=split, scenes=len(scenes), shift=shift)
    info["eval_seconds"] = round(time.perf_counter() - t0, 2)
    extra, md = {}, ""
    if spec.kind.scored_as is registry.Scoring.EXACT_FLOW:
        extra, md = _oracle_sensitivity(dataset, dev, batch_size)
    return write_scores(out, name, result, info, extra, md)


def _oracle_sensitivity(dataset: PairDataset, dev, batch_size: int) -> tuple[dict, str]:
    """Score oracle-flow again with a little Gaussian flow noise: the summary entries (metrics
    and error by FOE distance) and the summary.md section showing how the geometry degrades
    near the FOE."""
    noisy = evaluate(
        Method(registry.ORACLE_FLOW, flow_noise=ORACLE_FLOW_NOISE_PX), dataset, dev, batch_size
    )
    bins = report.foe_bins(noisy.pixels["foe_distance"], noisy.pixels["abs_err"])
    extra = {
        "flow_noise_px": ORACLE_FLOW_NOISE_PX,
        "metrics_with_flow_noise": noisy.summary,
        "error_by_foe_distance_with_flow_noise": bins,
    }
    return extra, report.sensitivity_markdown(ORACLE_FLOW_NOISE_PX, noisy.summary, bins)


def train_and_score(cfg: TrainConfig) -> dict | None:
    """Train ``cfg.model`` into ``cfg.out``, then score its best checkpoint on the test split
    (val when test is empty). Returns the summary (None in processes other than the main one
    under DDP). ``cfg.out`` is created by Trainer.setup once every input has been checked."""
    out = Path(cfg.out)
    trainer = Trainer(cfg)
    scored = []  # the test split, read (every frame) before the run folder is made
    trainer.setup(
        check=lambda: scored.append(
            eval_split(Path(cfg.data), "test", cfg.shift, cfg.progress, rotations=True)
        )
    )
    t0 = time.perf_counter()
    trainer.fit()
    train_seconds = time.perf_counter() - t0
    if not trainer.is_main_process:
        return None
    return score_checkpoint(
        runfolder.checkpoint_path(out, "best"),
        Path(cfg.data),
        "test",
        out,
        cfg.device,
        cfg.eval_batch_size,
        cfg.save_predictions,
        progress=cfg.progress,
        extra={"training_seconds": round(train_seconds, 1)},
        split_data=scored[0],
    )


def train_config(model: str, data: Path, out: Path, **overrides) -> TrainConfig:
    """The model's registry recipe (resuming: the settings ``out``'s last checkpoint was trained
    with, resume.RESUMED_FIELDS and config.KEPT_ON_RESUME), then ``overrides`` (None values
    ignored)."""
    recipe = dataclasses.asdict(registry.MODELS[model].recipe)
    cfg = TrainConfig(model=model, data=str(data), out=str(out), **recipe)
    if overrides.get("resume"):
        last = load_checkpoint(runfolder.checkpoint_path(out, "last"), "resume")
        config = last.get("config") if isinstance(last.get("config"), dict) else {}
        kept = {k: config[k] for k in KEPT_ON_RESUME if k in config}
        cfg = dataclasses.replace(cfg, **resumed_settings(last), **kept)
    return dataclasses.replace(cfg, **{k: v for k, v in overrides.items() if v is not None})


def run_method(model: str, data: Path, out: Path, **overrides) -> dict | None:
    """``stillbox-bench run``: train and score a network, or score a method without one.

    The main process holds the lock of ``out`` throughout (stillbox_gen.lock): a second run into
    the same folder is refused with a ValueError naming it and the process holding it. Under DDP
    (torchrun) only rank 0 (environment variable RANK) takes it; the other ranks write nothing.
    """
    if int(os.environ.get("RANK", "0")) != 0:
        return _run_method(model, data, out, **overrides)
    with folder_lock(Path(out), "--out"):
        return _run_method(model, data, out, **overrides)


def _run_method(model: str, data: Path, out: Path, **overrides) -> dict | None:
    spec = registry.MODELS[model]
    if not spec.trainable:
        o = {k: overrides[k] for k in ("device", "save_predictions") if k in overrides}
        o = {k: v for k, v in o.items() if v is not None}
        return score_baseline(model, data, out, progress=overrides.get("progress", True), **o)
    return train_and_score(train_config(model, data, out, **overrides))
