"""Rotating data in unsupervised training (thesis §5.2.1-5.2.2, issue 24 part 1): PoseNet's
Euler convention against the inverse warp, the rotation warp of eq. 5.1, the known orientations
of a rendered rotating dataset, and `run depthnet-unsup* --pose`."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from test_bench import bench

from benchmark.core import registry
from benchmark.core.data import FrameStore, load_scenes
from benchmark.core.errors import FieldError
from benchmark.core.posenet import euler_matrix
from benchmark.unsupervised.reprojection import inverse_warp, rotate_frame
from benchmark.unsupervised.rotation import Stabiliser, check_pose, target_rotations
from benchmark.unsupervised.sequences import SequenceDataset
from benchmark.unsupervised.training import (
    PhotometricStep,
    compensate,
    pose_cosine,
    smooth_settings,
    true_translations,
)


def _rx(a):  # hand-built right-handed rotations about the camera axes
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _camera(width: int, height: int, focal: float, cx: float, cy: float):
    K = np.array([[focal, 0, cx], [0, focal, cy], [0, 0, 1.0]])
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    ramp = torch.tensor(np.stack([xs, ys, np.ones_like(xs)]), dtype=torch.float64)[None]
    return K, ramp  # the ramp's bilinear samples are the sampled pixel coordinates themselves


def test_euler_angles_follow_the_documented_convention():
    """R = R_x(α)·R_y(β)·R_z(γ), right-handed: a quarter turn about z takes x to y."""
    a = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    expected = _rx(0.3) @ _ry(-0.2) @ _rz(0.5)
    np.testing.assert_allclose(euler_matrix(a).numpy(), expected, atol=1e-12)
    quarter = euler_matrix(torch.tensor([0, 0, math.pi / 2], dtype=torch.float64))
    np.testing.assert_allclose(quarter.numpy() @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    assert euler_matrix(torch.zeros(2, 5, 3)).shape == (2, 5, 3, 3)


def test_six_dof_poses_warp_a_point_where_numpy_projects_it():
    """PoseNet-style 6-DoF poses relative to the last frame (X_i = R_i·X_last + τ_i), moved to
    target 0 (target_rotations, compensate) and given to inverse_warp, send every target pixel
    at depth θ where numpy's projection of the same 3-D point in frame 1 lands."""
    K, ramp = _camera(32, 24, 16.0, 15.5, 11.5)
    angles = [[0.02, -0.05, 0.03], [-0.01, 0.04, 0.02], [0.0, 0.0, 0.0]]
    taus = [[0.3, -0.1, 0.2], [-0.2, 0.1, 0.4], [0.0, 0.0, 0.0]]
    poses = torch.tensor([[t + a for t, a in zip(taus, angles, strict=True)]], dtype=torch.float64)
    tgt = torch.tensor([0])
    rotations = target_rotations("6dof", poses, None, tgt)
    moves = compensate(poses[..., :3], tgt, rotations)
    theta = 6.0
    out, valid = inverse_warp(
        ramp, torch.full((1, 1, 24, 32), theta, dtype=torch.float64), rotations[:, 1],
        moves[:, 1], torch.tensor(K),
    )  # fmt: skip
    r = [_rx(a) @ _ry(b) @ _rz(c) for a, b, c in angles]
    for x, y in ((15, 11), (3, 4), (28, 20)):
        point_t = theta * np.linalg.inv(K) @ [x, y, 1.0]
        point_last = r[0].T @ (point_t - taus[0])  # X_0 = R_0·X_last + τ_0
        point_1 = r[1] @ point_last + taus[1]
        seen = K @ point_1 / point_1[2]
        assert valid[0, 0, y, x]
        np.testing.assert_allclose(out[0, :2, y, x].numpy(), seen[:2], atol=1e-9)


