"""The SFMLearner baseline (thesis chapter 5, issue 24 part 2): DispNet + PoseNet trained without
pose normalisation, its depth scaled by PoseNet ("P") or the ground-truth median ("GT"), and
`run sfmlearner-tiny` end to end."""

from __future__ import annotations

import csv
import json
from dataclasses import asdict
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from test_bench import bench

from benchmark.core import registry
from benchmark.core.data import FrameStore, load_scenes
from benchmark.core.dispnet import ALPHA, BETA, DispNet, SfmLearnerNet
from benchmark.core.errors import FieldError
from benchmark.core.metrics import median_scale
from benchmark.engine.scaling import (
    pose_scale,
    pose_windows,
    scale_free_depth,
    window,
)
from benchmark.unsupervised.sequences import SequenceDataset
from benchmark.unsupervised.training import (
    EPSILON,
    PhotometricStep,
    compensate,
    smooth_settings,
    video_training,
)

RECIPE = registry.SFMLEARNER_RECIPE


def test_dispnet_reads_the_target_frame_and_gives_four_scales_of_bounded_disparity():
    torch.manual_seed(0)
    net = DispNet(width=0.125).eval()
    for h, w in ((64, 64), (48, 80), (65, 33)):  # any size: the decoder crops
        disps = net(torch.randn(2, 3, h, w))
        sizes = [tuple(d.shape[-2:]) for d in disps]
        assert sizes == [(-(-h // 2**s), -(-w // 2**s)) for s in range(4)], sizes
        for d in disps:
            assert d.min() >= BETA and d.max() <= ALPHA + BETA
    both = SfmLearnerNet(5, width=0.125).eval()
    pair = torch.randn(1, 6, 64, 64)
    other = torch.cat([torch.randn(1, 3, 64, 64), pair[:, 3:]], 1)  # another reference
    depth = both(pair)
    assert len(depth) == 4 and torch.equal(depth[0], 1 / both.depth(pair[:, 3:])[0])
    assert torch.equal(both(other)[0], depth[0])  # the single frame: the reference is not read
    depth, poses = both(pair, torch.randn(1, 15, 64, 64))
    assert poses.shape == (1, 5, 3) and torch.equal(depth[0], both(pair)[0])
    with pytest.raises(ValueError, match="3, H, W"):
        DispNet(0.125)(pair)


def test_registry_has_sfmlearner_scaled_without_a_nominal_displacement():
    for name in ("sfmlearner", "sfmlearner-tiny"):
        spec = registry.MODELS[name]
        assert spec.kind is registry.SCALE_FREE and spec.kind.target is registry.Target.VIDEO
        assert spec.kind.scored_as is registry.Scoring.SCALE_FREE and spec.kind.best_by == "mae"
        assert spec.recipe == RECIPE
    net = registry.build_model("sfmlearner-tiny")
    assert isinstance(net, SfmLearnerNet) and net.frames == RECIPE.sequence_length
    assert net.depth.encoder[0][0].out_channels == 4  # 32 / 8
    assert RECIPE.loss_weights == (1, 0.5, 0.25, 0.125)  # one per DispNet scale, eq. 5.5's 1/2^s
    unsup = asdict(registry.UNSUPERVISED_RECIPE)
    assert {k for k, v in asdict(RECIPE).items() if v != unsup[k]} == {"loss_weights"}


def test_median_scale_by_hand():
    nan = float("nan")
    gt = torch.tensor(
        [
            [[2.0, 4.0], [nan, 10.0]],  # valid 2, 4, 10: median 4
            [[1.0, 2.0], [3.0, 5.0]],  # even count: median 2.5
            [[200.0, 300.0], [50.0, 0.0]],  # clipped to 100 m as scored: 100, 100, 50 -> 100
            [[nan, 0.0], [-1.0, nan]],  # no valid pixel
        ]
    )
    pred = torch.tensor(
        [
            [[1.0, 2.0], [99.0, 4.0]],  # over the valid pixels 1, 2, 4: median 2
            [[1.0, 1.0], [1.0, 1.0]],
            [[5.0, 4.0], [3.0, 1.0]],  # 5, 4, 3: median 4
            [[1.0, 1.0], [1.0, 1.0]],
        ]
    )
    got = median_scale(pred, gt)
    torch.testing.assert_close(got[:3], torch.tensor([2.0, 2.5, 25.0], dtype=torch.float64))
    assert torch.isnan(got[3])


def test_pose_scale_and_windows_by_hand():
    # PoseNet's positions relative to the window's last frame; the pair is window frames 1, 4
    poses = torch.tensor([[[9.0, 9, 9], [3.0, 4, 0], [1.0, 1, 1], [2.0, 2, 2], [0.0, 0, 0]]])
    translation = torch.tensor([[0.0, 6.0, 8.0]])  # 10 m measured
    got = pose_scale(poses, torch.tensor([[1, 4]]), translation)
    torch.testing.assert_close(got, torch.tensor([10.0 / (EPSILON + 5.0)]))
    # the window ends at the pair's second frame, or is the scene's first one
    assert [window(i2, 10, 5) for i2 in (2, 3, 4, 7, 9)] == [0, 0, 0, 3, 5]


class _Store:
    """A FrameStore stand-in: frame f of scene k is filled with 10·k + f (uint8)."""

    height, width = 4, 6

    def __init__(self, frames: int):
        self.scenes = [SimpleNamespace(index=i, rgb=[None] * frames) for i in (7, 3)]

    def rgb(self, k: int, f: int) -> np.ndarray:
        return np.full((self.height, self.width, 3), 10 * k + f, np.uint8)


class _Flat(torch.nn.Module):
    """An SfmLearnerNet stand-in: depth 2 everywhere, fixed PoseNet positions."""

    frames = 5

    def __init__(self, poses: torch.Tensor):
        super().__init__()
        self.poses = poses

    def forward(self, pair):
        return [torch.full_like(pair[:, :1], 2.0)]

    def pose(self, sequence):
        assert sequence.shape[1:] == (15, _Store.height, _Store.width)
        return self.poses


def test_scale_free_depth_puts_the_prediction_in_metres_both_ways():
    store = _Store(frames=8)
    batch = {  # pairs (1, 4) of scene index 3 (position 1) and (4, 7) of scene index 7
        "scene": torch.tensor([3, 7]),
        "frames": torch.tensor([[1, 4], [4, 7]]),
        "translation": torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 0.5]]),
        "target": torch.stack([torch.full((4, 6), 30.0), torch.arange(24.0).view(4, 6) + 1]),
        "input": torch.zeros(2, 6, 4, 6),
    }
    sequence, where = pose_windows(store, batch, 5)
    assert where.tolist() == [[1, 4], [1, 4]]  # windows 0..4 and 3..7
    frames = (sequence.view(2, 5, 3, 4, 6)[..., 0, 0, 0] * 0.2 + 0.5) * 255
    torch.testing.assert_close(frames, torch.tensor([[10.0, 11, 12, 13, 14], [3, 4, 5, 6, 7]]))
    positions = torch.zeros(2, 5, 3)
    positions[:, 1] = torch.tensor([0.0, 0.0, 1.5])  # PoseNet: frame 1 moved 1.5 units
    out = scale_free_depth(_Flat(positions), batch, store, torch.device("cpu"))
    # P: 2 units × (3 m / 1.5 units) = 4 m; 2 × (0.5 / 1.5) = 2/3 m
    torch.testing.assert_close(out["depth"][:, 0, 0], torch.tensor([4.0, 2 / 3]), rtol=1e-4, atol=0)
    # GT: the ground truth's median (30; 12.5 for 1..24) everywhere, the prediction being flat
    torch.testing.assert_close(out["depth_gt"][:, 2, 3], torch.tensor([30.0, 12.5]))
    assert out["depth_q"].shape == (2, 1, 1, 1)
    with pytest.raises(ValueError, match="4 frames"):
        pose_windows(store, {**batch, "frames": torch.tensor([[0, 6], [1, 4]])}, 5)


