"""``stillbox-bench finetune``: a trained depth network fine-tuned without depth on a user's own
stabilised footage (thesis §5.4.5), with the photometric training of chapter 5.

The footage, its motion and the camera geometry are handled as ``infer`` handles them
(benchmark.engine.footage_job.prepare: the same options, checks and crop), its moving stretches
become frame sequences (benchmark.unsupervised.footage_sequences, SequenceDataset), and the
network is the checkpoint's depth network with a fresh PoseNet (core.posenet.DepthPoseNet; a
``depthnet-unsup`` checkpoint keeps its own PoseNet), trained by PhotometricStep (eq. 5.5) with
d0 = the checkpoint's nominal displacement in eq. 5.2, so the network keeps answering in its
supervised convention.

Pose warm-up (``pose_warmup`` steps, :func:`freeze_depth`): the DepthNet is frozen (no gradient:
exactly the checkpoint's function) and only PoseNet learns; then both. The DepthNet's BatchNorm
keeps the checkpoint's statistics throughout (eval mode), so what is trained is what runs.
Measured in an earlier session: joint training from a good supervised DepthNet with a random
PoseNet degraded the DepthNet, as the first poses are wrong and the photometric loss then pushes
the depth the wrong way; with the depth right, the loss's gradient points PoseNet the right way.
:data:`POSE_WARMUP` is a guess, not a measurement (see its comment).

Run folder (core.runfolder, as ``run``): ``config.json``, ``environment.json``, ``steps.csv``
(loss, photometric and smooth terms, phase, and with ``--poses`` the cosine between PoseNet's
reference translation and the known one), ``tb/``, ``checkpoints/last.pt`` (the training state:
the depth network as ``model``, PoseNet as ``pose``, optimiser and counters) and
``checkpoints/best.pt``: the depth network alone, a plain depth checkpoint (``infer``, ``eval``,
``run --pretrained``). Without ground truth there is nothing to choose by: best.pt is the
network of the last checkpoint. Both are written at every ``ckpt_every`` steps and at the end.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import torch
from tqdm import tqdm

from stillbox_gen.conventions import NOMINAL_SHIFT

from ..core import runfolder
from ..core.checkpoint import first_line, load_checkpoint
from ..core.config import check_settings, default
from ..core.data import EpochBatches, EpochSampler, PairBatches
from ..core.errors import FieldError, Ref
from ..core.posenet import DepthPoseNet
from ..core.registry import UNSUPERVISED_RECIPE
from ..engine.footage_job import InferOptions, prepare
from ..engine.loop import COUNTERS, TrainingLoop, new_state
from ..engine.train import environment, make_optimizer
from .footage_sequences import describe_stretches, footage_store, frame_stride
from .sequences import SequenceDataset
from .training import PhotometricStep, pose_cosine, smooth_settings

#: Optimiser steps of a fine-tuning: 5 passes over a 1-minute 30 fps flight (1,800 frames) at
#: batch 32, about 1 CPU-hour at 64 px here (unsupervised steps: ~10 samples per CPU-second)
STEPS = 1000
#: Steps of the pose warm-up (DepthNet frozen). A guess to be measured (the proof experiment,
#: docs/results/finetune/README.md): Adam moves every PoseNet weight by about lr = 2e-4 a step,
#: all 256 inputs of its
#: prediction layer together, so a constant flight direction (a forward flight) is within reach in
#: tens of steps; 200 leaves room for 5-frame windows whose motion varies, and is a fifth of STEPS.
#: (Joint training from a flat DepthNet had not found StillBox's random directions in 120 steps;
#: there the depth was wrong too.)
POSE_WARMUP = 200
#: λ of a fine-tuning: eq. 5.5's smooth term off. Measured on the close-range proof (known
#: motion, 400 steps of 16; docs/results/finetune/README.md): λ = 0 gave test MAE 4.50 m,
#: depthnet-unsup's 0.003 gave 8.04 m and 0.03 gave 67.9 m (before: 6.42). The supervised
#: DepthNet's depths at the 0.1 m floor (21 % of that footage's pixels) are spikes of ξ whose
#: smooth term starts at half the photometric one at λ = 0.003, and the quickest way to flatten
#: them is to push the whole map far.
SMOOTH_WEIGHT = 0.0
#: Options a resumed fine-tuning keeps from its checkpoint (given again, they must be equal)
RESUMED = (
    *("ckpt", "input", "speed", "poses", "fps", "fov", "focal", "res", "train_fov"),
    *("lr", "batch_size", "pose_warmup", "occlusion", "smooth_weight", "seed", "known_motion"),
)
#: Options a resumed fine-tuning takes from its checkpoint unless given again (then the new value
#: holds: more steps continue the run further)
RESUMED_UNLESS_GIVEN = ("steps", "ckpt_every", "log_every")
PHASES = ("pose-warmup", "joint")


@dataclass
class FinetuneOptions:
    """The command line's options (units as ``infer``'s: m, m/s, frames/s, degrees, pixels).
    None: the default (a new run) or the resumed run's value (``resume``)."""

    out: Path
    ckpt: Path | None = None
    input: Path | None = None
    speed: float | None = None
    poses: Path | None = None
    fps: float | None = None
    fov: float | None = None
    focal: float | None = None
    res: tuple[int, int] | None = None
    train_fov: float | None = None
    steps: int | None = None
    pose_warmup: int | None = None
    lr: float | None = None
    batch_size: int | None = None
    occlusion: bool = False
    smooth_weight: float | None = None
    seed: int | None = None
    known_motion: bool | None = None
    resume: bool = False
    threads: int = 0
    device: str = "auto"
    ckpt_every: int | None = None
    log_every: int | None = None
    quiet: bool = False


