"""Training throughput: samples per second of one optimiser step (issue 15).

A timed step is what the training loop does per batch: assemble the batch, forward pass,
multi-scale loss, backward pass, optimiser step and ``loss.item()``. Batches are real training
pairs (``PairDataset`` in train mode on the first scenes of a dataset's train split) when a
dataset is given, else random inputs and targets (then no time goes to data). Each network is
timed with the training defaults (``levers on``: fused optimiser, whole-batch assembly,
channels-last memory format when TrainConfig's default says so, ``torch.compile`` when asked)
and, with ``baseline``, with every lever off (torch's default optimiser, contiguous format,
items assembled one by one and collated, as before issue 15), the two alternating step by step
in the same process so that both see the same load on a shared machine. The median step time
is reported, after untimed warm-up steps.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import time
from pathlib import Path

import torch

from ..core import registry
from ..core.config import TrainConfig
from ..core.data import EpochSampler, FrameStore, PairDataset, load_scenes
from ..core.errors import FieldError
from ..core.registry import Target
from ..engine.pair_step import TrainStep
from ..engine.train import make_optimizer
from .speed import TRAIN_BATCHES, _sync, csv_name

DEFAULT_SIZE = 64  # square input size of random batches, pixels (a dataset has its own)


def default_steps(batch: int) -> tuple[int, int]:
    """(warm-up, timed) steps for a batch size: about 24 warm-up and 160 timed samples, at least
    1 and 3 steps (so 3 + 20 steps at batch 8, 1 + 3 at batch 256)."""
    return max(1, math.ceil(24 / batch)), max(3, math.ceil(160 / batch))


class _Batches:
    """Training batches of one network: real pairs (``pairs``) or one random batch."""

    def __init__(self, target: Target, batch: int, pairs: PairDataset | None, size: int, seed: int):
        self.batch, self.pairs = batch, pairs
        if pairs is None:
            g = torch.Generator().manual_seed(seed)
            if target is Target.FLOW:  # pixels
                values = torch.randn((batch, 2, size, size), generator=g) * 3
            else:  # metres
                values = torch.rand((batch, size, size), generator=g) * 100
            self.random = {
                "input": torch.randn(batch, 6, size, size, generator=g),
                "target": values,
            }
        else:
            self.sampler = EpochSampler(len(pairs), seed)
            self.order: list[int] = []
            self.epoch = -1

    def indices(self) -> list[int]:
        if len(self.order) < self.batch:
            self.epoch += 1
            self.sampler.set_epoch(self.epoch)
            self.order = list(self.sampler)
        idx, self.order = self.order[: self.batch], self.order[self.batch :]
        return idx

    def get(self, levers: bool) -> dict:
        """A batch: whole-batch assembly with the levers on, single items collated without."""
        if self.pairs is None:
            return self.random
        idx = self.indices()
        if levers:
            return self.pairs.batch(idx, self.epoch)
        self.pairs.set_epoch(self.epoch)
        return torch.utils.data.default_collate([self.pairs[i] for i in idx])


def _variant(
    name: str,
    device: torch.device,
    levers: bool,
    compile_: bool,
    autocast: torch.dtype | None = None,
) -> TrainStep:
    spec = registry.MODELS[name]
    cfg = TrainConfig(model=name, data="", out="", **dataclasses.asdict(spec.recipe))
    torch.manual_seed(0)
    model = spec.build().to(device).train()
    channels_last = levers and cfg.channels_last
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    net = torch.compile(model) if levers and compile_ else model
    opt = make_optimizer(model.parameters(), cfg, fused=levers)
    return TrainStep(
        net, opt, device, cfg.loss_weights, cfg.loss_scale, channels_last, autocast=autocast
    )


def _pairs(data: Path, target: Target, needed: int, seed: int) -> PairDataset:
    """Train-mode pairs of the first train scenes holding at least ``needed`` frames."""
    scenes, frames = [], 0
    for s in load_scenes(data, "train"):
        if frames >= needed:
            break
        scenes.append(s)
        frames += len(s.rgb)
    if not scenes:
        raise FieldError("data", "has no train scenes", where=f" {data}")
    return PairDataset(FrameStore(scenes, progress=False), "train", seed=seed, target=target.value)


def measure(
    names: list[str] | tuple[str, ...],
    device: torch.device,
    batches: tuple[int, ...] = TRAIN_BATCHES,
    data: Path | None = None,
    size: int = DEFAULT_SIZE,
    baseline: bool = False,
    compile_: bool = False,
    warmup: int | None = None,
    steps: int | None = None,
    seed: int = 0,
    amp: bool = False,
) -> list[dict]:
    """One row per network, batch size and variant (levers on; off too with ``baseline``; on
    under bfloat16 autocast too with ``amp``, variant "bf16"): ``ms_per_step`` (median),
    ``samples_per_s``, ``data_share`` (share of the step spent assembling the batch),
    ``vs_baseline`` (samples/s over the baseline's: levers off, else with ``amp`` levers on; 1
    for the baseline), ``data`` (the dataset, or ``random``). ``warmup``/``steps`` None:
    :func:`default_steps`."""
    rows = []
    for name in names:
        target = registry.MODELS[name].kind.target
        for batch in batches:
            w, n = default_steps(batch)
            w, n = (w if warmup is None else warmup), (n if steps is None else steps)
            variants = {"on": _variant(name, device, True, compile_)}
            if baseline:
                variants["off"] = _variant(name, device, False, False)
            if amp:
                variants["bf16"] = _variant(name, device, True, compile_, torch.bfloat16)
            pairs = None
            if data is not None:
                pairs = _pairs(data, target, len(variants) * batch * (w + n), seed)
            feeds = {v: _Batches(target, batch, pairs, size, seed) for v in variants}
            times: dict[str, list[float]] = {v: [] for v in variants}
            waits: dict[str, list[float]] = {v: [] for v in variants}
            for i in range(w + n):
                for v, step in variants.items():  # alternate: both see the same load
                    _sync(device)
                    t0 = time.perf_counter()
                    b = feeds[v].get(v != "off")
                    t1 = time.perf_counter()
                    step(b).item()
                    _sync(device)
                    if i >= w:
                        times[v].append(time.perf_counter() - t0)
                        waits[v].append(t1 - t0)
            ref = "off" if baseline else "on" if amp else None
            base = statistics.median(times[ref]) if ref else None
            for v in variants:
                t = statistics.median(times[v])
                rows.append(
                    {
                        "model": name,
                        "output": target.value,
                        "batch": batch,
                        "px": f"{size}x{size}"
                        if pairs is None
                        else f"{pairs.store.width}x{pairs.store.height}",
                        "levers": v,
                        "compile": v != "off" and compile_,
                        "ms_per_step": round(t * 1e3, 2),
                        "samples_per_s": round(batch / t, 1),
                        "data_share": round(sum(waits[v]) / sum(times[v]), 4),
                        "vs_baseline": round(base / t, 3) if base else "",
                        "data": str(data) if pairs is not None else "random",
                        "device": str(device),
                        "threads": torch.get_num_threads(),
                        "torch": torch.__version__,
                        "warmup": w,
                        "steps": n,
                    }
                )
    return rows


def train_csv_name(device: torch.device) -> str:
    """``train-speed-<device>-<threads>t-torch<version>.csv`` (like speed.csv_name)."""
    return "train-" + csv_name(device)


def markdown(rows: list[dict]) -> str:
    """The rows as a markdown table (device, threads, torch, warm-up and steps left out)."""
    skip = ("device", "threads", "torch", "warmup", "steps")
    keys = [k for k in rows[0] if k not in skip]
    lines = ["| " + " | ".join(keys) + " |", "|---" * len(keys) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(str(r[k]) for k in keys) + " |")
    return "\n".join(lines)
