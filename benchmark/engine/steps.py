"""The training step of each kind of method: one table from what a network learns
(core.registry.Target) to the maker of its training set and step.

A maker is called once by Trainer.setup, after the data are loaded, with the run's TrainConfig
``cfg``, the network as trained ``net`` (maybe compiled or DDP-wrapped), its optimiser ``opt``,
the ``device``, the training split's frames ``store`` (core.data.FrameStore), ``d0`` (metres: the
nominal displacement the depth answers for, shift × the split's median metres per frame) and
``autocast`` (the forward pass's dtype, None: float32) and ``progress``, the trainer's live
state (``progress["global_step"]``: optimiser steps done, resumed ones included). It returns the
training set (indexable, with ``set_epoch(epoch)`` and ``batch(indices, epoch)`` as
core.data.PairDataset) and the step: a callable that takes one batch, makes one optimiser step
and returns the loss (a 0-d tensor). A step may also have ``logged()``: more steps.csv columns
for its last call (:func:`logged_columns`; the photometric step's terms and PoseNet's direction).

The packages that define steps fill the table when imported: benchmark.engine.pair_step (depth
and flow learnt from pairs with ground truth, chapter 3), benchmark.unsupervised.training (depth
learnt from frame sequences without it, chapters 4-5). ``stillbox-bench`` imports both
(benchmark/cli/__init__.py); a script that trains an unsupervised method imports the second.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import torch

from ..core.registry import Target

#: one optimiser step on a batch; returns the loss before the step (0-d tensor)
Step = Callable[[dict], torch.Tensor]


class StepMaker(Protocol):
    def __call__(
        self,
        cfg: Any,
        net: torch.nn.Module,
        opt: torch.optim.Optimizer,
        device: torch.device,
        store: Any,
        d0: float,
        autocast: torch.dtype | None,
        progress: dict | None = None,
    ) -> tuple[Any, Step]: ...


#: {what a network learns: the maker of its training set and step}
STEP_MAKERS: dict[Target, StepMaker] = {}


def training_step(*targets: Target) -> Callable[[StepMaker], StepMaker]:
    """Decorator: register a maker as the training step of methods learning ``targets``."""

    def register(maker: StepMaker) -> StepMaker:
        for target in targets:
            STEP_MAKERS[target] = maker
        return maker

    return register


def step_maker(target: Target) -> StepMaker:
    """The registered maker for ``target``; LookupError when no imported package defines one."""
    try:
        return STEP_MAKERS[target]
    except KeyError:
        raise LookupError(
            f"no training step registered for target '{target.value}': import the package that "
            "defines it (benchmark.unsupervised.training for 'video'; stillbox-bench imports all)"
        ) from None


def logged_columns(step: Step) -> dict[str, float]:
    """The steps.csv columns of ``step``'s last call beside its loss: its ``logged()`` when it
    has one, else none (read at logged steps only: it may cost a synchronisation)."""
    logged = getattr(step, "logged", None)
    return logged() if logged is not None else {}