def test_rotation_warp_of_eq_5_1_is_the_hand_computed_homography():
    """A pure 10° yaw R_y (target → reference): the stabilised frame's centre pixel samples the
    reference at (cx + f·tan 10°, cy), its top-left corner at numpy's K·R·K⁻¹·(0, 0, 1); a pixel
    whose ray leaves the reference is masked. Stabiliser swaps the pair's reference for it."""
    K, ramp = _camera(33, 25, 16.0, 16.0, 12.0)
    R = _ry(math.radians(10))
    out, valid = rotate_frame(ramp, torch.tensor(R)[None], torch.tensor(K))
    centre = out[0, :2, 12, 16].numpy()
    np.testing.assert_allclose(centre, [16 + 16 * math.tan(math.radians(10)), 12], atol=1e-9)
    corner = K @ R @ np.linalg.inv(K) @ [0.0, 0.0, 1.0]
    np.testing.assert_allclose(out[0, :2, 0, 0].numpy(), corner[:2] / corner[2], atol=1e-9)
    assert valid[0, 0, 12, 16] and valid[0, 0, 0, 0] and not valid[0, 0, 12, 32]
    # the Stabiliser of a batch: known R_{t→r} of reference 1, target 0; the target untouched
    known = torch.eye(3, dtype=torch.float64).repeat(1, 2, 1, 1)
    known[0, 1] = torch.tensor(R)
    pair = torch.cat([ramp, ramp + 1], 1)
    stab = Stabiliser("orientation", known, torch.tensor([0]), torch.tensor([1]), torch.tensor(K))
    stable = stab(pair, torch.zeros(1, 2, 3, dtype=torch.float64))
    assert torch.equal(stable[:, 3:], pair[:, 3:])
    torch.testing.assert_close(stable[:, :3], torch.where(valid, out, torch.zeros_like(out)))


def test_pose_modes_fit_the_network_and_the_data():
    """One-line FieldErrors on pose: a mode against the PoseNet's outputs or the data's motion."""
    still, turning = (
        SimpleNamespace(stabilised=True, index=0),
        SimpleNamespace(stabilised=False, index=4),
    )
    check_pose("translation", "translation", [still], "d")
    check_pose("orientation", "translation", [still, turning], "d")
    check_pose("6dof", "6dof", [turning], "d")
    for pose, model, scenes, words in (
        ("translation", "translation", [still, turning], "camera rotations (scene 4)"),
        ("orientation", "translation", [still], "d is stabilised"),
        ("6dof", "6dof", [still], "d is stabilised"),
        ("6dof", "translation", [turning], "depthnet-unsup-6dof"),
        ("orientation", "6dof", [turning], "needs depthnet-unsup(-tiny)"),
    ):
        with pytest.raises(FieldError, match="^pose: ") as e:
            check_pose(pose, model, scenes, "d")
        assert words in str(e.value) and "\n" not in str(e.value)


