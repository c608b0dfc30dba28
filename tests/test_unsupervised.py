"""Training DepthNet without depth (thesis chapter 5, issue 24 part 1): PoseNet, the pose
normalisation of eq. 5.2, the photometric loss of a rendered sample, and `run depthnet-unsup`."""

from __future__ import annotations

import csv
import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from test_bench import bench

from benchmark.core import registry
from benchmark.core.data import FrameStore, load_scenes
from benchmark.core.errors import FieldError
from benchmark.core.posenet import INITIAL_DEPTH, DepthPoseNet, PoseNet
from benchmark.unsupervised.reprojection import gradient_diffusion_loss
from benchmark.unsupervised.sequences import SequenceDataset
from benchmark.unsupervised.training import (
    EPSILON,
    PhotometricStep,
    compensate,
    mean_normalised,
    normalise_translations,
    reference_indices,
    smooth_settings,
    video_training,
)

WEIGHTS = registry.UNSUPERVISED_RECIPE.loss_weights


def test_posenet_gives_every_frame_a_pose_relative_to_the_last():
    torch.manual_seed(0)
    for dof in (3, 6):
        net = PoseNet(5, dof, width=0.25)
        poses = net(torch.randn(2, 15, 64, 64))
        assert poses.shape == (2, 5, dof)
        assert torch.equal(poses[:, -1], torch.zeros(2, dof))  # the last frame is the origin
        assert poses[:, :-1].abs().min() > 0
    with pytest.raises(ValueError, match="15"):
        PoseNet(5)(torch.randn(1, 6, 64, 64))
    both = DepthPoseNet(5, width=0.125).eval()
    pair = torch.randn(1, 6, 64, 64)
    depth = both(pair)  # the pair's forward is DepthNet's
    assert [d.shape[-1] for d in depth] == [16, 8, 4, 2, 1]
    assert torch.equal(depth[0], both.depth(pair)[0])
    depth, poses = both(pair, torch.randn(1, 15, 64, 64))  # training: both outputs
    assert poses.shape == (1, 5, 3) and torch.equal(depth[0], both.depth(pair)[0])


def test_poses_are_compensated_to_the_target_and_normalised_by_the_reference():
    """Hand-computed: positions relative to the last frame, target 1, reference 3."""
    last = torch.tensor([[[4.0, 0, 0], [1.0, 2, 2], [0.0, 0, 1], [4.0, 5, 2], [0.0, 0, 0]]])
    tgt, ref = torch.tensor([1]), torch.tensor([3])
    rel = compensate(last, tgt)
    assert torch.equal(rel[0, 1], torch.zeros(3))
    assert torch.equal(rel[0, 3], torch.tensor([3.0, 3, 0]))  # (4,5,2) - (1,2,2)
    d0 = 0.9
    out = normalise_translations(rel, ref, d0)
    ratio = d0 / (EPSILON + 18**0.5)  # eq. 5.2: one ratio for the whole sequence
    torch.testing.assert_close(out, rel * ratio)
    torch.testing.assert_close(out[0, 3].norm(), torch.tensor(d0), rtol=1e-5, atol=0)
    assert reference_indices(torch.tensor([0, 4, 2]), 5).tolist() == [
        *([[1, 2, 3, 4], [0, 1, 2, 3], [0, 1, 3, 4]])
    ]
    # Table 4.1's gradient-diffusion optimum, without and with the occlusion module, λ × 1e-4
    assert smooth_settings(None, None, False) == pytest.approx((0.003, 0.3))
    assert smooth_settings(None, None, True) == pytest.approx((3e-5, 0.3))
    assert smooth_settings(2.0, 1.0, True) == (2.0, 1.0)


