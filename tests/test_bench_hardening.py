"""stillbox-bench hardening: checkpoints never run code, checkpoint writes survive kills, resumed
logs equal uninterrupted ones, and bad input is one line naming the flag with nothing left behind.
"""

from __future__ import annotations

import csv
import dataclasses
import importlib.util
import json
import math
import os
import shutil
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import TINY_SHARES, CliResult, run_cli
from test_bench import bench

from benchmark.core import registry, runfolder
from benchmark.core.config import TrainConfig
from benchmark.core.data import load_scenes
from benchmark.engine import pair_step, train
from benchmark.engine.runner import train_config
from stillbox_gen.manifest import split_of


def assert_bench_error(proc: CliResult | subprocess.CompletedProcess, *words: str) -> str:
    """A user mistake: exit 2, one stderr line ``stillbox-bench: error: ...`` naming ``words``,
    no traceback."""
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("stillbox-bench: error: "), proc.stderr
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


def write_checkpoint(path: Path, name: str = "depthnet-tiny", **changes) -> Path:
    """A checkpoint of network ``name`` as 'run' writes it (weights, model name, displacement),
    with ``changes`` to its entries."""
    payload = {
        "model": registry.build_model(name).state_dict(),
        "model_name": name,
        "nominal_displacement": 0.3,
        "shift": 3,
        **changes,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(payload, path)
    return path


class CreatesFile:
    """Unpickling this calls open(path, 'w'): it creates ``path`` if the pickle is executed."""

    def __init__(self, path: Path):
        self.path = path

    def __reduce__(self):
        return (open, (str(self.path), "w"))


# ------------------------------------------------------------------ checkpoints never run code


@pytest.mark.render
@pytest.mark.parametrize("flag", ["--ckpt", "--pretrained", "--resume"])
def test_malicious_checkpoint_is_refused_not_executed(tiny_dataset, tmp_path, flag):
    marker = tmp_path / "executed"
    out = tmp_path / "out"
    evil = tmp_path / "evil.pt"
    if flag == "--resume":
        evil = out / "checkpoints" / "last.pt"
    write_checkpoint(evil, model=CreatesFile(marker))
    if flag == "--ckpt":
        args = ["eval", "--ckpt", evil, "--data", tiny_dataset, "--out", out]
    else:
        args = ["run", "depthnet-tiny", "--data", tiny_dataset, "--batch-size", 4, "--quiet"]
        args += ["--out", out, *(["--resume"] if flag == "--resume" else ["--pretrained", evil])]
    proc = bench(*args, check=False)
    assert not marker.exists(), "the checkpoint's pickle was executed"
    assert_bench_error(proc, flag, str(evil), "refused")
    assert flag == "--resume" or not out.exists()


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (b"not a checkpoint", ["not a readable checkpoint"]),
        (b"", ["not a readable checkpoint"]),
        ("state_dict", ["bare state_dict"]),
        ("tensor", ["not a stillbox-bench checkpoint"]),
        ("mismatch", ["its weights do not fit 'depthnet'", "conv1.0.weight"]),
    ],
    ids=["junk", "empty", "state_dict", "tensor", "mismatch"],
)
@pytest.mark.render
def test_eval_of_an_unusable_checkpoint_is_one_line(tiny_dataset, tmp_path, content, words):
    ckpt = tmp_path / "c.pt"
    if isinstance(content, bytes):
        ckpt.write_bytes(content)
    elif content == "state_dict":
        torch.save(registry.build_model("depthnet-tiny").state_dict(), ckpt)
    elif content == "tensor":
        torch.save(torch.zeros(3), ckpt)
    else:  # depthnet-tiny weights labelled as the full-width DepthNet
        write_checkpoint(ckpt, model_name="depthnet")
    out = tmp_path / "out"
    proc = bench("eval", "--ckpt", ckpt, "--data", tiny_dataset, "--out", out, check=False)
    assert_bench_error(proc, "--ckpt", str(ckpt), *words)
    assert not out.exists()


