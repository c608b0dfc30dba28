"""The reference harness (benchmark.supervised.reference) without the author's code, which is
not part of the project: the checkpoint conversion, the launcher's stand-ins, the split refusal,
and ``--epoch-size`` (the author's budget-scaled epochs)."""

from __future__ import annotations

import csv

import pytest
import torch

from benchmark.core import registry
from benchmark.core.checkpoint import load_checkpoint, load_weights
from benchmark.core.errors import FieldError
from benchmark.engine import runner
from benchmark.supervised import reference, reference_launcher


def test_convert_keeps_the_authors_weights(tiny_dataset, tmp_path):
    torch.manual_seed(0)
    net = registry.build_model("depthnet").eval()
    state = {f"module.{k}": v for k, v in net.state_dict().items()}  # DataParallel's names
    author = {"state_dict": state, "bn": True, "activation_function": "elu", "clamp": False}
    torch.save({**author, "epoch": 6}, tmp_path / "a.pth.tar")
    reference.convert(tmp_path / "a.pth.tar", tiny_dataset, tmp_path / "ours.pt")
    ck = load_checkpoint(tmp_path / "ours.pt", "ckpt")
    back = registry.build_model("depthnet").eval()
    load_weights(back, ck, "ckpt", tmp_path / "ours.pt", "depthnet")
    x = torch.randn(2, 6, 64, 64)
    assert torch.equal(back(x)[0], net(x)[0])
    assert ck["shift"] == 3 and ck["nominal_displacement"] == pytest.approx(0.3)
    torch.save({**author, "bn": False}, tmp_path / "b.pth.tar")
    with pytest.raises(FieldError, match="--bn --activation-function elu"):
        reference.convert(tmp_path / "b.pth.tar", tiny_dataset, tmp_path / "b.pt")


def test_the_split_needs_the_legacy_files(tiny_dataset):
    with pytest.raises(FieldError, match="--legacy"):
        reference.author_split(tiny_dataset)


def test_the_torchvision_stand_in_normalises_per_channel(monkeypatch):
    import sys

    for name in ("torchvision", "torchvision.transforms"):  # restored after the test
        monkeypatch.setitem(sys.modules, name, sys.modules.get(name))
    reference_launcher.torchvision_stand_in()
    import torchvision.transforms as T

    x = torch.rand(3, 4, 5) * 255
    steps = T.Compose([T.Normalize([0, 0, 0], [255] * 3), T.Normalize([0.5] * 3, [0.2] * 3)])
    torch.testing.assert_close(steps(x), (x / 255 - 0.5) / 0.2)


def test_epoch_size_sets_the_steps_per_epoch_and_the_schedule(tiny_dataset, tmp_path):
    cfg = runner.train_config(
        "depthnet-tiny", tiny_dataset, tmp_path / "r", epochs=4, epoch_size=2, batch_size=4,
        milestones=(0.5,), threads=1, progress=False,
    )  # fmt: skip
    trainer = runner.Trainer(cfg)
    trainer.setup()
    assert trainer.steps_per_epoch == 2 < len(trainer.train_set) // 4
    trainer.fit()
    with open(tmp_path / "r" / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["step"]) for r in rows] == [2, 4, 6, 8]
    # each row is written after its epoch's scheduler step: the lr of the epoch that follows
    assert [float(r["lr"]) for r in rows] == pytest.approx([1e-2, 3e-3, 3e-3, 3e-3])


def test_the_resolution_floor_is_the_error_of_the_downsampled_truth(tiny_dataset):
    import numpy as np

    from benchmark.core.data import load_scenes

    floor = reference.resolution_floor(tiny_dataset, "test")
    errors = []
    for scene in load_scenes(tiny_dataset, "test"):
        for f in range(3, scene.frames):
            gt = np.minimum(scene.load_depth(f).astype(np.float64), 100.0)
            quarter = gt.reshape(16, 4, 16, 4).mean(axis=(1, 3))
            up = torch.nn.functional.interpolate(
                torch.from_numpy(quarter)[None, None], size=(64, 64), mode="bilinear"
            )[0, 0].numpy()
            errors.append(np.abs(up - gt).mean())
    assert floor["pairs"] == len(errors)
    assert floor["mae"] == pytest.approx(np.mean(errors), rel=1e-5)
    assert floor["mae"] > 0.5  # depth edges: a 1/4-resolution output cannot reach zero


def test_report_reads_every_scored_checkpoint(tmp_path):
    import json

    for name, mae in (("author-s0-e6", 30.0), ("ours-s0-e6", 20.0), ("ours-s1-e12", 15.0)):
        (tmp_path / name).mkdir()
        summary = {
            "metrics": {"mae": mae, "mre": 1.0, "mle": 0.5, "depth_error": mae - 1, "p1.25": 0.2},
            "error_by_foe_distance": [
                {"from_px": 0.0, "to_px": 1.0, "mae": 2 * mae},
                {"from_px": 1.0, "to_px": None, "mae": mae},
            ],
        }
        (tmp_path / name / "summary.json").write_text(json.dumps(summary))
    rows = reference.collect(tmp_path, epoch_size=57, batch_size=32)
    assert [(r["code"], r["seed"], r["epoch"]) for r in rows] == [
        ("author", 0, 6), ("ours", 0, 6), ("ours", 1, 12)
    ]  # fmt: skip
    assert rows[2]["samples"] == 12 * 57 * 32 and rows[2]["mae_foe_0-1px"] == 30.0
    assert rows[2]["mae_foe_1-infpx"] == 15.0
    reference.plot(rows, tmp_path / "p.png", floor=4.8)
    assert (tmp_path / "p.png").stat().st_size > 1000
