"""Training of a registered network, resumable exactly: the engine's loop (engine.loop)
configured for a method of the registry on a generated dataset (``run``, ``compare``).

The kind of method chooses its training set and step through the table of engine.steps (pairs
with ground truth: engine.pair_step; frame sequences without it: benchmark.unsupervised.training);
the optimiser (the recipe's SGD or Adam), the learning-rate milestones, validation
(engine.evaluate, on fixed pairs of the val split), checkpoints and resume are the same for all.
Flow networks keep the checkpoint with the best validation EPE instead of the best MAE
(the kind's ``best_by``).

A training writes ``config.json``, ``environment.json``, ``steps.csv`` (loss every
``log_every`` steps), ``metrics.csv`` (one row per validation), ``tb/`` (TensorBoard) and
``checkpoints/{last,best}.pt`` into its run folder through benchmark.core.runfolder (docs/RUNS.md);
checkpoints are read back with ``weights_only=True``, so a checkpoint can never run code.
Multi-process training works unchanged under ``torchrun`` (DDP; gloo on CPU, NCCL on GPUs): the
main process (rank 0) logs, validates and saves.
"""

from __future__ import annotations

import math
import os
import platform
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from stillbox_gen.conventions import MAX_DEPTH

from ..core import registry, runfolder
from ..core.checkpoint import first_line, load_checkpoint, load_weights
from ..core.config import TrainConfig, check_settings
from ..core.data import (
    EpochBatches,
    EpochSampler,
    FrameStore,
    PairBatches,
    PairDataset,
    camera_of,
    load_scenes,
    nominal_displacement,
)
from ..core.device import resolve_device
from ..core.errors import FieldError
from ..core.posenet import DepthPoseNet
from . import evaluate, pair_step  # noqa: F401 - pair_step registers the depth and flow steps
from .loop import NonFiniteLoss, TrainingLoop, new_state
from .resume import RESUME_KEYS, check_resumed_settings
from .steps import step_maker

__all__ = ["NonFiniteLoss", "Trainer", "environment", "make_optimizer"]


def environment(device: torch.device) -> dict:
    from importlib.metadata import version

    return {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "stillbox-gen": version("stillbox-gen"),
        "device": str(device),
        "cuda_device": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "torch_threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "world_size": int(os.environ.get("WORLD_SIZE", "1")),
        "tensorboard": version("tensorboard") if runfolder.has_tensorboard() else None,
    }


def parameter_groups(model: torch.nn.Module, cfg: TrainConfig) -> list[dict]:
    """The optimiser's parameter groups: one at ``cfg.lr``, or with ``cfg.pose_lr`` the model's
    PoseNet (its ``pose`` module) apart at that rate. FieldError on ``pose_lr`` for a model
    without a PoseNet."""
    if cfg.pose_lr is None:
        return [{"params": list(model.parameters())}]
    pose = getattr(model, "pose", None)
    if not isinstance(pose, torch.nn.Module):
        raise FieldError(
            "pose_lr", f"is for a method with a PoseNet (depthnet-unsup*, sfmlearner*), got "
            f"'{cfg.model}'",
        )  # fmt: skip
    own = {id(p) for p in pose.parameters()}
    rest = [p for p in model.parameters() if id(p) not in own]
    return [{"params": rest}, {"params": list(pose.parameters()), "lr": cfg.pose_lr}]


def make_optimizer(params, cfg: TrainConfig, fused: bool = True) -> torch.optim.Optimizer:
    """The recipe's SGD or Adam. ``fused``: torch's fused implementation (one pass over each
    parameter for the whole update; the same formula, equal within floating-point rounding),
    1.12× (DepthNet, SGD) and 1.56× (FlowNetS, Adam) faster training steps at batch 8 on this
    2-core CPU; else torch's default (a loop of operations per parameter on the CPU)."""
    fused = fused or None  # None: torch's default implementation
    if cfg.optimizer == "adam":
        return torch.optim.Adam(
            params,
            lr=cfg.lr,
            betas=(cfg.momentum, cfg.beta2),
            weight_decay=cfg.weight_decay,
            fused=fused,
        )
    return torch.optim.SGD(
        params,
        lr=cfg.lr,
        momentum=cfg.momentum,
        dampening=cfg.dampening,
        weight_decay=cfg.weight_decay,
        fused=fused,
    )