@pytest.mark.render
def test_pretrained_from_another_architecture_is_one_line(tiny_dataset, tmp_path):
    ckpt = write_checkpoint(tmp_path / "flownets.pt", "flownets-depth-tiny")
    out = tmp_path / "out"
    proc = bench(
        "run", "depthnet-tiny", "--data", tiny_dataset, "--pretrained", ckpt, "--out", out,
        "--quiet", check=False,
    )  # fmt: skip
    assert_bench_error(proc, "--pretrained", str(ckpt), "flownets-depth-tiny", "'depthnet-tiny'")
    assert not out.exists()


# ------------------------------------------------------------------ bad flags leave nothing


BAD_FLAGS = [
    (["run", "depthnet-tiny", "--device", "foo"], ["--device", "foo"]),
    (["run", "constant", "--device", "foo"], ["--device", "foo"]),
    (["eval", "--ckpt", "CKPT", "--device", "foo"], ["--device", "foo"]),
    (["compare", "--models", "constant", "--device", "foo"], ["--device", "foo"]),
    (["speed", "--models", "depthnet-tiny", "--device", "cuda:x"], ["--device", "cuda:x"]),
    (["run", "depthnet-tiny", "--lr", "-1"], ["--lr", "-1"]),
    (["compare", "--models", "depthnet-tiny", "--lr", "0"], ["--lr"]),
    (["eval", "--ckpt", "CKPT", "--batch-size", "0"], ["--batch-size", "0"]),
    (["run", "depthnet-tiny", "--log-every", "0"], ["--log-every"]),
    (["run", "depthnet-tiny", "--batch-size", "1000"], ["--batch-size", "1000"]),
    (["run", "depthnet-tiny", "--seed", "-1"], ["--seed", "-1"]),
    (["compare", "--models", "depthnet-tiny", "--seed", str(2**64)], ["--seed"]),
]


@pytest.mark.render
@pytest.mark.parametrize(("args", "words"), BAD_FLAGS, ids=[" ".join(a) for a, _ in BAD_FLAGS])
def test_bad_flag_is_one_line_and_leaves_no_out_folder(tiny_dataset, tmp_path, args, words):
    ckpt = write_checkpoint(tmp_path / "c.pt")
    args = [str(ckpt) if a == "CKPT" else a for a in args]
    out = tmp_path / "out"
    data = [] if args[0] == "speed" else ["--data", tiny_dataset]
    quiet = ["--quiet"] if args[0] in ("run", "compare") else []
    proc = bench(*args, *data, *quiet, "--out", out, check=False)
    assert_bench_error(proc, *words)
    assert not out.exists()


# ------------------------------------------------------------------ checkpoint writes


def test_checkpoint_write_is_fsynced_before_the_rename(tmp_path, monkeypatch):
    path = tmp_path / "last.pt"
    seen = []
    fsync = os.fsync

    def spy(fd: int) -> None:
        seen.append((path.exists(), os.path.isdir(os.readlink(f"/proc/self/fd/{fd}"))))
        fsync(fd)

    monkeypatch.setattr(os, "fsync", spy)
    runfolder.save_checkpoint(path, {"x": torch.ones(2)})
    assert seen == [(False, False), (True, True)]  # the file before the rename, then the folder
    assert torch.load(path, weights_only=True)["x"].tolist() == [1.0, 1.0]
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]


def test_start_logs_cuts_a_resumed_run_back_and_a_new_one_afresh(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    for step in (1, 2, 3):
        runfolder.append_row(run, runfolder.STEPS_CSV, {"step": step, "loss": 10.0 / step})
    stale = run / "checkpoints" / ".last.pt.tmp-1"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"half")
    assert runfolder.start_logs(run, resume=True, last_step=2) == [stale]
    rows = runfolder.read_rows(run, runfolder.STEPS_CSV)
    assert [(r["step"], r["loss"]) for r in rows] == [("1", "10.0"), ("2", "5.0")]
    best = runfolder.checkpoint_path(run, "best")
    best.write_bytes(b"x")
    (run / "tb").mkdir()
    assert runfolder.start_logs(run, resume=False, last_step=0) == []
    assert not (run / "steps.csv").exists() and not best.exists() and not (run / "tb").exists()