class _Known(torch.nn.Module):
    """A DepthPoseNet stand-in answering a batch's known depth (list of scales) and poses, and
    calling ``stabilise`` as DepthPoseNet does."""

    def __init__(self, depth, poses):
        super().__init__()
        self.depth, self.poses, self.seen = depth, poses, None

    def forward(self, pair, sequence, stabilise=None):
        self.seen = pair if stabilise is None else stabilise(pair, self.poses)
        h, w = self.depth.shape[-2:]
        scales = [F.adaptive_avg_pool2d(self.depth, (h // 2**s, w // 2**s)) for s in range(2, 7)]
        return scales, self.poses


def test_known_orientations_stabilise_and_warp_a_rendered_sequence(rotating_dataset):
    """On a rendered rotating scene: the batch's rotations are the dataset's relative poses
    (identity at the target, 5° a frame elsewhere) and its translations the camera's 0.1 m a
    frame; with the true depth and the true translations relative to the last frame, the
    orientation mode's photometric loss is below that of the same poses without rotation, and
    DepthNet reads the stabilised reference."""
    scenes = load_scenes(rotating_dataset, "train", rotations=True)
    with pytest.raises(ValueError, match="camera rotations"):
        load_scenes(rotating_dataset, "train")  # the supervised baselines still refuse it
    data = SequenceDataset(FrameStore(scenes, progress=False), 5)
    indices = list(range(len(data)))
    batch = data.batch(indices, 0)
    taus, depths = [], []
    for j, i in enumerate(indices):
        k, first, t, r = data.draw(i, 0)
        scene = scenes[k]
        for f in range(5):
            rel = scene.relative_pose(first + t, first + f)
            np.testing.assert_allclose(batch["rotation"][j, f], rel[:3, :3], atol=1e-6)
            angle = math.degrees(math.acos(np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1, 1)))
            assert angle == pytest.approx(5 * abs(f - t), abs=1.0)  # 0.1° noise a frame
            move = float(batch["translation"][j, f].norm())
            assert move == pytest.approx(scene.displacement * abs(f - t), rel=1e-5, abs=1e-6)
        taus.append([scene.relative_pose(first + 4, first + f)[:3, 3] for f in range(5)])
        d0_ratio = 0.3 / float(batch["translation"][j, r].norm())
        depths.append(torch.from_numpy(data.store.depth(k, first + t)) * d0_ratio)
    depth = torch.stack(depths).unsqueeze(1).clamp(max=1e4)
    poses = torch.tensor(np.array(taus), dtype=torch.float32)
    lam, kappa = smooth_settings(None, None, False)
    loss = {}
    for pose in ("orientation", "translation"):
        net = _Known(depth, poses)
        step = PhotometricStep(
            net, None, torch.device("cpu"), registry.UNSUPERVISED_RECIPE.loss_weights, 0.3,
            lam, kappa, pose=pose,
        )  # fmt: skip
        with torch.no_grad():
            loss[pose] = step.losses(batch)
        if pose == "orientation":
            rows = torch.arange(len(indices))
            norms = loss[pose]["translations"][rows, batch["reference_index"]].norm(dim=1)
            torch.testing.assert_close(norms, torch.full_like(norms, 0.3), rtol=1e-4, atol=0)
            assert not torch.equal(net.seen[:, :3], batch["input"][:, :3])  # stabilised
            assert torch.equal(net.seen[:, 3:], batch["input"][:, 3:])
            # steps.csv's pose_cosine: 1 for the true motion, −1 for its opposite
            used = loss[pose]["translations"]
            assert pose_cosine(batch, used) == pytest.approx(1.0, abs=1e-4)
            assert pose_cosine(batch, -used) == pytest.approx(-1.0, abs=1e-4)
    assert loss["orientation"]["photometric"] < 0.8 * loss["translation"]["photometric"], loss
    # the true τ_i of X_i = R·X_t + τ_i, straight from the dataset's relative poses
    for j, i in enumerate(indices):
        k, first, t, _ = data.draw(i, 0)
        for f in range(5):
            tau = scenes[k].relative_pose(first + t, first + f)[:3, 3]
            np.testing.assert_allclose(true_translations(batch)[j, f], tau, atol=1e-5)


def _one_line(proc, word: str) -> None:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and word in lines[0], proc.stderr


def test_run_with_known_orientations_and_with_6dof(rotating_dataset, tmp_path):
    """Two-step runs on rotating data: `--pose orientation` (DepthNet and SFMLearner) and
    `depthnet-unsup-6dof-tiny` (whose checkpoint `eval` loads); the default translation mode,
    a 6dof mode on a 3-output PoseNet and an unknown mode are refused in one line naming
    --pose, without a run folder."""
    base = ["--data", rotating_dataset, "--batch-size", 2, "--max-steps", 2, "--quiet"]
    bench("run", "depthnet-unsup-tiny", "--pose", "orientation", "--out", tmp_path / "o", *base)
    assert json.loads((tmp_path / "o" / "config.json").read_text())["pose"] == "orientation"
    # SFMLearner reads the target alone: the known orientations only rotate its warps
    bench("run", "sfmlearner-tiny", "--pose", "orientation", "--out", tmp_path / "s", *base)
    sfm = json.loads((tmp_path / "s" / "summary.json").read_text())
    assert np.isfinite(sfm["metrics"]["mae"])
    bench("run", "depthnet-unsup-6dof-tiny", "--out", tmp_path / "6", *base)
    summary = json.loads((tmp_path / "6" / "summary.json").read_text())
    assert np.isfinite(summary["metrics"]["mae"])
    best = tmp_path / "6" / "checkpoints" / "best.pt"
    ck = torch.load(best, weights_only=True)
    assert ck["model"]["pose.predict.bias"].shape == (6 * 4,) and ck["config"]["pose"] == "6dof"
    bench("eval", "--ckpt", best, "--data", rotating_dataset, "--out", tmp_path / "ev")
    for model, flags in (
        ("depthnet-unsup-tiny", []),
        ("depthnet-unsup-tiny", ["--pose", "6dof"]),
        ("depthnet-unsup-tiny", ["--pose", "roll"]),
    ):
        no = tmp_path / "no"
        _one_line(bench("run", model, *flags, "--out", no, *base, check=False), "--pose")
        assert not no.exists()