def amp_dtype(cfg: TrainConfig, device: torch.device) -> torch.dtype | None:
    """The autocast dtype of the training step, or None (float32). ``cfg.amp`` None: bfloat16
    on a CUDA device that supports it, float32 elsewhere; True: bfloat16 on any device."""
    on = cfg.amp
    if on is None:
        on = device.type == "cuda" and torch.cuda.is_bf16_supported()
    return torch.bfloat16 if on else None


#: validation metrics of a scale-free depth (sfmlearner) with the ground truth's median scale
GT_SCALED = ("gt_mae", "gt_mre", "gt_mle")


def pretrained_part(model: torch.nn.Module, ck: dict) -> torch.nn.Module:
    """What a ``--pretrained`` checkpoint ``ck`` initialises: ``model`` whole, or the DepthNet of
    a DepthPoseNet when ``ck`` holds a depth network alone (thesis §5.4.4's D + O -> O: a
    supervised DepthNet trained on from video, with a fresh PoseNet)."""
    if isinstance(model, DepthPoseNet) and not any(k.startswith("pose.") for k in ck["model"]):
        return model.depth
    return model


class Trainer(TrainingLoop):
    """A registered method trained on a generated dataset (``run``, ``compare``): the engine's
    loop (engine.loop) with the kind's training set and step (engine.steps), the recipe's
    learning-rate milestones, a validation at each stage's end and the best checkpoint kept."""

    def __init__(self, cfg: TrainConfig):
        self.cfg = cfg
        self.run = Path(cfg.out)
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = 0
        if self.world > 1:
            backend = "nccl" if torch.cuda.is_available() else "gloo"
            torch.distributed.init_process_group(backend)
            self.rank = torch.distributed.get_rank()
        if cfg.threads > 0:
            torch.set_num_threads(cfg.threads)
        self.device = resolve_device(cfg.device)
        if self.device.type == "cuda" and self.world > 1:
            self.device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        self.is_main_process = self.rank == 0  # rank 0 logs, validates and saves
        self.show_progress = cfg.progress

    def log(self, msg: str) -> None:
        if self.is_main_process:
            tqdm.write(msg)

    def setup(self, check: Callable[[], None] | None = None) -> None:
        """Check every input (checkpoints, data, then ``check()`` in the main process, e.g. the
        test split scored after training), then create the run folder: an error leaves nothing
        behind."""
        cfg = self.cfg
        check_settings(asdict(cfg))  # FieldError naming the field (the CLI checked its flags)
        torch.manual_seed(cfg.seed)
        spec = registry.MODELS[cfg.model]
        if not spec.trainable:
            raise ValueError(f"{cfg.model}: has no network to train")
        last = runfolder.checkpoint_path(self.run, "last")
        resume = load_checkpoint(last, "resume") if cfg.resume else None
        if resume is not None and resume["model_name"] != cfg.model:
            raise FieldError(
                "resume", f"a run of '{resume['model_name']}', not '{cfg.model}'", where=f" {last}"
            )
        if resume is not None and not all(k in resume for k in RESUME_KEYS):
            raise FieldError(
                "resume", "holds no training state (not a 'last.pt')", where=f" {last}"
            )
        if resume is not None:
            check_resumed_settings(cfg, resume, last)
        self.kind = spec.kind
        self.model = spec.build().to(self.device)
        self.nominal_displacement = None
        if cfg.pretrained and resume is None:  # resuming: the checkpoint's weights
            ck = load_checkpoint(cfg.pretrained, "pretrained")
            load_weights(
                pretrained_part(self.model, ck), ck, "pretrained", cfg.pretrained, cfg.model
            )
            self.log(f"initialised from {cfg.pretrained}")
        cuda = self.device.type == "cuda"
        if cfg.channels_last:
            self.model = self.model.to(memory_format=torch.channels_last)
        if cuda:  # untested here (no GPU): cuDNN picks the fastest kernels for the input size
            torch.backends.cudnn.benchmark = True
        self.net = self.model
        if self.world > 1:
            ids = [self.device.index] if cuda else None
            self.net = torch.nn.parallel.DistributedDataParallel(self.model, device_ids=ids)
        if cfg.compile:
            self.net = torch.compile(self.net)
        self.opt = make_optimizer(parameter_groups(self.model, cfg), cfg)
        miles = sorted({max(1, round(m * cfg.epochs)) for m in cfg.milestones})
        self.sched = torch.optim.lr_scheduler.MultiStepLR(self.opt, miles, cfg.gamma)
        self.state = new_state() | {"best": math.inf}
        if resume is not None:
            self._load_training_state(resume, last)

        lo, hi = cfg.depth_range
        if not 0 <= lo < hi <= MAX_DEPTH:
            raise FieldError(
                "depth_range",
                f"must be LO,HI metres with 0 <= LO < HI <= {MAX_DEPTH:g}, got {lo:g},{hi:g}",
            )
        # rotating scenes: PairDataset stabilises its pairs, depthnet-unsup*'s --pose its sequences
        train_scenes = load_scenes(Path(cfg.data), "train", rotations=True)
        val_scenes = load_scenes(Path(cfg.data), "val", rotations=True)
        if not train_scenes or not val_scenes:
            raise FieldError(
                "data",
                "needs scenes in both train and val splits "
                f"(has {len(train_scenes)} train, {len(val_scenes)} val)",
                where=f" {cfg.data}",
            )
        t0 = time.perf_counter()
        show = cfg.progress and self.is_main_process
        self.train_store = FrameStore(train_scenes, cfg.cache, show)
        self.val_store = FrameStore(val_scenes, cfg.cache, show)
        self.cache_seconds = time.perf_counter() - t0
        self._check_frame_size(cfg.data)
        frames = min(s.frames for s in val_scenes)
        if not 1 <= cfg.shift < frames:
            raise FieldError(
                "shift",
                f"must be at least 1 and below the {frames} frames of a scene, got {cfg.shift}",
            )
        self.camera = camera_of(Path(cfg.data))
        self.nominal_displacement = nominal_displacement(train_scenes, cfg.shift)
        make = step_maker(self.kind.target)  # the kind's training set and step (engine.steps)
        self.train_set, self.train_step = make(
            cfg, self.net, self.opt, self.device, self.train_store, self.nominal_displacement,
            amp_dtype(cfg, self.device), self.state,
        )  # fmt: skip
        self.val_set = PairDataset(self.val_store, "eval", cfg.shift)
        self.per_rank_batch = max(1, cfg.batch_size // self.world)
        self.sampler = EpochSampler(len(self.train_set), cfg.seed, self.rank, self.world)
        # whole batches from PairDataset.batch (the same tensors as collating single pairs);
        # workers (CUDA's default, untested here) get each batch's epoch with its indices
        workers = cfg.workers if cfg.workers is not None else (2 if cuda else 0)
        self.loader = torch.utils.data.DataLoader(
            PairBatches(self.train_set),
            batch_size=None,
            sampler=EpochBatches(self.sampler, self.per_rank_batch),
            num_workers=workers,
            pin_memory=cuda,
            persistent_workers=workers > 0,
        )
        self.steps_per_epoch = len(self.train_set) // self.world // self.per_rank_batch
        if cfg.epoch_size:  # the first epoch_size batches of each epoch's permutation
            self.steps_per_epoch = min(self.steps_per_epoch, cfg.epoch_size)
        if self.steps_per_epoch == 0:
            raise FieldError(
                "batch_size",
                f"larger than the {len(self.train_set)} training samples",
                where=f" {cfg.batch_size}",
            )
        if check is not None and self.is_main_process:
            check()
        if self.is_main_process:
            self._start_run_folder()
        if resume is not None:
            self.log(f"resumed from {last} at step {self.state['global_step']}")

    def _check_frame_size(self, data: str) -> None:
        """FieldError on ``data`` unless the frames (train and val) fit the network: height and
        width multiples of its ``min_multiple`` pixels (64 for six stride-2 stages)."""
        multiple = getattr(self.model, "min_multiple", 1)
        for store in (self.train_store, self.val_store):
            if store.height % multiple or store.width % multiple:
                raise FieldError(
                    "data",
                    f"frames of {store.width}x{store.height} px; '{self.cfg.model}' needs sizes "
                    f"that are multiples of {multiple} px (e.g. stillbox-gen --res {multiple})",
                    where=f" {data}",
                )

    def _load_training_state(self, ck: dict, path: Path) -> None:
        """Weights, optimiser, scheduler and counters (with the open stage's running sums)."""
        load_weights(self.model, ck, "resume", path, self.cfg.model)
        try:
            self.opt.load_state_dict(ck["optimizer"])
            self.sched.load_state_dict(ck["scheduler"])
            self.state.update(ck["state"])
        except (KeyError, ValueError, TypeError) as e:
            raise FieldError(
                "resume", f"its training state does not fit this run ({first_line(e)})",
                where=f" {path}",
            ) from None  # fmt: skip

    def _start_run_folder(self) -> None:
        """Create the run folder (runfolder.start_logs), write config.json and environment.json,
        open TensorBoard (on resume, start_logs dropped the events logged after the checkpoint)."""
        cfg = self.cfg
        for p in runfolder.start_logs(self.run, cfg.resume, self.state["global_step"]):
            self.log(f"removed {p}, left by an interrupted checkpoint write")
        runfolder.write_config(self.run, asdict(cfg))
        env = environment(self.device)
        env["frame_cache_bytes"] = self.train_store.nbytes + self.val_store.nbytes
        env["frame_cache_seconds"] = round(self.cache_seconds, 2)
        runfolder.write_environment(self.run, env)
        # on resume, start_logs cut the event files back to the checkpoint's step (no purge_step:
        # its reader-side purge would also hide that step's points)
        self.tb = runfolder.tensorboard_writer(self.run)
        if not runfolder.has_tensorboard():
            self.log(runfolder.TENSORBOARD_MISSING)

    def checkpoint(self, name: str) -> None:
        """Save ``checkpoints/<name>.pt`` (main process only): weights, optimiser, scheduler,
        counters, model name, nominal displacement (metres), shift, depth range (metres), the
        training camera (frame size in pixels, horizontal field of view in degrees) and config.
        Weights that are no longer finite are never saved (NonFiniteLoss, in every process)."""
        self.check_finite_weights()
        if not self.is_main_process:
            return
        runfolder.save_checkpoint(
            runfolder.checkpoint_path(self.run, name),
            {
                "model": self.model.state_dict(),
                "optimizer": self.opt.state_dict(),
                "scheduler": self.sched.state_dict(),
                "state": dict(self.state),
                "model_name": self.cfg.model,
                "nominal_displacement": self.nominal_displacement,
                "shift": self.cfg.shift,
                "depth_range": [float(v) for v in self.cfg.depth_range],
                "camera": self.camera,
                "config": asdict(self.cfg),
            },
        )

    def total_steps(self) -> int:
        total = self.cfg.epochs * self.steps_per_epoch
        return min(total, self.cfg.max_steps) if self.cfg.max_steps else total

    def validate(self) -> dict:
        result = evaluate.evaluate(
            evaluate.Method(
                self.kind,
                self.model,
                self.nominal_displacement,
                depth_range=registry.output_clamp(self.cfg.depth_range),
            ),
            self.val_set,
            self.device,
            self.cfg.eval_batch_size,
            self.nominal_displacement,
            collect=False,
        )
        return result.summary

    def end_of_stage(self) -> None:
        """Close the open stage: validate, log a metrics row from its running sums, reset them,
        keep the best checkpoint, save the last one."""
        st, stage = self.state, self.close_stage()
        steps, seconds = stage["stage_steps"], stage["stage_seconds"]
        train_loss = stage["stage_loss_sum"] / steps if steps else float("nan")
        samples, wait = stage["stage_samples"], stage["stage_wait"]
        if self.is_main_process:
            val = self.validate()
            row = {
                "epoch": st["epoch"] + st["step_in_epoch"] / self.steps_per_epoch,
                "step": st["global_step"],
                "lr": self.opt.param_groups[0]["lr"],
                "train_loss": train_loss,
                **{f"val_{k}": val[k] for k in ("mae", "mre", "mle", "depth_error")},
                **({"val_epe": val["epe"]} if "epe" in val else {}),
                **{f"val_{k}": val[k] for k in GT_SCALED if k in val},  # sfmlearner's "GT"
                "samples_per_s": samples / seconds if seconds else 0.0,
                "data_wait_share": wait / seconds if seconds else 0.0,
                "seconds": seconds,
            }
            runfolder.append_row(self.run, runfolder.METRICS_CSV, row)
            for k, v in row.items():
                self.tb.add_scalar(f"epoch/{k}", v, st["global_step"])
            epe = f", EPE {val['epe']:.3f} px" if "epe" in val else ""
            if "gt_mae" in val:  # scale-free depth: MAE above with PoseNet's scale ("P")
                epe += f" (P scale; GT median scale: MAE {val['gt_mae']:.3f} m)"
            self.log(
                f"step {st['global_step']}: train loss {train_loss:.3f}, val MAE "
                f"{val['mae']:.3f} m, MRE {val['mre']:.3f}, MLE {val['mle']:.3f}{epe}"
            )
            score = val[self.kind.best_by]
            if score < st["best"] or not runfolder.checkpoint_path(self.run, "best").exists():
                if score < st["best"]:  # a NaN score never becomes the best
                    st["best"] = score
                self.checkpoint("best")
        self.checkpoint("last")