class _Known(torch.nn.Module):
    """A DepthPoseNet stand-in answering a batch's known depth (list of scales) and poses."""

    def __init__(self, depth: torch.Tensor, poses: torch.Tensor):
        super().__init__()
        self.depth, self.poses = depth, poses

    def forward(self, pair, sequence):
        h, w = self.depth.shape[-2:]
        scales = [F.adaptive_avg_pool2d(self.depth, (h // 2**s, w // 2**s)) for s in range(2, 7)]
        return scales, self.poses


@pytest.fixture(scope="module")
def sequences(tiny_dataset) -> SequenceDataset:
    return SequenceDataset(FrameStore(load_scenes(tiny_dataset, "train"), progress=False), 5)


def _known_losses(data: SequenceDataset, indices, wrong=None, occlusion=False):
    """Loss terms of a batch with the true depth (or ``wrong(depth)``) and true poses, in the
    network's convention: the reference at the nominal displacement d0."""
    batch = data.batch(indices, 0)
    d0 = 0.3
    depths, poses = [], []
    for j, i in enumerate(indices):
        k, first, t, r = data.draw(i, 0)
        move = batch["translation"][j]  # (N, 3) metres, target to each frame (target axes)
        scale = d0 / float(move[r].norm())
        depths.append(torch.from_numpy(data.store.depth(k, first + t)) * scale)
        poses.append(-move)  # X_i = X_t - T_i: the reprojection module's convention
    depth = torch.stack(depths).unsqueeze(1).clamp(max=1e4)
    net = _Known(depth if wrong is None else wrong(depth), torch.stack(poses))
    lam, kappa = smooth_settings(None, None, occlusion)  # the recipe's
    step = PhotometricStep(net, None, torch.device("cpu"), WEIGHTS, d0, lam, kappa, occlusion)
    with torch.no_grad():
        return step.losses(batch)


def test_true_depth_and_poses_bring_the_photometric_loss_to_its_floor(sequences):
    """Rendered samples re-projected with their true depth and poses (the depth through the
    network's scales: 1/4 resolution at best, upsampled): the photometric loss is lower than
    with the depth halved, doubled, constant (each map's median) or infinite (no parallax);
    the normalised translations put the reference at d0. (Within ±10 % of the truth the loss
    is flat at 64 px: sub-pixel motion and a 16 px finest depth map.)"""
    indices = list(range(0, len(sequences), 3))[:8]
    true = _known_losses(sequences, indices)
    rows = torch.arange(len(indices))
    ref = sequences.batch(indices, 0)["reference_index"]
    norms = true["translations"][rows, ref].norm(dim=1)  # d0 up to ε (true ‖t_r‖ ≥ 0.1 m)
    torch.testing.assert_close(norms, torch.full((len(indices),), 0.3), rtol=2e-4, atol=0)
    wrongs = {
        "x0.5": lambda d: d * 0.5,
        "x2": lambda d: d * 2,
        "constant": lambda d: d.flatten(1).median(1).values.view(-1, 1, 1, 1).expand_as(d),
    }
    for name, wrong in wrongs.items():
        other = _known_losses(sequences, indices, wrong)
        assert true["photometric"] < other["photometric"], (name, true, other)
        # eq. 5.5 as trained (the recipe's λ): the truth beats the smoother wrong maps too
        # (with Table 4.1's λ = 30 as is, each map's median had the lower loss)
        assert true["loss"] < other["loss"], (name, true["loss"], other["loss"])
    still = _known_losses(sequences, indices, lambda d: torch.full_like(d, 1e4))["photometric"]
    assert true["photometric"] < 0.8 * still, (true["photometric"], still)
    # the occlusion module only drops pixels: never a much larger mean
    occluded = _known_losses(sequences, indices, occlusion=True)
    assert occluded["photometric"] <= true["photometric"] * 1.05


def test_the_smooth_term_does_not_reward_pushing_depth_far(sequences):
    """Eq. 5.5's smooth term is on ξ / mean(ξ): the true depth and the true depth × 3 (or
    / 3) have the same smooth loss (on ξ as it is, × 3 divided it by 9, so descending it pushed
    fine-tuned depth far), and a map with one bump has a larger one than the flat map (0)."""
    indices = list(range(0, len(sequences), 3))[:4]
    true = _known_losses(sequences, indices)["smooth"]
    for factor in (3.0, 1 / 3):
        scaled = _known_losses(sequences, indices, lambda d, f=factor: d * f)["smooth"]
        torch.testing.assert_close(scaled, true, rtol=1e-4, atol=0)
    xi = torch.ones(2, 1, 9, 9)
    torch.testing.assert_close(mean_normalised(xi * 7), xi)
    bump = xi.clone()
    bump[:, :, 4, 4] = 2.0
    flat = gradient_diffusion_loss(mean_normalised(xi * 5), torch.zeros(2, 3, 9, 9), 0.3)
    bumpy = gradient_diffusion_loss(mean_normalised(bump * 5), torch.zeros(2, 3, 9, 9), 0.3)
    assert flat.abs().max() < 1e-12 and (bumpy > 0.01).all(), (flat, bumpy)


def test_depthnet_starts_flat_without_a_smooth_loss(sequences):
    """DepthPoseNet's DepthNet starts at INITIAL_DEPTH at every pixel and scale, whatever the
    input: no spike of ξ = 1/θ for the smooth loss to flatten (with DepthNet's own
    initialisation a quarter of the pixels were below 0.1 m and λ·L_s 10⁴ times the
    photometric loss), so the first loss is the photometric term alone."""
    torch.manual_seed(0)
    model = registry.build_model("depthnet-unsup-tiny").train()
    batch = sequences.batch([0, 1, 2, 3], 0)
    with torch.no_grad():
        for depth in model(batch["input"]):
            torch.testing.assert_close(depth, torch.full_like(depth, INITIAL_DEPTH))
        lam, kappa = smooth_settings(None, None, False)
        r = registry.UNSUPERVISED_RECIPE
        step = PhotometricStep(model, None, torch.device("cpu"), r.loss_weights, 0.3, lam, kappa)
        out = step.losses(batch)
    assert out["smooth"] == 0 and 0 < out["photometric"] < 2, out


def test_training_steps_lower_the_loss(sequences):
    """The recipe's Adam steps on one batch of the tiny variant lower eq. 5.5's loss."""
    torch.manual_seed(0)
    model = registry.build_model("depthnet-unsup-tiny").train()
    r = registry.UNSUPERVISED_RECIPE
    opt = torch.optim.Adam(model.parameters(), lr=1e-3, betas=(r.momentum, r.beta2))
    lam, kappa = smooth_settings(None, None, False)
    step = PhotometricStep(model, opt, torch.device("cpu"), r.loss_weights, 0.3, lam, kappa)
    batch = sequences.batch([0, 1, 2, 3], 0)
    first = step.losses(batch)["loss"].item()
    for _ in range(8):
        step(batch)
    last = step.losses(batch)["loss"].item()
    assert np.isfinite(first) and last < 0.8 * first, (first, last)


def _video_cfg(model: str, known_motion: bool | None) -> SimpleNamespace:
    """The TrainConfig fields video_training reads, at the recipe's values."""
    return SimpleNamespace(
        model=model, sequence_length=5, shift=3, seed=0, smooth_weight=None, smooth_kappa=None,
        occlusion=False, loss_weights=WEIGHTS, pose="translation", data="d",
        known_motion=known_motion, pose_warmup=None,
    )  # fmt: skip


def test_known_motion_warps_with_the_datasets_translations(sequences):
    """run --known-motion: the step warps with the batch's true translations normalised to d0
    at the reference, whatever PoseNet outputs; without it, with PoseNet's. Refused for a
    method without the displacement's scale (sfmlearner)."""
    cpu, store = torch.device("cpu"), sequences.store
    torch.manual_seed(0)
    net = registry.build_model("depthnet-unsup-tiny")
    batch = sequences.batch([0, 4, 8], 0)
    known = normalise_translations(-batch["translation"], batch["reference_index"], 0.3)
    used = {}
    for flag in (True, None):
        step = video_training(_video_cfg("depthnet-unsup-tiny", flag), net, None, cpu, store, 0.3)[
            1
        ]
        with torch.no_grad():
            used[flag] = step.losses(batch)["translations"]
    torch.testing.assert_close(used[True], known)
    assert not torch.allclose(used[None], known, atol=1e-3)
    with pytest.raises(FieldError, match="stabilised data"):
        video_training(_video_cfg("sfmlearner-tiny", True), net, None, cpu, store, 0.3)


def _one_line(proc, word: str) -> None:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and word in lines[0], proc.stderr


def test_run_eval_resume_and_bad_options(tiny_dataset, tmp_path):
    """`run depthnet-unsup-tiny` writes a run folder whose checkpoint `eval` loads, resumes to
    more steps, and refuses bad options in one line without a run folder."""
    out = tmp_path / "unsup"
    args = ["run", "depthnet-unsup-tiny", "--data", tiny_dataset, "--out", out, "--quiet"]
    bench(*args, "--batch-size", 4, "--max-steps", 3, "--log-every", 1)
    config = json.loads((out / "config.json").read_text())
    assert config["model"] == "depthnet-unsup-tiny" and config["sequence_length"] == 5
    steps = list(csv.DictReader((out / "steps.csv").open()))
    assert [int(row["step"]) for row in steps] == [1, 2, 3]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["output"] == "unsupervised-depth" and np.isfinite(summary["metrics"]["mae"])
    ck = torch.load(out / "checkpoints" / "best.pt", weights_only=True)
    assert any(k.startswith("pose.") for k in ck["model"])  # PoseNet saved beside DepthNet
    bench("eval", "--ckpt", out / "checkpoints" / "best.pt", "--data", tiny_dataset,
          "--out", tmp_path / "ev")  # fmt: skip
    again = json.loads((tmp_path / "ev" / "summary.json").read_text())
    assert again["metrics"]["mae"] == pytest.approx(summary["metrics"]["mae"])
    bench(*args, "--resume", "--max-steps", 5, "--log-every", 1)
    steps = list(csv.DictReader((out / "steps.csv").open()))
    assert [int(row["step"]) for row in steps] == [1, 2, 3, 4, 5]
    _one_line(bench(*args, "--resume", "--occlusion", "--max-steps", 6, check=False), "--occlusion")
    for flags, word in ((["--batch-size", 1000], "--batch-size"), (["--lr", 0], "--lr")):
        no = ["run", "depthnet-unsup-tiny", "--data", tiny_dataset, "--out", tmp_path / "no"]
        _one_line(bench(*no, *flags, "--quiet", check=False), word)
        assert not (tmp_path / "no").exists()


def test_pose_warmup_trains_posenet_alone_then_both_and_resumes_into_the_right_phase(
    tiny_dataset, tmp_path
):
    """run --pose-warmup 2 from a depthnet-unsup checkpoint: after 2 steps the DepthNet
    (weights and BatchNorm statistics) is exactly the checkpoint's while PoseNet has moved;
    resumed to 3 steps (the warm-up's count read from the resumed step), the DepthNet moves
    too. Refused with --known-motion (no PoseNet to warm up), in one line."""
    base = ["run", "depthnet-unsup-tiny", "--data", tiny_dataset, "--quiet", "--batch-size", 4]
    bench(*base, "--out", tmp_path / "start", "--max-steps", 1)
    start = tmp_path / "start" / "checkpoints" / "last.pt"
    warm = [*base, "--pretrained", start, "--pose-warmup", 2, "--out", tmp_path / "warm"]
    bench(*warm, "--max-steps", 2, "--ckpt-every", 1)

    def weights(path, part):
        model = torch.load(path, weights_only=True)["model"]
        return {k: v for k, v in model.items() if k.startswith(part)}

    last = tmp_path / "warm" / "checkpoints" / "last.pt"
    before, after = weights(start, "depth."), weights(last, "depth.")
    assert any("running_mean" in k for k in before)  # BatchNorm statistics are compared too
    for k, v in before.items():
        torch.testing.assert_close(after[k], v, rtol=0, atol=0, msg=k)
    pose0, pose2 = weights(start, "pose."), weights(last, "pose.")
    assert any(not torch.equal(pose0[k], pose2[k]) for k in pose0)
    bench(*warm, "--resume", "--max-steps", 3)
    moved = weights(last, "depth.")
    assert any(not torch.equal(moved[k], before[k]) for k in before)
    known = [*base, "--known-motion", "--pose-warmup", 2, "--out", tmp_path / "km"]
    _one_line(bench(*known, "--max-steps", 1, check=False), "--pose-warmup")
    assert not (tmp_path / "km").exists()


def test_pose_lr_sets_posenets_learning_rate_alone(tiny_dataset, tmp_path):
    """run --pose-lr: from one checkpoint, one Adam step (about lr × sign(gradient) per weight)
    moves the DepthNet's weights exactly as without it and PoseNet's about pose-lr / lr times
    farther; a resume may not change it; a network without a PoseNet refuses it, in one line
    naming the flag, before writing anything."""
    base = ["run", "depthnet-unsup-tiny", "--data", tiny_dataset, "--quiet", "--batch-size", 4]
    bench(*base, "--out", tmp_path / "start", "--max-steps", 1)
    start = tmp_path / "start" / "checkpoints" / "last.pt"
    moved = {}
    for name, flags in (("same", []), ("fast", ["--pose-lr", "0.02"])):
        out = tmp_path / name
        bench(*base, *flags, "--pretrained", start, "--out", out, "--max-steps", 1)
        after = torch.load(out / "checkpoints" / "last.pt", weights_only=True)["model"]
        before = torch.load(start, weights_only=True)["model"]
        moved[name] = {k: after[k] - before[k] for k in before if after[k].is_floating_point()}
    lr = registry.UNSUPERVISED_RECIPE.lr
    for k, same in moved["same"].items():
        fast = moved["fast"][k]
        if k.startswith("depth."):
            torch.testing.assert_close(fast, same, rtol=0, atol=0, msg=k)
        elif "running" not in k:
            assert same.abs().max() <= 1.01 * lr, k
    pose = [k for k in moved["fast"] if k.startswith("pose.") and "running" not in k]
    assert max(moved["fast"][k].abs().max() for k in pose) > 0.5 * 0.02
    resumed = [*base, "--pose-lr", "0.01", "--out", tmp_path / "fast", "--resume"]
    _one_line(bench(*resumed, "--max-steps", 2, check=False), "--pose-lr")
    no = ["run", "depthnet-tiny", "--data", tiny_dataset, "--quiet", "--out", tmp_path / "no"]
    _one_line(bench(*no, "--pose-lr", "0.01", "--max-steps", 1, check=False), "--pose-lr")
    assert not (tmp_path / "no").exists()


def test_a_finished_run_without_milestones_resumes_to_more_epochs(tiny_dataset, tmp_path):
    """depthnet-unsup's recipe has no milestones, so its learning rate does not depend on the
    epoch count: a finished 1-epoch run resumed with --epochs 2 ends with the weights and
    steps.csv of a run started with 2. DepthNet's recipe (milestones at fractions of the
    epochs) refuses it in one line naming --epochs."""
    base = ["run", "depthnet-unsup-tiny", "--data", tiny_dataset, "--quiet", "--batch-size", 4]
    base += ["--epoch-size", 2, "--log-every", 1]
    bench(*base, "--epochs", 2, "--out", tmp_path / "whole")
    bench(*base, "--epochs", 1, "--out", tmp_path / "parts")
    bench(*base, "--epochs", 2, "--out", tmp_path / "parts", "--resume")
    for name in ("whole", "parts"):
        rows = list(csv.DictReader((tmp_path / name / "steps.csv").open()))
        assert [r["step"] for r in rows] == ["1", "2", "3", "4"]
    whole, parts = ((tmp_path / n / "steps.csv").read_text() for n in ("whole", "parts"))
    assert whole == parts
    a, b = (torch.load(tmp_path / n / "checkpoints" / "last.pt", weights_only=True)["model"]
            for n in ("whole", "parts"))  # fmt: skip
    for k, v in a.items():
        torch.testing.assert_close(b[k], v, rtol=0, atol=0, msg=k)
    sup = ["run", "depthnet-tiny", "--data", tiny_dataset, "--quiet", "--max-steps", 1]
    sup += ["--batch-size", 4]
    bench(*sup, "--epochs", 1, "--out", tmp_path / "sup")
    _one_line(bench(*sup, "--epochs", 2, "--out", tmp_path / "sup", "--resume", check=False),
              "--epochs")  # fmt: skip


def test_steps_csv_logs_the_terms_and_posenets_direction(tiny_dataset, tmp_path):
    """depthnet-unsup's steps.csv: photometric + smooth = loss on every row, and pose_cosine 1
    when the warps use the dataset's motion (--known-motion), within [−1, 1] with PoseNet's."""
    base = ["run", "depthnet-unsup-tiny", "--data", tiny_dataset, "--quiet", "--batch-size", 4]
    for flags in (["--known-motion"], []):
        out = tmp_path / ("km" if flags else "posenet")
        bench(*base, *flags, "--out", out, "--max-steps", 2, "--log-every", 1)
        rows = list(csv.DictReader((out / "steps.csv").open()))
        assert len(rows) == 2
        for row in rows:
            terms = float(row["photometric"]) + float(row["smooth"])
            assert terms == pytest.approx(float(row["loss"]), rel=1e-5)
            cosine = float(row["pose_cosine"])
            assert cosine == pytest.approx(1.0, abs=1e-5) if flags else -1 <= cosine <= 1


def test_pretrained_depthnet_initialises_the_depth_half():
    """--pretrained with a supervised DepthNet's checkpoint (thesis §5.4.4's D + O -> O) loads
    it into depthnet-unsup's DepthNet and leaves its PoseNet as initialised; a depthnet-unsup
    checkpoint initialises the whole network."""
    from benchmark.core.checkpoint import load_weights
    from benchmark.engine.train import pretrained_part

    torch.manual_seed(0)
    supervised = registry.build_model("depthnet-tiny")
    unsup = registry.build_model("depthnet-unsup-tiny")
    pose = {k: v.clone() for k, v in unsup.pose.state_dict().items()}
    ck = {"model": supervised.state_dict(), "model_name": "depthnet-tiny"}
    part = pretrained_part(unsup, ck)
    assert part is unsup.depth
    load_weights(part, ck, "pretrained", "sup.pt", "depthnet-unsup-tiny")
    for k, v in supervised.state_dict().items():
        torch.testing.assert_close(unsup.depth.state_dict()[k], v, rtol=0, atol=0)
    for k, v in unsup.pose.state_dict().items():
        torch.testing.assert_close(v, pose[k], rtol=0, atol=0)
    whole = {"model": unsup.state_dict(), "model_name": "depthnet-unsup-tiny"}
    assert pretrained_part(unsup, whole) is unsup