@pytest.fixture(scope="module")
def sequences(tiny_dataset) -> SequenceDataset:
    return SequenceDataset(FrameStore(load_scenes(tiny_dataset, "train"), progress=False), 5)


class _Known(torch.nn.Module):
    """Answers a batch's true depth (one full-resolution scale) and true positions, × ``c``."""

    def __init__(self, depth: torch.Tensor, poses: torch.Tensor, c: float):
        super().__init__()
        self.depth, self.poses, self.c = depth, poses, c

    def forward(self, pair, sequence):
        return [self.depth * self.c], self.poses * self.c


def test_without_pose_normalisation_the_loss_has_no_scale(sequences):
    """d0 None (sfmlearner): PoseNet's translations are used as they are, and the true depth
    and poses multiplied by any c give the same photometric loss (SFMLearner's arbitrary
    scale); depthnet-unsup's normalisation is kept otherwise, and video_training picks None
    for sfmlearner only."""
    indices = [0, 4, 8]
    batch = sequences.batch(indices, 0)
    depths, poses = [], []
    for j, i in enumerate(indices):
        k, first, t, _ = sequences.draw(i, 0)
        depths.append(torch.from_numpy(sequences.store.depth(k, first + t)))
        poses.append(-batch["translation"][j])  # the reprojection module's convention
    depth = torch.stack(depths).unsqueeze(1).clamp(max=1e4)
    lam, kappa = smooth_settings(None, None, False)
    losses = {}
    for c in (1.0, 3.0):
        net = _Known(depth, torch.stack(poses), c)
        step = PhotometricStep(net, None, torch.device("cpu"), (1.0,), None, lam, kappa)
        with torch.no_grad():
            losses[c] = step.losses(batch)
        tgt = batch["target_index"]
        torch.testing.assert_close(losses[c]["translations"], compensate(net.poses * c, tgt))
    torch.testing.assert_close(
        losses[1.0]["photometric"], losses[3.0]["photometric"], rtol=1e-4, atol=0
    )
    cfg = SimpleNamespace(
        model="sfmlearner-tiny", sequence_length=5, shift=3, seed=0, smooth_weight=None,
        smooth_kappa=None, occlusion=False, loss_weights=RECIPE.loss_weights,
        pose="translation", data="d", known_motion=None, pose_warmup=None,
    )  # fmt: skip
    store, cpu = sequences.store, torch.device("cpu")
    assert video_training(cfg, None, None, cpu, store, 0.3)[1].d0 is None
    cfg.model = "depthnet-unsup-tiny"
    assert video_training(cfg, None, None, cpu, store, 0.3)[1].d0 == 0.3
    cfg.model, cfg.shift = "sfmlearner-tiny", 5  # P scaling: the pair within one sequence
    with pytest.raises(FieldError, match="shift"):
        video_training(cfg, None, None, cpu, store, 0.3)


