"""stillbox-bench hardening: checkpoints never run code, checkpoint writes survive kills, resumed
logs equal uninterrupted ones, and bad input is one line naming the flag with nothing left behind.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import test_bench
import torch

from benchmark import models, train
from benchmark.runner import train_config

tiny_dataset = test_bench.tiny_dataset  # the fixture: six 64 px scenes, every split non-empty


def assert_bench_error(proc: subprocess.CompletedProcess, *words: str) -> str:
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
        "model": models.build_model(name).state_dict(),
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


# ------------------------------------------------------------------ checkpoint writes


def test_checkpoint_write_is_fsynced_before_the_rename(tmp_path, monkeypatch):
    path = tmp_path / "last.pt"
    seen = []
    fsync = os.fsync

    def spy(fd: int) -> None:
        seen.append((path.exists(), os.path.isdir(os.readlink(f"/proc/self/fd/{fd}"))))
        fsync(fd)

    monkeypatch.setattr(os, "fsync", spy)
    train.save_checkpoint(path, {"x": torch.ones(2)})
    assert seen == [(False, False), (True, True)]  # the file before the rename, then the folder
    assert torch.load(path, weights_only=True)["x"].tolist() == [1.0, 1.0]
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]


def test_stale_checkpoint_temporary_is_removed_on_start(tiny_dataset, tmp_path):
    out = tmp_path / "run"
    stale = [out / "checkpoints" / ".last.pt.tmp", out / "checkpoints" / ".best.pt.tmp"]
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
