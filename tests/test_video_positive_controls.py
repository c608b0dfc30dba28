"""Positive controls of learning from video (thesis chapter 5; ``pytest -m positive_control``).

A silent defect in the warp, the pose conventions or the loss would look like a short budget
(no unsupervised network learnt depth at this project's CPU budgets); these tests tell them
apart. Both drive the training step itself (``PhotometricStep``: eq. 5.3 through
``inverse_warp``, ``photometric_map`` and ``masked_mean``) with one of its two networks
replaced by the truth, on real renders:

- depth: with the known camera motion (``known_translation``, ``finetune --known-motion``'s
  path), the photometric loss alone (no smooth term) fits a free depth map of one close-range
  128 px scene to below half the MAE of the ground truth's median plane;
- pose: PoseNet alone, with the true depth in the training's convention (× d0 / ‖t_pair‖),
  learns the translation directions of 12 sequences of 6 scenes (mean cosine > 0.9).

Each also runs with one defect injected (the translation's sign flipped in the warp, the focal
length × 1.5, the principal point a quarter of the frame off, the target and the reference
swapped) and must then fail: the ``defect`` cases. A rotation transposed is no defect here: the
scenes are stabilised (R = I). Measured (1 thread, idle machine): depth MAE 1.34 m against the
constant's 3.49 (ratio 0.38, 10 s); with the defects 46.4 m, 3.17, 1.79 (0.51: not asserted),
2.62. Pose cosine 0.985 (14 s); with the defects -0.91, 0.50, 0.81, -0.75. A principal point
an eighth of the frame off passes both (0.44, 0.93).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from benchmark.core.data import NORM_MEAN, NORM_STD, FrameStore
from benchmark.core.metrics import image_metrics
from benchmark.core.posenet import PoseNet
from benchmark.unsupervised import training
from benchmark.unsupervised.sequences import SequenceDataset
from benchmark.unsupervised.training import PhotometricStep
from stillbox_gen.conventions import NOMINAL_SHIFT
from stillbox_gen.dataset import Dataset

pytestmark = [pytest.mark.positive_control, pytest.mark.usefixtures("one_torch_thread")]

#: Frames of the depth control: the target 8 and references 2, 4, 6, 8 frames away on both
#: sides (0.2-0.8 m). At 128 px gap 1 has little signal (docs/results/finetune/README.md).
DEPTH_FRAMES = tuple(range(0, 17, 2))
#: The free depth map is at 1/4 of the frame, upsampled bilinearly by the step (DepthNet's
#: finest scale, §4.7.1). Per pixel at full resolution, a few per cent of the pixels (around
#: the focus of expansion, occlusions, flat texture) run off to hundreds of metres under Adam.
DEPTH_FACTOR = 4
DEPTH_STEPS, DEPTH_LR = 150, 0.05
#: The pose control: PoseNet at 1/4 width, Adam, on the windows starting at these frames.
POSE_WINDOWS, POSE_WIDTH, POSE_STEPS, POSE_LR = (0, 5), 0.25, 100, 1e-3
KAPPA = 0.3  # unused: no smooth term (λ = 0)

DEFECTS = ("translation sign", "focal x1.5", "principal point", "target and reference swapped")


def inject(defect: str | None, batch: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    """Break one thing of the training step's inputs or of its warp (None: nothing)."""
    if defect == "translation sign":  # the warp moves the camera the other way
        warp = training.inverse_warp
        monkeypatch.setattr(
            training, "inverse_warp", lambda ref, depth, rot, t, K: warp(ref, depth, rot, -t, K)
        )
    elif defect == "focal x1.5":
        batch["K"] = batch["K"].clone()
        batch["K"][:, 0, 0] *= 1.5
        batch["K"][:, 1, 1] *= 1.5
    elif defect == "principal point":  # a quarter of the frame off, right and down
        h, w = batch["frames"].shape[-2:]
        batch["K"] = batch["K"].clone()
        batch["K"][:, 0, 2] += w / 4
        batch["K"][:, 1, 2] += h / 4
    elif defect == "target and reference swapped":
        batch["target_index"], batch["reference_index"] = (
            batch["reference_index"],
            batch["target_index"],
        )
    else:
        assert defect is None, defect


# ---------------------------------------------------------------- depth from the known motion


