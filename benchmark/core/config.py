"""The configuration of a training run, as written to its ``config.json`` (docs/RUNS.md).

Every setting of a run is one field of :class:`TrainConfig`, defined once here with, in its
metadata (:func:`setting`), whether a method's recipe sets it (:data:`Recipe` is made of those
fields; their defaults are DepthNet's recipe, the thesis one) and, for a setting the command line
offers, its :class:`Flag`: declaration, help per command, how the flag's text becomes the value
and the rule a value must follow. The click options of ``run`` and ``compare``, the copy of their
values into a TrainConfig, the checks of those values (:func:`check_settings`) and the recipes
are all read from these fields: a new training knob is one field here (plus its validation when
it needs more than a rule). A run of a method starts from that method's recipe
(``runner.train_config``).
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable
from dataclasses import MISSING, dataclass, field, fields, make_dataclass
from typing import Any

from stillbox_gen.conventions import MAX_DEPTH, NOMINAL_SHIFT

from .errors import FieldError

EVAL_BATCH_SIZE = 64  # pairs per forward pass when scoring (results do not depend on it)
#: the largest --seed: torch.manual_seed takes an unsigned 64-bit integer
MAX_SEED = 2**64 - 1


@dataclass(frozen=True)
class Flag:
    """How a TrainConfig field is set on the command line.

    ``decl``: click's declaration (``"--epochs"``, ``"--amp/--no-amp"``); ``help``: its text per
    command offering it (``"run"``, ``"compare"``); in a recipe field's text ``{depth}`` and
    ``{clamped}`` stand for DepthNet's and the clamped DepthNet's values (the CLI fills them in).
    ``kind``: ``"int"``, ``"float"``, ``"text"``, ``"path"`` (a file), ``"flag"`` (on when given)
    or ``"switch"`` (``--x/--no-x``, None when neither is given); ``metavar``: click's.
    ``parse``: the given value -> the field's (a FieldError when it does not parse);
    ``rule``: (test, requirement): a given value must pass ``test``, else
    :func:`check_settings` refuses it with ``requirement`` (e.g. "must be at least 1").
    """

    decl: str
    help: dict[str, str]
    kind: str = "int"
    metavar: str | None = None
    parse: Callable[[Any], Any] | None = None
    rule: tuple[Callable[[Any], bool], str] | None = None

    @property
    def name(self) -> str:
        """The flag as messages name it (``--amp`` for ``--amp/--no-amp``)."""
        return self.decl.split("/")[0]


def setting(default, *, recipe: bool = False, flag: Flag | None = None):
    """A TrainConfig field: its ``default``, whether a method's recipe sets it (``recipe``) and
    its command-line ``flag`` (None: not on the command line)."""
    return field(default=default, metadata={"recipe": recipe, "flag": flag})


def parse_range(text: str) -> tuple[float, float]:
    """depth_range "LO,HI" -> (LO, HI) metres (FieldError when not two numbers; the range itself
    is checked by Trainer.setup, before the run folder exists)."""
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise FieldError(
            "depth_range", f"expected LO,HI in metres (e.g. 10,60), got '{text}'"
        ) from None
    return (lo, hi)


AT_LEAST_1 = (lambda v: v >= 1, "must be at least 1")
#: TrainConfig.pose of the depthnet-unsup* methods (thesis §5.2.1-5.2.2): PoseNet's translations
#: on stabilised data; on rotating data, the dataset's known rotations ("O" in Tables 5.1-5.2) with
#: PoseNet's translations, or PoseNet's 6 DoF (benchmark.unsupervised.rotation)
POSE_MODES = ("translation", "orientation", "6dof")
MODELS_DEFAULT = "  [default: model's]"  # a recipe field's default in compare's help


#: TrainConfig fields a resumed run takes from its checkpoint's config unless given again (they
#: may change: --max-steps 4000 continues a run stopped by --max-steps 2000)
KEPT_ON_RESUME = ("max_steps", "ckpt_every", "log_every")


@dataclass
class TrainConfig:
    """Everything a training run depends on.

    ``model``: registry name; ``data``: dataset folder; ``out``: run folder. The recipe fields
    (``epochs`` … ``depth_range``, the thesis recipe at 64/128 px, thesis 3.6): ``milestones``
    are fractions of the epoch count at which the learning rate is multiplied by ``gamma``
    (epochs 19, 30, 44, 53 of 55); ``loss_weights`` weigh the outputs finest (1/4) to coarsest
    (1/64); the loss is multiplied by ``loss_scale``. ``optimizer``: "sgd" (DepthNet recipe) or
    "adam" (public FlowNetS flow recipe); ``momentum`` is SGD's momentum or Adam's beta1;
    ``dampening`` is SGD's, ``beta2`` Adam's; ``pose_lr``: PoseNet's learning rate in a method
    that learns from video (None: ``lr``). ``shift``: the nominal frame shift of the training
    pairs (the network answers for ``shift`` × metres per frame); ``depth_range``: metres,
    training targets are clipped to it and a depth network's outputs are clamped to it when
    scored or used (DepthNet: [0, 100] m, the clamped DepthNet of thesis 6.4: [10, 60] m).
    ``max_steps``: stop after this many optimiser steps (smoke runs); ``epoch_size``: optimiser
    steps per epoch (0: one sample per training frame; the public DepthNet code's
    ``--epoch-size``, which fits the 55-epoch schedule to a smaller budget); ``threads``: torch
    intra-op threads (0: torch's default); ``ckpt_every``: optimiser steps between mid-epoch
    ``last.pt`` checkpoints (0: epoch ends only); ``log_every``: steps between ``steps.csv``
    rows; ``cache``: decoded frames in memory (None: when they fit).

    Speed switches (docs/SPEED.md, measured in docs/results/training-speed.md; results equal
    within floating-point noise unless said): ``channels_last``: network and inputs in
    channels-last memory format (on this
    2-core CPU 1.12× faster DepthNet steps at batch 256, 0.9× at batch 8: off by default);
    ``compile``: ``torch.compile`` the network (here 55 s of compilation, then 0.74× at batch 8:
    off by default); ``amp``: bfloat16 autocast of the forward pass (None: on CUDA devices that
    support it, off on the CPU, where it changes results by bfloat16 rounding; 1.5× at batch
    256 here); ``workers``: DataLoader worker processes assembling batches (None: none on the
    CPU, 2 persistent ones with pinned memory on CUDA). CUDA defaults are untested here.
    """

    model: str
    data: str
    out: str
    epochs: int = setting(
        55,
        recipe=True,
        flag=Flag(
            "--epochs",
            {
                "run": "Epochs (one sample per training frame each).  [default: model's, {depth}]",
                "compare": "Epochs of every network." + MODELS_DEFAULT,
            },
            rule=AT_LEAST_1,
        ),
    )
    max_steps: int | None = setting(
        None,
        flag=Flag(
            "--max-steps",
            {
                "run": "Stop after this many optimiser steps (smoke runs).",
                "compare": "Stop every training after this many steps.",
            },
            rule=AT_LEAST_1,
        ),
    )
    epoch_size: int = setting(
        0,
        flag=Flag(
            "--epoch-size",
            {
                "run": "Optimiser steps per epoch (0: one pass over the training frames); the "
                "learning-rate milestones, validations and checkpoints fall at epoch ends."
            },
            rule=(lambda v: v >= 0, "must be 0 (one pass over the training frames) or more"),
        ),
    )
    batch_size: int = setting(
        256,
        recipe=True,
        flag=Flag(
            "--batch-size",
            {
                "run": "Samples per optimiser step.  [default: model's, {depth}]",
                "compare": "Samples per optimiser step." + MODELS_DEFAULT,
                "finetune": "Sequences per step.  [default: {unsupervised}, the unsupervised "
                "recipe's]",
            },
            rule=AT_LEAST_1,
        ),
    )
    lr: float = setting(
        1e-2,
        recipe=True,
        flag=Flag(
            "--lr",
            {
                "run": "Initial SGD learning rate.  [default: model's, {depth}]",
                "compare": "Initial learning rate." + MODELS_DEFAULT,
                "finetune": "Adam's learning rate.  [default: {unsupervised}, the unsupervised "
                "recipe's]",
            },
            kind="float",
            rule=(lambda v: v > 0 and math.isfinite(v), "must be a positive number"),
        ),
    )
    pose_lr: float | None = setting(
        None,
        flag=Flag(
            "--pose-lr",
            {
                "run": "depthnet-unsup*, sfmlearner*: PoseNet's learning rate (the depth network "
                "keeps --lr; the schedule scales both).  [default: --lr]"
            },
            kind="float",
            rule=(lambda v: v > 0 and math.isfinite(v), "must be a positive number"),
        ),
    )
    optimizer: str = setting("sgd", recipe=True)
    momentum: float = setting(0.9, recipe=True)
    dampening: float = setting(0.9, recipe=True)
    beta2: float = setting(0.999, recipe=True)
    weight_decay: float = setting(4e-4, recipe=True)
    milestones: tuple[float, ...] = setting((19 / 55, 30 / 55, 44 / 55, 53 / 55), recipe=True)
    gamma: float = setting(0.3, recipe=True)
    loss_weights: tuple[float, ...] = setting((0.32, 0.08, 0.02, 0.01, 0.005), recipe=True)
    loss_scale: float = setting(1.0, recipe=True)
    shift: int = setting(
        NOMINAL_SHIFT,
        recipe=True,
        flag=Flag(
            "--shift",
            {
                "run": "Nominal frame shift of the training pairs.  [default: model's, {depth}; "
                "{clamped} for depthnet-clamped*]"
            },
        ),
    )
    depth_range: tuple[float, float] = setting(
        (0.0, MAX_DEPTH),
        recipe=True,
        flag=Flag(
            "--clamp",
            {
                "run": "Clip depth targets to [LO, HI] m and clamp the outputs to it where the "
                "network is used (thesis 6.4's clamped DepthNet).  [default: model's, {depth}; "
                "{clamped} for depthnet-clamped*]"
            },
            kind="text",
            metavar="LO,HI",
            parse=parse_range,
        ),
    )
    device: str = setting(
        "auto",
        flag=Flag(
            "--device",
            dict.fromkeys(("run", "compare"), "auto | cpu | cuda | cuda:N."),
            kind="text",
        ),
    )
    threads: int = setting(
        0,
        flag=Flag(
            "--threads",
            {
                "run": "Torch CPU threads (0 = torch default).",
                "compare": "Torch CPU threads.",
                "finetune": "Torch CPU threads (0 = torch default).",
            },
            rule=(lambda v: v >= 0, "must be 0 (torch default) or more"),
        ),
    )
    seed: int = setting(
        0,
        flag=Flag(
            "--seed",
            {
                "run": "Seed of initialisation and pair sampling.",
                "compare": "Seed of every training.",
                "finetune": "Seed of PoseNet's initialisation and the sampling.",
            },
            rule=(lambda v: 0 <= v <= MAX_SEED, f"must be an integer from 0 to {MAX_SEED}"),
        ),
    )
    pretrained: str | None = setting(
        None,
        flag=Flag(
            "--pretrained",
            {"run": "Checkpoint to start from (curriculum 64->128->...)."},
            kind="path",
            parse=str,
        ),
    )
    resume: bool = setting(
        False,
        flag=Flag(
            "--resume",
            {
                "run": "Continue the run in --out from checkpoints/last.pt, keeping its logs up to "
                "that checkpoint (an interrupted epoch's train loss is logged as if never "
                "interrupted)."
            },
            kind="flag",
        ),
    )
    eval_batch_size: int = setting(EVAL_BATCH_SIZE)
    ckpt_every: int = setting(
        200,
        flag=Flag(
            "--ckpt-every",
            {
                "run": "Steps between mid-epoch checkpoints.",
                "finetune": "Steps between checkpoints.",
            },
            rule=(lambda v: v >= 0, "must be 0 or more"),
        ),
    )
    log_every: int = setting(
        10,
        flag=Flag(
            "--log-every",
            dict.fromkeys(("run", "finetune"), "Steps between steps.csv rows."),
            rule=AT_LEAST_1,
        ),
    )
    cache: bool | None = setting(None)
    save_predictions: bool = setting(
        False,
        flag=Flag(
            "--save-predictions",
            {"run": "Store predicted depth maps (float32 .npy, full resolution)."},
            kind="flag",
        ),
    )
    progress: bool = setting(
        True,
        flag=Flag(
            "--quiet",
            dict.fromkeys(("run", "compare"), "No progress bars."),
            kind="flag",
            parse=operator.not_,
        ),
    )
    channels_last: bool = setting(
        False,
        flag=Flag(
            "--channels-last",
            {
                "run": "Channels-last memory format (1.12x at batch 256, 0.90x at batch 8 on the "
                "2-core CPU)."
            },
            kind="flag",
        ),
    )
    compile: bool = setting(
        False,
        flag=Flag(
            "--compile", {"run": "torch.compile the network (off: slower here)."}, kind="flag"
        ),
    )
    amp: bool | None = setting(
        None,
        flag=Flag(
            "--amp/--no-amp",
            {
                "run": "bfloat16 autocast of the forward pass.  [default: on CUDA only; changes "
                "results]"
            },
            kind="switch",
        ),
    )
    workers: int | None = setting(None)
    sequence_length: int = setting(5, recipe=True)
    occlusion: bool | None = setting(
        None,
        flag=Flag(
            "--occlusion",
            {
                "run": "depthnet-unsup*: drop the pixels the occlusion module finds hidden in "
                "each reference from the photometric loss (thesis 4.5.6)."
            },
            kind="flag",
            parse=lambda given: given or None,
        ),
    )
    known_motion: bool | None = setting(
        None,
        flag=Flag(
            "--known-motion",
            {
                "run": "depthnet-unsup on stabilised data: the dataset's camera translations "
                "replace PoseNet's in the photometric loss's warps (a control: depth learnt "
                "with the motion given, as finetune --known-motion)."
            },
            kind="flag",
            parse=lambda given: given or None,
        ),
    )
    pose_warmup: int | None = setting(
        None,
        flag=Flag(
            "--pose-warmup",
            {
                "run": "depthnet-unsup*, sfmlearner*: first steps with the DepthNet frozen (no "
                "gradient, its BatchNorm statistics kept) and PoseNet alone learning, for a "
                "--pretrained depth network (finetune's warm-up).  [default: 0]"
            },
            kind="int",
            rule=(lambda v: v >= 0, "must be 0 or more"),
        ),
    )
    smooth_weight: float | None = setting(
        None,
        recipe=True,
        flag=Flag(
            "--smooth-weight",
            {
                "run": "depthnet-unsup*, sfmlearner*: λ of the smooth loss (0: the photometric "
                "loss alone).  [default: Table 4.1's gradient-diffusion optimum × 1e-4]"
            },
            kind="float",
            rule=(lambda v: v >= 0 and math.isfinite(v), "must be a number ≥ 0"),
        ),
    )
    smooth_kappa: float | None = setting(None, recipe=True)
    pose: str | None = setting(
        None,
        recipe=True,
        flag=Flag(
            "--pose",
            {
                "run": "depthnet-unsup*: translation (PoseNet's 3 outputs, stabilised data), "
                "orientation (rotating data: the dataset's known rotations, PoseNet's "
                "translations) or 6dof (rotating data: depthnet-unsup-6dof*).  [default: "
                "model's]"
            },
            kind="text",
            metavar="MODE",
            rule=(lambda v: v in POSE_MODES, f"must be one of {', '.join(POSE_MODES)}"),
        ),
    )


#: TrainConfig's fields with a command-line flag, in TrainConfig's order
FLAGGED = tuple(f for f in fields(TrainConfig) if f.metadata.get("flag") is not None)

#: Training hyper-parameters of a method: TrainConfig's recipe fields, with their defaults
#: (DepthNet's recipe); registry.DEPTH_RECIPE, FLOW_RECIPE, CLAMPED_RECIPE are instances.
Recipe = make_dataclass(
    "Recipe",
    [
        (f.name, f.type, field(default=f.default))
        for f in fields(TrainConfig)
        if f.metadata.get("recipe")
    ],
    frozen=True,
)
Recipe.__module__ = __name__
Recipe.__doc__ = "Training hyper-parameters: TrainConfig's recipe fields (see its docstring)."


def flag_of(name: str) -> Flag | None:
    """The command-line flag of TrainConfig field ``name`` (None when it has none)."""
    return {f.name: f.metadata.get("flag") for f in fields(TrainConfig)}[name]


def check_settings(values: dict) -> None:
    """FieldError for the first of ``values`` (TrainConfig field -> value; None: the default
    applies) that breaks its field's rule, in TrainConfig's order."""
    for f in FLAGGED:
        flag, value = f.metadata["flag"], values.get(f.name)
        if value is not None and flag.rule is not None and not flag.rule[0](value):
            raise FieldError(f.name, f"{flag.rule[1]}, got {value}")


def default(name: str):
    """The default of TrainConfig field ``name`` (KeyError for a field without one)."""
    field_ = {f.name: f for f in fields(TrainConfig)}[name]
    if field_.default is MISSING:
        raise KeyError(f"TrainConfig.{name} has no default")
    return field_.default