def defaults(known_motion: bool = False) -> dict:
    """The values of a new run's options left at None (no pose warm-up when the warps use the
    known motion: PoseNet is not used)."""
    r = UNSUPERVISED_RECIPE
    warmup = 0 if known_motion else POSE_WARMUP
    return {"pose_warmup": warmup, "lr": r.lr, "batch_size": r.batch_size, "seed": 0,
            "known_motion": False, "smooth_weight": SMOOTH_WEIGHT, "steps": STEPS,
            "ckpt_every": default("ckpt_every"), "log_every": default("log_every")}  # fmt: skip


#: options that are TrainConfig's training knobs: declared, and their rules, in core.config
TRAINING_KNOBS = ("lr", "batch_size", "seed", "threads", "ckpt_every", "log_every")


def check_numbers(o: FinetuneOptions) -> None:
    """FieldError naming the first option out of its range (reads no file): the training knobs
    by TrainConfig's rules (config.check_settings), then fine-tuning's own."""
    check_settings({name: getattr(o, name) for name in TRAINING_KNOBS})
    rules = (
        ("steps", o.steps is None or o.steps >= 1, "must be at least 1"),
        ("pose_warmup", o.pose_warmup is None or o.pose_warmup >= 0, "must be 0 or more"),
        (
            "smooth_weight",
            o.smooth_weight is None or (o.smooth_weight >= 0 and math.isfinite(o.smooth_weight)),
            "must be 0 or more",
        ),  # fmt: skip
    )
    for name, ok, rule in rules:
        if not ok:
            raise FieldError(name, f"{rule}, got {getattr(o, name)}")


def _plain(value):
    """An option as config.json holds it (paths as text, tuples as lists)."""
    if isinstance(value, Path):
        return str(value)
    return list(value) if isinstance(value, tuple) else value


def resumed_options(o: FinetuneOptions, recorded: dict, where: Path) -> FinetuneOptions:
    """``o`` with the RESUMED options the run was started with (one given with another value
    is a FieldError naming it) and the RESUMED_UNLESS_GIVEN ones not given again."""
    kept = {}
    for name in RESUMED:
        given, then = getattr(o, name), recorded.get(name)
        if given is None or (name == "occlusion" and given is False):
            kept[name] = then
        elif _plain(given) != then:
            raise FieldError(
                name,
                f"the run in {where} was fine-tuned with {then}, not {_plain(given)}; a resumed "
                "run keeps its settings (leave ", Ref(name), " out, or start a new ", Ref("out"),
                ")",
            )  # fmt: skip
    for name in RESUMED_UNLESS_GIVEN:
        if getattr(o, name) is None:
            kept[name] = recorded.get(name)  # None (the default) for a run that recorded none
    types = {"ckpt": Path, "input": Path, "poses": Path, "res": tuple}
    kept = {k: (types[k](v) if k in types and v is not None else v) for k, v in kept.items()}
    return replace(o, **kept)


