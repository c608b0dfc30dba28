"""Training speed (issue 15): whole-batch assembly gives the same tensors as collating single
pairs, the batches keep the sampler's order, the training step's levers keep the loss, and
``stillbox-bench speed --train`` writes its table (speed itself is never asserted)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
from conftest import invoke_main
from test_bench import bench
from torch.utils.data import DataLoader, default_collate

from benchmark import cli
from benchmark.core import registry
from benchmark.core.config import TrainConfig
from benchmark.core.data import (
    EpochBatches,
    EpochSampler,
    FrameStore,
    PairBatches,
    PairDataset,
    load_scenes,
)
from benchmark.engine.pair_step import TrainStep
from benchmark.engine.train import make_optimizer


@pytest.fixture(scope="module")
def store(tiny_dataset) -> FrameStore:
    return FrameStore(load_scenes(tiny_dataset, "train"), progress=False)


def assert_same_batch(a: dict, b: dict) -> None:
    """Same keys, dtypes, shapes and values, bit for bit (NaN where NaN)."""
    assert a.keys() == b.keys()
    for k in a:
        x, y = a[k], b[k]
        assert (x.dtype, x.shape) == (y.dtype, y.shape), k
        if x.is_floating_point():
            assert torch.equal(x.isnan(), y.isnan()), k
            x, y = x.nan_to_num(), y.nan_to_num()
        assert torch.equal(x, y), k


@pytest.mark.parametrize(
    ("mode", "target", "depth_range"),
    [
        ("train", "depth", (0.0, 100.0)),
        ("train", "depth", (10.0, 60.0)),
        ("train", "flow", (0.0, 100.0)),
        ("eval", "depth", (0.0, 100.0)),
    ],
)
def test_batch_equals_collated_items(store, mode, target, depth_range):
    ds = PairDataset(store, mode, 3, seed=4, target=target, depth_range=depth_range)
    order = list(range(len(ds)))[::-1]
    for epoch in (0, 1, 5):
        ds.set_epoch(epoch)
        old = default_collate([ds[i] for i in order])
        ds.set_epoch(0)  # batch() takes the epoch it is given
        assert_same_batch(ds.batch(order, epoch), old)


def test_pairs_are_the_original_draws(store):
    """The four uniforms drawn in one call are those of four rng.uniform() calls: the pairs and
    flips of a seed are those of the sampling before issue 15."""
    ds = PairDataset(store, "train", 3, seed=9)
    for epoch in (0, 2):
        for i in range(len(ds)):
            k, _ = ds.items[i]
            rng = np.random.default_rng([9, epoch, i])
            last = len(store.scenes[k].rgb) - 1
            i1 = int(rng.integers(0, last + 1))
            i2 = min(last, i1 + round(2 * 3 * rng.uniform()))
            if rng.uniform() > 0.5:
                i1, i2 = i2, i1
            flip_h, flip_v = rng.uniform() < 0.5, rng.uniform() < 0.5
            assert ds._draw(i, epoch) == (k, i1, i2, flip_h, flip_v)


@pytest.mark.parametrize("workers", [0, 2])
def test_epoch_batches_follow_the_sampler(store, workers):
    """The loader of the training loop yields the batches of the per-item DataLoader it
    replaced (same order, last incomplete batch dropped, resumable mid-epoch), also from worker
    processes whose copy of the dataset never saw set_epoch."""
    ds = PairDataset(store, "train", 3, seed=2)
    sampler = EpochSampler(len(ds), seed=2)
    loader = DataLoader(
        PairBatches(ds),
        batch_size=None,
        sampler=EpochBatches(sampler, 3),
        num_workers=workers,
        persistent_workers=workers > 0,
    )
    old = DataLoader(ds, batch_size=3, sampler=sampler, drop_last=True)
    for epoch, skip in ((0, 0), (1, 0), (1, 6)):
        sampler.set_epoch(epoch, skip)
        ds.set_epoch(epoch)
        got, want = list(loader), list(old)
        assert len(got) == len(want) == len(loader) == (len(ds) - skip) // 3
        for a, b in zip(got, want, strict=True):
            assert_same_batch(a, b)


@pytest.mark.parametrize("model", ["depthnet-tiny", "flownets-flow-tiny"])
def test_levers_keep_the_loss_within_float_noise(model):
    """Channels-last format and the fused optimiser: the same losses over a few steps."""
    spec = registry.MODELS[model]
    cfg = TrainConfig(model, "", "")
    flow = spec.kind.target is registry.Target.FLOW
    if flow:
        cfg.optimizer, cfg.lr = "adam", 1e-4
    g = torch.Generator().manual_seed(0)
    x = torch.randn(4, 6, 64, 64, generator=g)
    shape = (4, 2, 64, 64) if flow else (4, 64, 64)
    y = torch.rand(shape, generator=g) * (3 if flow else 100)
    losses = []
    for levers in (False, True):
        torch.manual_seed(0)
        net = spec.build().train()
        if levers:
            net = net.to(memory_format=torch.channels_last)
        opt = make_optimizer(net.parameters(), cfg, fused=levers)
        step = TrainStep(net, opt, torch.device("cpu"), cfg.loss_weights, 1.0, levers)
        losses.append([step({"input": x, "target": y}).item() for _ in range(4)])
    np.testing.assert_allclose(losses[1], losses[0], rtol=1e-4)


def test_speed_train_writes_its_table(tiny_dataset, tmp_path):
    args = ["speed", "--train", "--models", "depthnet-tiny,flownets-flow-tiny", "--batches", "2"]
    args += ["--warmup", 1, "--repeats", 1, "--out", tmp_path]
    proc = invoke_main(cli.main, *args, "--baseline", "--data", tiny_dataset)
    assert proc.returncode == 0, proc.stderr
    (path,) = tmp_path.glob("train-speed-cpu*.csv")
    rows = list(csv.DictReader(path.read_text().splitlines()))
    assert [(r["model"], r["levers"]) for r in rows] == [
        ("depthnet-tiny", "on"),
        ("depthnet-tiny", "off"),
        ("flownets-flow-tiny", "on"),
        ("flownets-flow-tiny", "off"),
    ]
    assert {r["output"] for r in rows} == {"depth", "flow"}
    assert all(r["data"] == str(tiny_dataset) and float(r["samples_per_s"]) > 0 for r in rows)
    assert all(r["batch"] == "2" and r["steps"] == "1" for r in rows)
    assert f"training pairs of {tiny_dataset}" in proc.stdout and str(path) in proc.stdout
    proc = invoke_main(cli.main, *args, "--out", tmp_path / "random")
    assert proc.returncode == 0, proc.stderr
    assert "random inputs and targets" in proc.stdout
    (path,) = (tmp_path / "random").glob("train-speed-cpu*.csv")
    rows = list(csv.DictReader(path.read_text().splitlines()))
    assert [r["data"] for r in rows] == ["random", "random"] and rows[0]["vs_baseline"] == ""


def test_speed_train_amp_times_the_bf16_step_against_float32(tmp_path):
    """--amp adds a bfloat16-autocast row, alternated with the float32 levers-on step, whose
    ratio is against that step; the step really runs under autocast."""
    from benchmark.supervised.train_speed import _variant

    args = ["speed", "--train", "--models", "depthnet-tiny", "--batches", "2", "--amp"]
    proc = invoke_main(cli.main, *args, "--warmup", 1, "--repeats", 1, "--out", tmp_path)
    assert proc.returncode == 0, proc.stderr
    (path,) = tmp_path.glob("train-speed-cpu*.csv")
    rows = {r["levers"]: r for r in csv.DictReader(path.read_text().splitlines())}
    assert list(rows) == ["on", "bf16"] and float(rows["on"]["vs_baseline"]) == 1
    assert float(rows["bf16"]["vs_baseline"]) > 0 and "bfloat16 autocast" in proc.stdout
    step = _variant("depthnet-tiny", torch.device("cpu"), True, False, torch.bfloat16)
    assert step.autocast is torch.bfloat16
    x = torch.randn(2, 6, 64, 64)
    with torch.autocast("cpu", torch.bfloat16):  # what the step's forward runs under
        assert step.net(x)[0].dtype is torch.bfloat16
    assert torch.isfinite(step({"input": x, "target": torch.rand(2, 64, 64) * 100}))
    alone = invoke_main(cli.main, "speed", "--amp", "--out", tmp_path / "latency")
    assert alone.returncode == 2 and "--amp: only with --train" in alone.stderr


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--models", "constant"], ["--models", "no network"]),
        (["--batches", "8,x"], ["--batches"]),
        (["--batches", "0"], ["--batches"]),
        (["--data", "/nonexistent/dataset"], ["--data"]),
    ],
)
def test_bad_speed_train_input_is_a_one_line_error(args, words):
    proc = invoke_main(cli.main, "speed", "--train", *args)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert all(w in lines[0] for w in words), lines[0]


def test_run_flags_reach_the_config(tiny_dataset, tmp_path):
    """`run --channels-last --amp` trains with them (recorded in config.json); defaults stay off
    on the CPU (amp None: CUDA only)."""
    on, off = tmp_path / "on", tmp_path / "off"
    common = ("--data", tiny_dataset, "--batch-size", 4, "--max-steps", 1, "--quiet")
    bench("run", "depthnet-tiny", "--out", on, "--channels-last", "--amp", *common)
    bench("run", "depthnet-tiny", "--out", off, *common)
    c_on = json.loads((on / "config.json").read_text())
    c_off = json.loads((off / "config.json").read_text())
    assert (c_on["channels_last"], c_on["amp"], c_on["compile"]) == (True, True, False)
    assert (c_off["channels_last"], c_off["amp"], c_off["compile"]) == (False, None, False)