def test_report_files_round_trip(tmp_path):
    """summary.json keeps NaN (a metric without value) and key order; per_sample.csv its rows."""
    summary = {"model": "m", "metrics": {"mae": float("nan"), "images": 0}, "z": [1, 2]}
    rows = [{"scene": 0, "mae": 1.5}, {"scene": 1, "mae": 2.5}]
    pixels = {"gt": np.arange(3, dtype=np.float32)}
    runfolder.write_report(tmp_path, summary, "# m\n", rows, pixels)
    back = runfolder.read_summary(tmp_path)
    assert list(back) == ["model", "metrics", "z"] and math.isnan(back["metrics"]["mae"])
    assert (tmp_path / "per_sample.csv").read_text() == "scene,mae\n0,1.5\n1,2.5\n"
    assert runfolder.read_pixels(tmp_path)["gt"].tolist() == [0.0, 1.0, 2.0]
    assert (tmp_path / "summary.md").read_text() == "# m\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "per_sample.csv", "pixels.npz", "summary.json", "summary.md"
    ]  # fmt: skip


@pytest.mark.render
def test_stale_checkpoint_temporary_is_removed_on_start(tiny_dataset, tmp_path):
    out = tmp_path / "run"
    stale = [out / "checkpoints" / ".last.pt.tmp-1", out / "checkpoints" / ".best.pt.tmp-2"]
    for p in stale:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"half a checkpoint")
    cfg = train_config(
        "depthnet-tiny", tiny_dataset, out, batch_size=4, max_steps=1, progress=False
    )
    trainer = train.Trainer(cfg)
    trainer.setup()
    assert not any(p.exists() for p in stale)
    trainer.tb.close()


# ------------------------------------------------------------------ resumed logs


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _train(cfg: TrainConfig) -> None:
    trainer = train.Trainer(cfg)
    trainer.setup()
    trainer.fit()


def _config(data: Path, out: Path) -> TrainConfig:
    return train_config(
        "depthnet-tiny", data, out, batch_size=4, epochs=2, log_every=1, ckpt_every=0,
        progress=False,
    )  # fmt: skip