def _one_line(proc, word: str) -> None:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and word in lines[0], proc.stderr


def test_run_sfmlearner_tiny_reports_both_scales(tiny_dataset, tmp_path):
    """`run sfmlearner-tiny` trains 3 steps, validates and scores with both scales (P: the
    metrics and best.pt; GT: ``gt_``), and `eval` of its checkpoint gives the same scores."""
    out = tmp_path / "sfm"
    args = ["run", "sfmlearner-tiny", "--data", tiny_dataset, "--out", out, "--quiet"]
    bench(*args, "--batch-size", 4, "--max-steps", 3, "--log-every", 1)
    steps = list(csv.DictReader((out / "steps.csv").open()))
    assert [int(row["step"]) for row in steps] == [1, 2, 3]
    assert all(np.isfinite(float(row["loss"])) for row in steps)
    rows = list(csv.DictReader((out / "metrics.csv").open()))
    assert rows and np.isfinite(float(rows[-1]["val_gt_mae"]))
    summary = json.loads((out / "summary.json").read_text())
    m = summary["metrics"]
    assert summary["output"] == "scale-free-depth" and "PoseNet" in summary["scale"]
    assert np.isfinite(m["mae"]) and np.isfinite(m["gt_mae"]) and m["mae"] != m["gt_mae"]
    assert "sfmlearner-tiny (this run), GT |" in (out / "summary.md").read_text()
    ck = torch.load(out / "checkpoints" / "best.pt", weights_only=True)
    assert any(k.startswith("pose.") for k in ck["model"])
    bench("eval", "--ckpt", out / "checkpoints" / "best.pt", "--data", tiny_dataset,
          "--out", tmp_path / "ev")  # fmt: skip
    again = json.loads((tmp_path / "ev" / "summary.json").read_text())["metrics"]
    assert again["mae"] == pytest.approx(m["mae"]) and again["gt_mae"] == pytest.approx(m["gt_mae"])
    # infer has no PoseNet sequence to scale it by: refused in one line, nothing written
    inf = ["infer", "--ckpt", out / "checkpoints" / "best.pt", "--input", tiny_dataset]
    inf += ["--speed", 9, "--fps", 30, "--out", tmp_path / "inf"]
    _one_line(bench(*inf, check=False), "scale-free-depth")
    assert not (tmp_path / "inf").exists()
    no = ["run", "sfmlearner-tiny", "--data", tiny_dataset, "--out", tmp_path / "no", "--quiet"]
    _one_line(bench(*no, "--shift", 5, check=False), "--shift")
    assert not (tmp_path / "no").exists()