def freeze_depth(net: DepthPoseNet, frozen: bool) -> None:
    """The pose warm-up's switch: ``frozen``, the DepthNet gets no gradient, so it answers as
    the checkpoint; else its weights train. Its BatchNorm always uses (and keeps) the
    checkpoint's running statistics, in both phases (call after ``net.train()``): the network
    trained is then the one ``eval`` and ``infer`` run. With batch statistics of 16 footage
    sequences the close-range proof got worse than before fine-tuning (test MAE 6.42 -> 7.92 m);
    with the checkpoint's it got better (4.50 m; docs/results/finetune/README.md)."""
    net.depth.requires_grad_(not frozen)
    net.depth.eval()


class FinetuneStep:
    """Fine-tuning's training step (engine.steps.Step): a PhotometricStep with the DepthNet
    frozen while ``progress["global_step"]`` (steps done, resumed ones included) is below
    ``warmup`` (:func:`freeze_depth`). ``phase`` is the last step's (PHASES), ``losses`` this
    session's losses per phase; ``poses``: the footage's known motion is in the batches (the
    ``pose_cosine`` column)."""

    def __init__(
        self, net: DepthPoseNet, step: PhotometricStep, warmup: int, progress: dict, poses: bool
    ):
        self.net, self.step, self.warmup, self.progress = net, step, warmup, progress
        self.poses = poses
        self.phase = PHASES[0]
        self.losses: dict[str, list[float]] = {p: [] for p in PHASES}

    def __call__(self, batch: dict) -> torch.Tensor:
        warm = self.progress["global_step"] < self.warmup
        self.phase = PHASES[0] if warm else PHASES[1]
        self.net.train()
        freeze_depth(self.net, warm)
        terms = self.step.update(batch)
        detached = {k: v.detach() for k, v in terms.items()}
        self._last = batch, detached
        self.losses[self.phase].append(float(detached["loss"]))
        return detached["loss"]

    def logged(self) -> dict:
        """steps.csv's columns of the last step beside its loss: its phase, the photometric and
        smooth terms, and PoseNet's direction (empty without the known motion)."""
        batch, terms = self._last
        return {
            "phase": self.phase,
            "photometric": float(terms["photometric"]),
            "smooth": float(terms["smooth"]),
            "pose_cosine": pose_cosine(batch, terms["translations"]) if self.poses else "",
        }


