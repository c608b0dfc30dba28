"""The engine's training loop: what every training does between its setup and its last save.

Two configurations run it: ``run`` and ``compare`` (engine.train.Trainer: a registered method on
a generated dataset, validated at each epoch's end) and ``finetune``
(benchmark.unsupervised.finetune.Finetuner: a checkpoint on a user's footage, no validation).
A configuration sets up its network, optimiser, training set, step and run folder, then
:meth:`TrainingLoop.fit` draws each epoch's batches from a seeded permutation
(core.data.EpochSampler: resumable at any step), makes one optimiser step per batch, logs
``steps.csv`` every ``log_every`` steps, saves ``checkpoints/last.pt`` every ``ckpt_every``,
closes a stage at each epoch's end and at the last step (the configuration's
:meth:`~TrainingLoop.end_of_stage`), and stops on a NaN or infinite loss or weights
(:class:`NonFiniteLoss`) or at Ctrl-C or SIGTERM (the next step boundary, saving 'last').
"""

from __future__ import annotations

import math
import time

import torch
from tqdm import tqdm

from ..core import runfolder
from ..core.stopping import stop_requests
from .steps import logged_columns

#: the counters of a training: epochs and steps done (resumed ones included)
COUNTERS = ("epoch", "step_in_epoch", "global_step")
#: running sums of the open stage (steps since the last validation), kept in the checkpoint so
#: a resumed stage logs the same train_loss and samples/s as an uninterrupted one
STAGE_KEYS = ("stage_loss_sum", "stage_steps", "stage_samples", "stage_wait", "stage_seconds")


class NonFiniteLoss(ValueError):
    """Training stopped on a NaN or infinite loss or weights (one line: step, epoch, what is
    kept)."""


def new_state() -> dict:
    """The loop's state before the first step: counters and open-stage sums at 0."""
    return dict.fromkeys((*COUNTERS, *STAGE_KEYS), 0)