class FreeDepth(nn.Module):
    """Stands in for the DepthPoseNet: its depth is a free map (log-depth, one value per
    ``factor``² pixels, from ``start`` metres everywhere); its poses are zeros, unused with the
    known motion."""

    def __init__(self, height: int, width: int, factor: int, start: float, frames: int):
        super().__init__()
        size = (1, 1, height // factor, width // factor)
        self.log_depth = nn.Parameter(torch.full(size, math.log(start)))
        self.frames = frames

    def forward(self, pair: torch.Tensor, sequence: torch.Tensor, stabilise=None):
        return [self.log_depth.exp()], pair.new_zeros(len(pair), self.frames, 3)


def depth_batch(data: Path) -> tuple[dict, torch.Tensor]:
    """The depth control's sample, in SequenceDataset.batch's layout (one sequence of
    DEPTH_FRAMES, its middle frame the target), and the target's true depth (1, 1, H, W)."""
    (scene,) = Dataset(data).scenes()
    assert scene.stabilised
    target = len(DEPTH_FRAMES) // 2
    t = DEPTH_FRAMES[target]
    rgb = np.stack([scene.load_rgb(f).transpose(2, 0, 1) for f in DEPTH_FRAMES])
    frames = torch.from_numpy(rgb).float()[None] / 255.0
    sequence = (frames - NORM_MEAN) / NORM_STD
    n, h, w = len(DEPTH_FRAMES), *frames.shape[-2:]
    moves = np.stack([scene.translation(t, f) for f in DEPTH_FRAMES])  # camera t -> f, metres
    batch = {
        "frames": frames,
        "sequence": sequence.reshape(1, 3 * n, h, w),
        "input": torch.cat([sequence[:, target + 1], sequence[:, target]], 1),
        "target_index": torch.tensor([target]),
        "reference_index": torch.tensor([target + 1]),
        "K": torch.tensor(np.asarray(scene.K), dtype=torch.float32)[None],
        "translation": torch.from_numpy(moves.astype(np.float32))[None],
    }
    return batch, torch.from_numpy(scene.load_depth(t).astype(np.float32))[None, None]


def fit_depth(data: Path, defect: str | None, monkeypatch) -> tuple[float, float]:
    """(MAE of the fitted map, MAE of the truth's median plane), metres, as the benchmark
    scores them (image_metrics: predictions clamped to [0.1, 100] m)."""
    batch, truth = depth_batch(data)
    inject(defect, batch, monkeypatch)
    h, w = truth.shape[-2:]
    net = FreeDepth(h, w, DEPTH_FACTOR, float(truth.median()), len(DEPTH_FRAMES))
    opt = torch.optim.Adam(net.parameters(), lr=DEPTH_LR)
    step = PhotometricStep(net, opt, torch.device("cpu"), (1.0,), None, 0.0, KAPPA,
                           known_translation=True)  # fmt: skip
    for _ in range(DEPTH_STEPS):
        step.update(batch)
    with torch.no_grad():  # the step's own upsampling of the map to the frame
        depth = F.interpolate(net.log_depth.exp(), size=(h, w), mode="bilinear",
                              align_corners=False)  # fmt: skip
    constant = torch.full_like(truth, float(truth.median()))
    return tuple(float(image_metrics(d[:, 0], truth[:, 0])["mae"][0]) for d in (depth, constant))


def test_the_photometric_loss_learns_depth_from_the_known_motion(close_range_scene, monkeypatch):
    mae, constant = fit_depth(close_range_scene, None, monkeypatch)
    assert mae < constant / 2, (mae, constant)


@pytest.mark.parametrize("defect", [d for d in DEFECTS if d != "principal point"])
def test_the_depth_control_fails_with_a_defect(close_range_scene, monkeypatch, defect):
    """The principal point a quarter of the frame off only raises the MAE to about half the
    constant's (the free map absorbs most of it): the pose control catches it instead."""
    mae, constant = fit_depth(close_range_scene, defect, monkeypatch)
    assert mae > constant / 2, (mae, constant)


# ---------------------------------------------------------------- pose from the true depth


class TrueDepthPoseNet(nn.Module):
    """Stands in for the DepthPoseNet: a fresh PoseNet, and the batch's true depth in the
    training's convention (what a perfect DepthNet answers: depth × d0 / ‖t_pair‖)."""

    def __init__(self, depth: torch.Tensor, frames: int):
        super().__init__()
        self.pose = PoseNet(frames, 3, POSE_WIDTH)
        self.register_buffer("depth", depth)

    def forward(self, pair: torch.Tensor, sequence: torch.Tensor, stabilise=None):
        return [self.depth], self.pose(sequence)


def fit_pose(data: Path, defect: str | None, monkeypatch) -> float:
    """Mean cosine between the reference translation the step uses after POSE_STEPS and the
    true one (scene.relative_pose: X_r = X_t + τ on stabilised scenes)."""
    scenes = Dataset(data).scenes()
    sequences = SequenceDataset(FrameStore(scenes, progress=False), 5, seed=0)
    picked = [i for i, (_, first) in enumerate(sequences.items) if first in POSE_WINDOWS]
    batch = sequences.batch(picked, 0)
    d0 = NOMINAL_SHIFT * scenes[0].displacement  # the supervised DepthNet's nominal metres
    truth, depth = [], []
    for j, i in enumerate(picked):
        k, first = sequences.items[i]
        t, r = first + int(batch["target_index"][j]), first + int(batch["reference_index"][j])
        move = scenes[k].relative_pose(t, r)[:3, 3]
        truth.append(torch.tensor(move, dtype=torch.float32))
        scaled = scenes[k].load_depth(t) * d0 / np.linalg.norm(move)
        depth.append(torch.from_numpy(scaled.astype(np.float32))[None])
    assert len(picked) >= 8 and len({s.index for s in scenes}) >= 4
    inject(defect, batch, monkeypatch)
    torch.manual_seed(0)
    net = TrueDepthPoseNet(torch.stack(depth), 5)
    opt = torch.optim.Adam(net.pose.parameters(), lr=POSE_LR)
    step = PhotometricStep(net, opt, torch.device("cpu"), (1.0,), d0, 0.0, KAPPA)
    for _ in range(POSE_STEPS):
        step.update(batch)
    with torch.no_grad():
        translations = step.losses(batch)["translations"]
    rows = torch.arange(len(picked))
    used = translations[rows, batch["reference_index"]]
    return float(F.cosine_similarity(used, torch.stack(truth), dim=1).mean())


def test_posenet_learns_the_translation_directions(tiny_dataset, monkeypatch):
    cosine = fit_pose(tiny_dataset, None, monkeypatch)
    assert cosine > 0.9, cosine


@pytest.mark.parametrize("defect", DEFECTS)
def test_the_pose_control_fails_with_a_defect(tiny_dataset, monkeypatch, defect):
    cosine = fit_pose(tiny_dataset, defect, monkeypatch)
    assert cosine < 0.9, cosine