class Finetuner(TrainingLoop):
    """A fine-tuning checked and set up (:meth:`setup`, nothing written), then run (:meth:`fit`,
    writing the run folder): the engine's loop (engine.loop) with a footage's sequences, the
    :class:`FinetuneStep`, no validation and both checkpoints at every save."""

    label = "fine-tuning"
    bar_title = "finetune"

    def __init__(self, o: FinetuneOptions):
        self.o = o
        self.run = Path(o.out)
        self.world, self.is_main_process, self.sched = 1, True, None
        self.show_progress = not o.quiet

    @property
    def cfg(self) -> FinetuneOptions:
        """The options the engine's loop reads (``lr``, ``log_every``, ``ckpt_every``)."""
        return self.o

    def log(self, msg: str) -> None:
        if not self.o.quiet:
            tqdm.write(msg)

    def setup(self) -> None:
        """Every check and the whole footage read, then the network, optimiser and state (from
        ``checkpoints/last.pt`` when resuming): ValueError of one line naming the option."""
        o = self.o
        check_numbers(o)
        last = runfolder.checkpoint_path(self.run, "last")
        resume = None
        if o.resume:
            resume = load_checkpoint(last, "resume")
            if not all(k in resume for k in ("optimizer", "state", "config")):
                raise FieldError("resume", "holds no fine-tuning state", where=f" {last}")
            o = resumed_options(o, resume["config"], last)
        for name in ("ckpt", "input"):
            if getattr(o, name) is None:
                raise FieldError(name, "missing: give it (or ", Ref("resume"), " a run)")
        o = replace(o, **{k: v for k, v in defaults(bool(o.known_motion)).items()
                          if getattr(o, k) is None})  # fmt: skip
        if o.known_motion and o.poses is None:
            raise FieldError("known_motion", "needs --poses (the camera's motion in camera axes)")
        self.o = o
        if o.threads > 0:
            torch.set_num_threads(o.threads)
        job = prepare(self._infer_options(last if resume else o.ckpt), out=False)
        source = resume if resume is not None else load_checkpoint(o.ckpt, "ckpt")
        self.job, self.d0, self.device = job, job.scale.d0, job.device
        self.shift = int(source.get("shift", NOMINAL_SHIFT))
        self.length = UNSUPERVISED_RECIPE.sequence_length
        self.stride = frame_stride(job.positions, self.d0, self.shift)
        self.store = footage_store(job, self.length, self.stride, not o.quiet)
        self.data = SequenceDataset(self.store, self.length, o.seed)
        self.steps_per_epoch = len(self.data) // o.batch_size
        if self.steps_per_epoch == 0:
            raise FieldError(
                "batch_size", f"larger than the {len(self.data)} sequences of the footage",
                where=f" {o.batch_size}",
            )  # fmt: skip
        self._network(resume, last)

    def _infer_options(self, ckpt: Path) -> InferOptions:
        o = self.o
        same = ("input", "speed", "poses", "fps", "fov", "focal", "res", "train_fov", "device")
        return InferOptions(
            ckpt=ckpt, out=self.run, quiet=o.quiet, **{k: getattr(o, k) for k in same}
        )

    def _network(self, resume: dict | None, last: Path) -> None:
        """The DepthPoseNet (a fresh PoseNet from ``seed``), optimiser, step and counters."""
        o, model = self.o, self.job.model
        torch.manual_seed(o.seed)
        self.own_pose = not isinstance(model, DepthPoseNet)
        net = DepthPoseNet(self.length, getattr(model, "width", 1.0), depth=model) if (
            self.own_pose) else model  # fmt: skip
        self.net = self.model = net.to(self.device)
        self.opt = make_optimizer(self.net.parameters(), replace(UNSUPERVISED_RECIPE, lr=o.lr))
        lam, kappa = smooth_settings(o.smooth_weight, None, o.occlusion)
        weights = UNSUPERVISED_RECIPE.loss_weights
        step = PhotometricStep(
            self.net,
            self.opt,
            self.device,
            weights,
            self.d0,
            lam,
            kappa,
            o.occlusion,
            known_translation=o.known_motion,
        )
        self.state = new_state()
        self.train_set, self.per_rank_batch = self.data, o.batch_size
        self.train_step = FinetuneStep(
            self.net, step, o.pose_warmup, self.state, o.poses is not None
        )
        self.sampler = EpochSampler(len(self.data), o.seed)
        batches = EpochBatches(self.sampler, o.batch_size)
        self.loader = torch.utils.data.DataLoader(
            PairBatches(self.data), batch_size=None, sampler=batches
        )
        if resume is None:
            return
        try:
            if self.own_pose:
                self.net.pose.load_state_dict(resume["pose"])
            self.opt.load_state_dict(resume["optimizer"])
            self.state.update(resume["state"])
        except (KeyError, ValueError, TypeError, RuntimeError) as e:
            raise FieldError(
                "resume", f"its training state does not fit ({first_line(e)})", where=f" {last}"
            ) from None

    # ------------------------------------------------------------ the run folder

    def config(self) -> dict:
        """config.json: the options (resolved) and what was derived from them."""
        options = {f.name: _plain(getattr(self.o, f.name)) for f in fields(self.o)}
        job = self.job
        return {
            "command": "finetune",
            **options,
            "model_name": job.info["model_name"],
            "nominal_displacement": self.d0,
            "shift": self.shift,
            "sequence_length": self.length,
            "stride": self.stride,
            "sequences": len(self.data),
            "stretches": [len(s.rgb) for s in self.store.scenes],
            "frames_in": job.source.count,
            "input_size": list(job.size),
            "crop": asdict(job.crop),
            "K": self.store.scenes[0].K.tolist(),
            "recipe": {k: _plain(v) for k, v in asdict(UNSUPERVISED_RECIPE).items()},
        }

    def checkpoint(self, name: str) -> None:
        """Every save writes both checkpoints: checkpoints/last.pt (the training state) and
        best.pt (the depth network alone; without ground truth there is nothing to choose by,
        so it is the last network). Weights that are not finite are never saved."""
        self.check_finite_weights()
        depth = self.net.depth if self.own_pose else self.net
        info = self.job.info
        plain = {
            "model": depth.state_dict(),
            "model_name": info["model_name"],
            "nominal_displacement": self.d0,
            "shift": self.shift,
            "depth_range": [float(v) for v in info["depth_range"]],
            "camera": {
                "width": self.job.size[0],
                "height": self.job.size[1],
                "fov_deg": float(info["fov_deg"]),
            },  # fmt: skip
            "state": {k: self.state[k] for k in COUNTERS},
            "config": self.config(),
        }
        full = {**plain, "optimizer": self.opt.state_dict()}
        if self.own_pose:
            full["pose"] = self.net.pose.state_dict()
        runfolder.save_checkpoint(runfolder.checkpoint_path(self.run, "last"), full)
        runfolder.save_checkpoint(runfolder.checkpoint_path(self.run, "best"), plain)

    def _start_folder(self) -> None:
        for p in runfolder.start_logs(self.run, self.o.resume, self.state["global_step"]):
            self.log(f"removed {p}, left by an interrupted checkpoint write")
        runfolder.write_config(self.run, self.config())
        runfolder.write_environment(self.run, environment(self.device))
        self.tb = runfolder.tensorboard_writer(self.run)
        if not runfolder.has_tensorboard():
            self.log(runfolder.TENSORBOARD_MISSING)

    # ------------------------------------------------------------ training

    def total_steps(self) -> int:
        return self.o.steps

    def end_of_stage(self) -> None:
        """No validation: the stage's sums are dropped; the last step saves both checkpoints."""
        self.close_stage()
        if self.state["global_step"] >= self.total_steps():
            self.checkpoint("last")

    def step_row(self, loss: float) -> dict:
        """steps.csv: step, epoch, phase, loss, photometric, smooth, pose_cosine, lr."""
        st, terms = self.state, self.train_step.logged()
        return {"step": st["global_step"], "epoch": st["epoch"], "phase": terms.pop("phase"),
                "loss": loss, **terms, "lr": self.opt.param_groups[0]["lr"]}  # fmt: skip

    def fit(self) -> dict:
        """Train to ``steps`` (Ctrl-C or SIGTERM: stop at the next step boundary, saving both
        checkpoints, then KeyboardInterrupt); returns the summary (:func:`describe`)."""
        self._start_folder()
        start, first = time.perf_counter(), self.state["global_step"]
        super().fit()
        return self.summary(self.train_step.losses, first, time.perf_counter() - start)

    def summary(self, losses: dict[str, list[float]], first: int, seconds: float) -> dict:
        """What the run did, for :func:`describe` (losses: this session's, per phase)."""
        return {
            "steps": self.state["global_step"],
            "resumed_at": first,
            "pose_warmup": min(self.o.pose_warmup, self.state["global_step"]),
            "loss": {p: [v[0], v[-1]] for p, v in losses.items() if v},
            "seconds": seconds,
            "stretches": describe_stretches(self.store),
            "stride": self.stride,
            "sequences": len(self.data),
            "best": str(runfolder.checkpoint_path(self.run, "best")),
        }


def describe(s: dict) -> str:
    """The one-paragraph summary printed at the end."""
    parts = [f"{p} loss {a:.4f} -> {b:.4f}" for p, (a, b) in s["loss"].items()]
    since = f" (resumed at step {s['resumed_at']})" if s["resumed_at"] else ""
    return (
        f"Fine-tuned {s['steps']} steps{since}, the first {s['pose_warmup']} with the DepthNet "
        f"frozen (pose warm-up), in {s['seconds'] / 60:.1f} min, on {s['sequences']} sequences "
        f"of {s['stretches']} (one frame in {s['stride']} kept); {'; '.join(parts) or 'no step'}. "
        f"The fine-tuned depth network: {s['best']} (use it with 'infer' or 'eval')."
    )


def finetune(o: FinetuneOptions) -> dict:
    """Check, read, then fine-tune into ``o.out`` holding its lock (stillbox_gen.lock); returns
    the summary. Every check is done before the run folder is written."""
    from stillbox_gen.lock import folder_lock

    with folder_lock(Path(o.out), "--out"):
        tuner = Finetuner(o)
        tuner.setup()
        return tuner.fit()