class TrainingLoop:
    """The loop of a configured training. A configuration sets, before :meth:`fit`:

    ``run`` (the run folder), ``cfg`` (its options: ``lr``, ``log_every`` steps between
    steps.csv rows, ``ckpt_every`` steps between saves of 'last', 0: stage ends only),
    ``state`` (:func:`new_state`, maybe resumed), ``device``, ``world`` and ``is_main_process``
    (DDP: rank 0 logs and saves), ``model`` (the network) and ``net`` (as trained: maybe
    compiled or DDP-wrapped), ``opt``, ``sched`` (stepped at each
    epoch's end; None: none), ``train_set`` (``set_epoch``), ``train_step`` (engine.steps.Step),
    ``sampler`` (core.data.EpochSampler), ``loader`` (its batches), ``per_rank_batch``,
    ``steps_per_epoch``, ``tb`` (runfolder.tensorboard_writer); and implements
    :meth:`total_steps`, :meth:`checkpoint` and :meth:`end_of_stage`.
    """

    #: the word for this training in messages ("training stopped: ...")
    label = "training"
    #: the progress bar's title (None: none)
    bar_title: str | None = None
    show_progress = True

    # ------------------------------------------------------------ what a configuration defines

    def total_steps(self) -> int:
        raise NotImplementedError

    def checkpoint(self, name: str) -> None:
        """Save ``checkpoints/<name>.pt`` ('last': the training state)."""
        raise NotImplementedError

    def end_of_stage(self) -> None:
        """Close the open stage (:meth:`close_stage`) at an epoch's end or the last step."""
        raise NotImplementedError

    def step_row(self, loss: float) -> dict:
        """The steps.csv row of the step just made (``loss``: its value before the step)."""
        return {
            "step": self.state["global_step"],
            "epoch": self.state["epoch"],
            "loss": loss,
            "lr": self.opt.param_groups[0]["lr"],
        } | logged_columns(self.train_step)

    # ------------------------------------------------------------ shared

    def close_stage(self) -> dict:
        """The open stage's sums (``STAGE_KEYS``), reset to 0 for the next one."""
        sums = {k: self.state[k] for k in STAGE_KEYS}
        self.state.update(dict.fromkeys(STAGE_KEYS, 0))
        return sums

    def check_finite_weights(self) -> None:
        """NonFiniteLoss (in every process) when a weight is NaN or infinite: such weights are
        never saved."""
        state = self.model.state_dict().values()
        if not all(torch.isfinite(t).all() for t in state if t.is_floating_point()):
            self._stop("the weights are not finite", self.state["global_step"])

    def _finite_everywhere(self, loss: float) -> bool:
        """True when the step's loss is finite in every process (one all-reduce under DDP, so
        all processes stop together)."""
        finite = math.isfinite(loss)
        if self.world > 1:
            flag = torch.tensor([0.0 if finite else 1.0], device=self.device)
            torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
            finite = flag.item() == 0.0
        return finite

    def _stop(self, what: str, step: int) -> None:
        """Raise NonFiniteLoss: ``what`` (a NaN or infinite loss or weights) at optimiser step
        ``step``. Nothing is saved after it, so checkpoints/last.pt stays the last one with
        finite weights; TensorBoard is closed first."""
        last = runfolder.checkpoint_path(self.run, "last")
        if self.is_main_process:
            self.tb.close()
        if self.world > 1:
            torch.distributed.destroy_process_group()
        kept = f"{last} is kept" if last.exists() else "no checkpoint was saved"
        raise NonFiniteLoss(
            f"{self.label} stopped: {what} at step {step} (epoch {self.state['epoch']}); try a "
            f"smaller --lr (this run: {self.cfg.lr:g}); {kept}"
        )

    def fit(self) -> None:
        """Train to ``total_steps``; Ctrl-C or SIGTERM stops at the next step boundary, saving
        'last' (then KeyboardInterrupt)."""
        with stop_requests() as stop:
            self._fit(stop)
        if stop:
            raise KeyboardInterrupt

    def _fit(self, stop: list) -> None:
        """Stages end at each epoch's end and at ``total_steps``. A stage whose end was reached
        but not closed (Ctrl-C on its last step) is closed first when resuming."""
        cfg, st = self.cfg, self.state
        total = self.total_steps()
        bar = tqdm(
            total=total,
            initial=st["global_step"],
            unit="step",
            desc=self.bar_title,
            dynamic_ncols=True,
            disable=not (self.show_progress and self.is_main_process),
        )
        while not stop:
            if st["stage_steps"] and (st["step_in_epoch"] == 0 or st["global_step"] >= total):
                self.end_of_stage()
            if st["global_step"] >= total:
                break
            self.train_set.set_epoch(st["epoch"])
            self.sampler.set_epoch(st["epoch"], skip=st["step_in_epoch"] * self.per_rank_batch)
            self.net.train()
            seconds0, t_segment = st["stage_seconds"], time.perf_counter()
            t_data = time.perf_counter()
            for batch in self.loader:
                st["stage_wait"] += time.perf_counter() - t_data
                value = self.train_step(batch).item()
                if not self._finite_everywhere(value):
                    bar.close()
                    self._stop(f"the loss is {value}", st["global_step"] + 1)
                st["global_step"] += 1
                st["step_in_epoch"] += 1
                st["stage_loss_sum"] += value
                st["stage_steps"] += 1
                st["stage_samples"] += len(batch["input"]) * self.world
                st["stage_seconds"] = seconds0 + time.perf_counter() - t_segment
                bar.set_postfix(  # shown at the bar's next refresh (at most 10 a second)
                    loss=f"{value:.3f}",
                    samples_s=f"{st['stage_samples'] / st['stage_seconds']:.0f}",
                    epoch=st["epoch"],
                    refresh=False,
                )
                bar.update(1)
                if self.is_main_process and st["global_step"] % cfg.log_every == 0:
                    self._log_step(value)
                if cfg.ckpt_every and st["global_step"] % cfg.ckpt_every == 0:
                    self.checkpoint("last")
                if st["global_step"] >= total or stop:
                    break
                if st["step_in_epoch"] >= self.steps_per_epoch:  # --epoch-size
                    break
                t_data = time.perf_counter()
            if st["step_in_epoch"] >= self.steps_per_epoch:
                st["epoch"] += 1
                st["step_in_epoch"] = 0
                if self.sched is not None:
                    self.sched.step()
            if stop:
                self.checkpoint("last")
        bar.close()
        if self.is_main_process:
            self.tb.close()
        if self.world > 1:
            torch.distributed.destroy_process_group()

    def _log_step(self, loss: float) -> None:
        """A steps.csv row and its numeric columns in TensorBoard (``train/<column>``)."""
        row = self.step_row(loss)
        runfolder.append_row(self.run, runfolder.STEPS_CSV, row)
        for k, v in row.items():
            if k not in ("step", "epoch", "lr") and isinstance(v, (int, float)):
                self.tb.add_scalar(f"train/{k}", v, self.state["global_step"])
