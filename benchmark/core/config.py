"""The configuration of a training run, as written to its ``config.json`` (docs/RUNS.md).

Hyper-parameters default to DepthNet's recipe (:data:`benchmark.core.registry.DEPTH_RECIPE`); a run
of another method starts from that method's recipe (``runner.train_config``). The command line's
defaults are read from here (:func:`default`), so every number is written once.
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, fields

from .registry import DEPTH_RECIPE

_R = DEPTH_RECIPE

EVAL_BATCH_SIZE = 64  # pairs per forward pass when scoring (results do not depend on it)
#: the largest --seed: torch.manual_seed takes an unsigned 64-bit integer
MAX_SEED = 2**64 - 1


@dataclass
class TrainConfig:
    """Everything a training run depends on.

    ``model``: registry name; ``data``: dataset folder; ``out``: run folder. The recipe fields
    (``epochs`` … ``depth_range``) are those of :class:`benchmark.core.registry.Recipe` (``shift``:
    nominal frame shift of the pairs; ``depth_range``: metres, targets clipped and outputs
    clamped to it); ``threads``: torch intra-op threads (0: torch's default); ``ckpt_every``:
    optimiser steps between mid-epoch ``last.pt`` checkpoints (0: epoch ends only);
    ``log_every``: steps between ``steps.csv`` rows; ``cache``: decoded frames in memory (None:
    when they fit).

    Speed switches (README "Speed on this machine"; results equal within floating-point noise
    unless said): ``channels_last``: network and inputs in channels-last memory format (on this
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
    epochs: int = _R.epochs
    max_steps: int | None = None  # stop after this many optimiser steps (smoke runs)
    batch_size: int = _R.batch_size
    lr: float = _R.lr
    optimizer: str = _R.optimizer
    momentum: float = _R.momentum
    dampening: float = _R.dampening
    beta2: float = _R.beta2
    weight_decay: float = _R.weight_decay
    milestones: tuple[float, ...] = _R.milestones
    gamma: float = _R.gamma
    loss_weights: tuple[float, ...] = _R.loss_weights
    loss_scale: float = _R.loss_scale
    shift: int = _R.shift
    depth_range: tuple[float, float] = _R.depth_range
    device: str = "auto"
    threads: int = 0
    seed: int = 0
    pretrained: str | None = None
    resume: bool = False
    eval_batch_size: int = EVAL_BATCH_SIZE
    ckpt_every: int = 200
    log_every: int = 10
    cache: bool | None = None
    save_predictions: bool = False
    progress: bool = True
    channels_last: bool = False
    compile: bool = False
    amp: bool | None = None
    workers: int | None = None


def default(name: str):
    """The default of TrainConfig field ``name`` (KeyError for a field without one)."""
    field = {f.name: f for f in fields(TrainConfig)}[name]
    if field.default is MISSING:
        raise KeyError(f"TrainConfig.{name} has no default")
    return field.default