@pytest.fixture(scope="module")
def uninterrupted(tiny_dataset, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("uninterrupted") / "run"
    _train(_config(tiny_dataset, out))
    return out


@pytest.mark.render
def test_own_checkpoints_load_with_weights_only(uninterrupted):
    """Trainer checkpoints (weights, optimiser and scheduler state, config) hold only what the
    safe unpickler accepts."""
    for name in ("last.pt", "best.pt"):
        ck = torch.load(uninterrupted / "checkpoints" / name, weights_only=True)
        assert ck["model_name"] == "depthnet-tiny" and ck["state"]["global_step"] == 14
        assert ck["optimizer"]["state"] and ck["scheduler"]["milestones"]


@pytest.mark.render
@pytest.mark.parametrize(
    ("stop_at", "sig"),
    [(3, signal.SIGINT), (7, signal.SIGINT), (3, signal.SIGTERM)],
    ids=["mid-epoch", "last-step-of-epoch", "SIGTERM-mid-epoch"],
)
def test_resumed_epoch_logs_the_uninterrupted_train_loss(
    tiny_dataset,
    uninterrupted,
    tmp_path,
    monkeypatch,
    stop_at,
    sig,
):
    """Ctrl-C (or SIGTERM, as `timeout` and job schedulers send) after step ``stop_at`` (7 steps
    per epoch), then --resume: metrics.csv and steps.csv equal those of an uninterrupted run."""
    expected = _rows(uninterrupted / "metrics.csv")
    assert [int(r["step"]) for r in expected] == [7, 14]
    cfg = _config(tiny_dataset, tmp_path / "run")
    loss, calls = pair_step.multiscale_loss, []

    def loss_then_ctrl_c(*args):
        calls.append(1)
        if len(calls) == stop_at:
            signal.raise_signal(sig)
        return loss(*args)

    monkeypatch.setattr(pair_step, "multiscale_loss", loss_then_ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        _train(cfg)
    assert len(calls) == stop_at
    monkeypatch.setattr(pair_step, "multiscale_loss", loss)
    _train(dataclasses.replace(cfg, resume=True))
    got = _rows(Path(cfg.out) / "metrics.csv")
    assert [r["step"] for r in got] == [r["step"] for r in expected]
    for g, e in zip(got, expected, strict=True):
        assert float(g["train_loss"]) == pytest.approx(float(e["train_loss"]), rel=1e-9), g["step"]
        assert float(g["val_mae"]) == pytest.approx(float(e["val_mae"]), rel=1e-6), g["step"]
    steps = _rows(Path(cfg.out) / "steps.csv")
    assert [int(r["step"]) for r in steps] == list(range(1, 15))


def test_run_resume_keeps_max_steps_and_intervals_unless_given_again(tiny_dataset, tmp_path):
    """--max-steps, --log-every and --ckpt-every left out of --resume are the run's (the
    defaults would log every 10th step and train to the end of the epochs)."""
    out = tmp_path / "run"
    common = ("depthnet-tiny", "--data", tiny_dataset, "--out", out, "--batch-size", 4,
              "--epochs", 2, "--threads", 1, "--quiet")  # fmt: skip
    bench("run", *common, "--max-steps", 2, "--log-every", 1, "--ckpt-every", 1)
    bench("run", *common, "--resume", "--max-steps", 4)
    assert [int(r["step"]) for r in _rows(out / "steps.csv")] == [1, 2, 3, 4]
    config = json.loads((out / "config.json").read_text())
    assert (config["max_steps"], config["log_every"], config["ckpt_every"]) == (4, 1, 1)
    bench("run", *common, "--resume")  # the run's 4 steps: nothing more is trained
    assert torch.load(out / "checkpoints" / "last.pt")["state"]["global_step"] == 4


def _tb_steps(folder: Path, tag: str) -> tuple[list[int], list[int]]:
    """Steps of ``tag`` as TensorBoard's EventAccumulator shows them, and as the event files hold
    them (every record of every file, in file order: what a reader without purging sees)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    acc = EventAccumulator(str(folder))
    acc.Reload()
    shown = [e.step for e in acc.Scalars(tag)]
    raw = [
        e.step
        for path in sorted(folder.glob("events.out.tfevents.*"))
        for e in EventFileLoader(str(path)).Load()
        if any(v.tag == tag for v in e.summary.value)
    ]
    return shown, raw


@pytest.mark.render
def test_resume_keeps_one_tensorboard_point_per_step(tiny_dataset, tmp_path, monkeypatch):
    """Events logged after the checkpoint a run resumes from (as a kill -9 between checkpoints
    leaves them: here the run went on to step 14, then last.pt was put back to its step-3 state,
    and the newest event file got a record cut short) are dropped on --resume: TensorBoard and
    the raw event files hold each train/loss and epoch step once, none missing."""
    cfg = _config(tiny_dataset, tmp_path / "run")
    out, loss, calls = Path(cfg.out), pair_step.multiscale_loss, []

    def loss_then_ctrl_c(*args):
        calls.append(1)
        if len(calls) == 3:
            signal.raise_signal(signal.SIGINT)
        return loss(*args)

    monkeypatch.setattr(pair_step, "multiscale_loss", loss_then_ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        _train(cfg)
    monkeypatch.setattr(pair_step, "multiscale_loss", loss)
    last = runfolder.checkpoint_path(out, "last")
    at_step_3 = last.read_bytes()
    _train(dataclasses.replace(cfg, resume=True))
    assert _tb_steps(out / "tb", "train/loss")[1] == list(range(1, 15))
    last.write_bytes(at_step_3)
    newest = sorted((out / "tb").glob("events.out.tfevents.*"))[-1]
    with open(newest, "ab") as f:
        f.write(b"\x30\x00\x00\x00")  # a record cut short by the kill
    _train(dataclasses.replace(cfg, resume=True))
    assert _tb_steps(out / "tb", "train/loss") == (list(range(1, 15)),) * 2
    assert _tb_steps(out / "tb", "epoch/val_mae") == ([7, 14],) * 2
    assert [int(r["step"]) for r in _rows(out / "steps.csv")] == list(range(1, 15))


@pytest.mark.render
def test_a_run_without_the_tensorboard_package_trains_and_resumes_without_events(
    tiny_dataset, tmp_path, monkeypatch
):
    """`.[bench]` without the `tb` extra: run and --resume train, log steps.csv and
    metrics.csv as usual, write no tb/ and say once why; environment.json records no version."""
    real = importlib.util.find_spec
    hidden = lambda name, *a: None if name == "tensorboard" else real(name, *a)  # noqa: E731
    monkeypatch.setattr(importlib.util, "find_spec", hidden)
    out = tmp_path / "run"
    args = ("--data", tiny_dataset, "--batch-size", 4, "--log-every", 1, "--quiet", "--out", out)
    first = bench("run", "depthnet-tiny", "--max-steps", 2, "--ckpt-every", 1, *args)
    assert (
        first.stderr.count(runfolder.TENSORBOARD_MISSING)
        + first.stdout.count(runfolder.TENSORBOARD_MISSING)
        == 1
    )
    bench("run", "depthnet-tiny", "--max-steps", 3, "--resume", *args)
    assert [int(r["step"]) for r in _rows(out / "steps.csv")] == [1, 2, 3]
    assert not (out / "tb").exists()
    assert json.loads((out / "environment.json").read_text())["tensorboard"] is None


@pytest.mark.render
def test_rerun_after_a_kill_before_the_first_checkpoint_starts_logs_afresh(
    tiny_dataset,
    tmp_path,
):
    """A run killed before any checkpoint leaves logs but nothing to resume: running the same
    command again replaces them instead of appending duplicate rows."""
    out = tmp_path / "run"
    (out / "tb").mkdir(parents=True)
    (out / "tb" / "events.out.tfevents.killed").write_bytes(b"")
    with open(out / "steps.csv", "w") as f:
        f.write("step,epoch,loss,lr\n" + "".join(f"{s},0,20.0,0.01\n" for s in (1, 2, 3)))
    (out / "checkpoints").mkdir()
    bench(
        "run", "depthnet-tiny", "--data", tiny_dataset, "--batch-size", 4, "--max-steps", 2,
        "--log-every", 1, "--quiet", "--out", out,
    )  # fmt: skip
    assert [int(r["step"]) for r in _rows(out / "steps.csv")] == [1, 2]
    assert [int(r["step"]) for r in _rows(out / "metrics.csv")] == [2]
    assert not (out / "tb" / "events.out.tfevents.killed").exists()


# ------------------------------------------------------------------ every check before --out


def _copy_with_broken_test_frame(data: Path, to: Path) -> Path:
    """A copy of ``data`` whose first test scene has one frame that does not decode."""
    shutil.copytree(data, to)
    victim = load_scenes(to, "test")[0].rgb[5]
    victim.write_bytes(b"not a png")
    return victim


@pytest.fixture(scope="module")
def dataset_32px(tmp_path_factory) -> Path:
    """tiny_dataset's scenes at 32 px: frames DepthNet (multiples of 64) cannot read."""
    seed = next(
        s
        for s in range(100)
        if {split_of(s, k, TINY_SHARES) for k in range(6)} == {"train", "val", "test"}
    )
    out = tmp_path_factory.mktemp("bench32") / "tiny32"
    split = ",".join(map(str, TINY_SHARES))
    run_cli("--res", 32, "--scenes", 6, "--seed", seed, "--split", split, "--out", out, "--quiet")
    return out


@pytest.mark.render
def test_run_on_32px_frames_is_refused_before_writing(dataset_32px, tmp_path):
    out = tmp_path / "out"
    proc = bench("run", "depthnet-tiny", "--data", dataset_32px, "--out", out, "--quiet",
                 check=False)  # fmt: skip
    assert_bench_error(proc, "--data", str(dataset_32px), "32x32", "multiples of 64")
    assert not out.exists()


@pytest.mark.render
def test_run_with_a_broken_test_scene_is_refused_before_training(tiny_dataset, tmp_path):
    """The test split is scored only after training, but read (every frame) before --out is
    made: a broken test frame costs no training and leaves no checkpoint."""
    data = tmp_path / "data"
    victim = _copy_with_broken_test_frame(tiny_dataset, data)
    out = tmp_path / "out"
    proc = bench(
        "run", "depthnet-tiny", "--data", data, "--batch-size", 4, "--max-steps", 1, "--quiet",
        "--out", out, check=False,
    )  # fmt: skip
    assert_bench_error(proc, victim.name)
    assert not out.exists()


@pytest.mark.render
@pytest.mark.parametrize("command", ["run", "eval", "report"])
def test_out_that_cannot_be_made_is_one_line(tiny_dataset, tmp_path, command):
    out = Path("/proc/stillbox-bench-test")
    ckpt = write_checkpoint(tmp_path / "c.pt")
    summary = {"model": "m", "metrics": {"mae": 1.0}}
    runfolder.write_report(tmp_path / "r", summary, "", [], {})
    args = {
        "run": ["run", "depthnet-tiny", "--data", tiny_dataset, "--batch-size", 4, "--quiet"],
        "eval": ["eval", "--ckpt", ckpt, "--data", tiny_dataset],
        "report": ["report", tmp_path / "r"],
    }[command]
    target = out / "cmp" if command == "report" else out
    proc = bench(*args, "--out", target, check=False)
    if command == "eval":  # after its frame-caching progress bar, which \r clears
        proc = dataclasses.replace(proc, stderr=proc.stderr.rsplit("\r", 1)[-1])
    assert_bench_error(proc, "--out", f"cannot create '{out}")


# ------------------------------------------------------------------ resume keeps its settings


@pytest.mark.render
def test_resume_refuses_changed_settings_and_keeps_its_own(tiny_dataset, tmp_path):
    """A resumed run trains with its checkpoint's optimiser, schedule and sampling position, so a
    new --batch-size, --epochs, --lr, --clamp or --seed is refused (config.json and last.pt
    untouched); options left out are the run's own, and --max-steps may grow."""
    out = tmp_path / "run"
    common = ["run", "depthnet-tiny", "--data", tiny_dataset, "--quiet", "--out", out]
    bench(*common, "--batch-size", 4, "--epochs", 2, "--seed", 5, "--max-steps", 2)
    config = (out / "config.json").read_bytes()
    last = runfolder.checkpoint_path(out, "last").read_bytes()
    changes = [("--batch-size", "8", "4"), ("--epochs", "3", "2"), ("--lr", "0.5", "0.01")]
    changes += [("--clamp", "10,60", "0,100"), ("--seed", "0", "5")]
    for flag, value, then in changes:
        proc = bench(*common, "--resume", flag, value, check=False)
        line = assert_bench_error(proc, flag, f"trained with {then}, not {value}")
        assert "resumed run keeps its settings" in line
    assert (out / "config.json").read_bytes() == config
    assert runfolder.checkpoint_path(out, "last").read_bytes() == last
    bench(*common, "--resume", "--max-steps", 3, "--batch-size", 4)
    recorded = json.loads((out / "config.json").read_text())
    assert (recorded["batch_size"], recorded["epochs"], recorded["seed"]) == (4, 2, 5)
    assert (recorded["max_steps"], recorded["resume"]) == (3, True)
    steps = torch.load(runfolder.checkpoint_path(out, "last"), weights_only=True)["state"]
    assert steps["global_step"] == 3


# ------------------------------------------------------------------ non-finite loss


@pytest.mark.render
def test_huge_lr_stops_on_the_first_non_finite_value(tiny_dataset, tmp_path):
    out = tmp_path / "run"
    proc = bench(
        "run", "depthnet-tiny", "--data", tiny_dataset, "--batch-size", 4, "--lr", "1e300",
        "--quiet", "--out", out, check=False,
    )  # fmt: skip
    line = assert_bench_error(proc, "training stopped", "at step ", "(epoch 0)", "--lr")
    assert "no checkpoint was saved" in line
    assert not runfolder.checkpoint_path(out, "last").exists()
    assert not (out / "summary.json").exists()


@pytest.mark.render
def test_nan_loss_keeps_the_last_good_checkpoint(tiny_dataset, tmp_path, monkeypatch):
    """The loss turns NaN at step 3 (checkpoints every step): training stops there in one line
    naming step 3, and last.pt is step 2's, with finite weights."""
    loss, calls = pair_step.multiscale_loss, []

    def nan_at_step_3(*args):
        calls.append(1)
        return loss(*args) * (math.nan if len(calls) == 3 else 1.0)

    monkeypatch.setattr(pair_step, "multiscale_loss", nan_at_step_3)
    cfg = dataclasses.replace(_config(tiny_dataset, tmp_path / "run"), ckpt_every=1)
    with pytest.raises(train.NonFiniteLoss, match=r"loss is nan at step 3 \(epoch 0\)"):
        _train(cfg)
    ck = torch.load(runfolder.checkpoint_path(cfg.out, "last"), weights_only=True)
    assert ck["state"]["global_step"] == 2
    assert all(torch.isfinite(v).all() for v in ck["model"].values() if v.is_floating_point())
    assert [int(r["step"]) for r in _rows(Path(cfg.out) / "steps.csv")] == [1, 2]


# ------------------------------------------------------------------ checkpoint metadata


BAD_METADATA = [
    ({"nominal_displacement": "0.3"}, "'nominal_displacement' is '0.3'"),
    ({"nominal_displacement": math.nan}, "'nominal_displacement' is nan"),
    ({"nominal_displacement": -1.0}, "'nominal_displacement' is -1.0"),
    ({"nominal_displacement": None}, "'nominal_displacement' is None"),
    ({"depth_range": [60.0, 10.0]}, "'depth_range' is [60.0, 10.0]"),
    ({"depth_range": [0.0, math.inf]}, "'depth_range' is [0.0, inf]"),
    ({"shift": 0}, "'shift' is 0"),
    ({"shift": 2.5}, "'shift' is 2.5"),
    ({"camera": {"width": 64, "height": 64, "fov_deg": math.nan}}, "'camera.fov_deg' is nan"),
    ({"camera": {"width": "64", "height": 64, "fov_deg": 90.0}}, "'camera.width' is '64'"),
    ({"camera": [64, 64]}, "'camera' is [64, 64]"),
]


@pytest.mark.render
@pytest.mark.parametrize(("change", "words"), BAD_METADATA, ids=[w for _, w in BAD_METADATA])
def test_eval_refuses_unusable_checkpoint_metadata(tiny_dataset, tmp_path, change, words):
    ckpt = write_checkpoint(tmp_path / "c.pt", **change)
    out = tmp_path / "out"
    proc = bench("eval", "--ckpt", ckpt, "--data", tiny_dataset, "--out", out, check=False)
    assert_bench_error(proc, f"--ckpt {ckpt}", words)
    assert not out.exists()


@pytest.mark.render
def test_eval_refuses_a_shift_the_scenes_cannot_give(tiny_dataset, tmp_path):
    ckpt = write_checkpoint(tmp_path / "c.pt", shift=10)
    out = tmp_path / "out"
    proc = bench("eval", "--ckpt", ckpt, "--data", tiny_dataset, "--out", out, check=False)
    assert_bench_error(proc, f"--ckpt {ckpt}", "'shift' 10", "10 frames")
    assert not out.exists()


@pytest.mark.render
@pytest.mark.parametrize(
    "command", ["infer", "eval-multishift", "eval-sequences", "pretrained", "resume"]
)
def test_every_reader_checks_checkpoint_metadata(tiny_dataset, tmp_path, command):
    """The same check (checkpoint.check_metadata) and line for every command reading one."""
    out = tmp_path / "out"
    ckpt = tmp_path / "c.pt"
    if command == "resume":
        ckpt = runfolder.checkpoint_path(out, "last")
    write_checkpoint(ckpt, nominal_displacement=math.nan)
    run = ["run", "depthnet-tiny", "--data", tiny_dataset, "--quiet", "--out", out]
    args = {
        "infer": ["infer", "--ckpt", ckpt, "--input", load_scenes(tiny_dataset, "test")[0].rgb[0]
                  .parent, "--speed", 1, "--fps", 10, "--quiet", "--out", out],
        "eval-multishift": ["eval-multishift", "--ckpt", ckpt, "--data", tiny_dataset,
                            "--max-shift", 3, "--quiet", "--out", out],
        "eval-sequences": ["eval-sequences", "--ckpt", ckpt, "--data", tiny_dataset, "--quiet",
                           "--out", out],
        "pretrained": [*run, "--pretrained", ckpt],
        "resume": [*run, "--resume"],
    }[command]  # fmt: skip
    proc = bench(*args, check=False)
    flag = {"pretrained": "--pretrained", "resume": "--resume"}.get(command, "--ckpt")
    assert_bench_error(proc, f"{flag} {ckpt}", "'nominal_displacement' is nan")
    assert command == "resume" or not out.exists()


# ------------------------------------------------------------------ report


def test_report_of_an_unreadable_summary_or_pixels_is_one_line(tmp_path):
    """A summary.json that is not JSON (or not a summary) and a pixels.npz holding an object
    array (never unpickled) are named in one line."""
    summary = {"model": "m", "metrics": {"mae": 1.0}}
    pixels = {"foe_distance": np.ones(3), "abs_err": np.ones(3)}
    good, bad = tmp_path / "good", tmp_path / "bad"
    runfolder.write_report(good, summary, "", [], pixels)
    runfolder.write_report(bad, summary, "", [], pixels)
    out = tmp_path / "cmp"
    assert bench("report", good, "--out", out).returncode == 0
    cases = [
        ("summary.json", b'{"model": "m", "metr'),
        ("summary.json", b"\xff\xfe not utf-8"),
        ("summary.json", b'["model", "metrics"]'),
        ("pixels.npz", b"not a zip"),
        ("pixels.npz", "objects"),
    ]
    marker = tmp_path / "executed"
    for name, content in cases:
        runfolder.write_report(bad, summary, "", [], pixels)
        if content == "objects":
            np.savez(bad / name, foe_distance=np.array([CreatesFile(marker)], dtype=object),
                     abs_err=np.ones(1))  # fmt: skip
        else:
            (bad / name).write_bytes(content)
        proc = bench("report", good, bad, "--out", tmp_path / "cmp2", check=False)
        assert_bench_error(proc, str(bad / name))
        assert not marker.exists(), "pixels.npz was unpickled"
        assert not list(tmp_path.glob("cmp2*")), name


def test_compare_reusing_an_unreadable_run_is_one_line(default_dataset, tmp_path):
    """compare reads a finished run of its --out as report does: the same one line."""
    summary = {"model": "constant", "metrics": {"mae": 1.0}}
    pixels = {"foe_distance": np.ones(3), "abs_err": np.ones(3)}
    run = tmp_path / "cmp" / "constant"
    for name, content in [("summary.json", b'{"model": "m", "metr'), ("pixels.npz", b"zip?")]:
        runfolder.write_report(run, summary, "", [], pixels)
        (run / name).write_bytes(content)
        proc = bench("compare", "--data", default_dataset, "--models", "constant",
                     "--out", tmp_path / "cmp", check=False)  # fmt: skip
        assert_bench_error(proc, str(run / name))
        assert not (tmp_path / "cmp" / "comparison.md").exists()
