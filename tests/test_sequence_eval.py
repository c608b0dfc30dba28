"""`eval-sequences` (thesis §5.4.3-5.4.4, Tables 5.2-5.3; issue 24 part 3): the pair whose mean
output is closest to 50 m, the upside-down flip, the P and GT scales, a stand-in network that
knows the truth, and the command end to end on tiny checkpoints."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from test_bench import bench

from benchmark.core import registry
from benchmark.core.metrics import median_scale
from benchmark.core.posenet import POSE_SCALE, euler_matrix
from benchmark.unsupervised.reprojection import rotate_frame
from benchmark.unsupervised.sequence_eval import (
    PAIR_TARGET_DEPTH,
    SCALE_GT,
    SCALE_P,
    SCALE_P_FIXED,
    UPRIGHT,
    UPSIDE_DOWN,
    EvalModel,
    Window,
    choose_pair,
    constant_plane,
    evaluate,
    predict,
    scene_windows,
    upside_down,
)
from benchmark.unsupervised.sequence_report import POSE_HEADER, THESIS_ROWS, markdown, thesis_row
from benchmark.unsupervised.training import EPSILON
from stillbox_gen.dataset import Dataset

CPU = torch.device("cpu")
H, W = 8, 12


def _window(rotation=None, cy: float = (H - 1) / 2) -> Window:
    """A synthetic window: random frames, depth 1..96 m, the camera 0.1 m a frame forward."""
    rng = np.random.default_rng(0)
    K = np.array([[6.0, 0, (W - 1) / 2], [0, 6.0, cy], [0, 0, 1]])
    position = np.array([[0.0, 0.0, -0.1 * (4 - i)] for i in range(5)])  # in t's axes
    rot = np.tile(np.eye(3), (5, 1, 1)) if rotation is None else rotation
    return Window(
        rng.integers(0, 256, (5, H, W, 3), dtype=np.uint8),
        np.arange(1.0, H * W + 1, dtype=np.float32).reshape(H, W),
        K, rot, position, rotation is None, 0, 4,
    )  # fmt: skip


class _PerPair(torch.nn.Module):
    """A DepthNet stand-in: pair b of a batch gets the constant ``values[b]`` (metres at d0);
    records the pairs it read."""

    def __init__(self, values):
        super().__init__()
        self.values, self.seen = torch.tensor(values), None

    def forward(self, pair):
        self.seen = pair
        b, _, h, w = pair.shape
        return [self.values.view(-1, 1, 1, 1).expand(b, 1, h // 4 or 1, w // 4 or 1).clone()]


def test_the_pair_closest_to_50_m_is_kept_and_scaled_by_its_displacement():
    """Mean outputs 20, 45, 58, 90 m for references 0..3: 45 is closest to 50, so reference 1
    (3 frames before t, 0.3 m away) is kept, × 0.3 / d0 = 0.15 m: 90 m everywhere."""
    assert PAIR_TARGET_DEPTH == 50.0
    assert choose_pair(torch.tensor([20.0, 45.0, 58.0, 90.0])) == 1
    assert choose_pair(torch.tensor([40.0, 60.0])) == 0  # a tie: the first
    net = _PerPair([20.0, 45.0, 58.0, 90.0])
    m = EvalModel("depthnet-tiny", registry.DEPTH, net, d0=0.15)
    w = _window()
    out = predict(m, w, CPU)
    assert out["shifts"][SCALE_P] == 3 and m.scales == (SCALE_P, SCALE_P_FIXED)
    torch.testing.assert_close(out[SCALE_P], torch.full((H, W), 90.0), rtol=1e-6, atol=0)
    # the fixed pair: the reference whose displacement is closest to d0, whatever the outputs:
    # with d0 = 0.22 m, reference 2 (0.2 m, 2 frames before t): 58 × 0.2 / 0.22
    fixed = predict(EvalModel("depthnet-tiny", registry.DEPTH, net, d0=0.22), w, CPU)
    assert fixed["shifts"] == {SCALE_P: 3, SCALE_P_FIXED: 2}
    torch.testing.assert_close(
        fixed[SCALE_P_FIXED], torch.full((H, W), 58 * 0.2 / 0.22), rtol=1e-6, atol=0
    )
    # the pairs (r, t) for r = 0..3, normalised as DepthNet's inputs; stabilised: not warped
    frames = (torch.from_numpy(w.frames).permute(0, 3, 1, 2).float() / 255 - 0.5) / 0.2
    torch.testing.assert_close(net.seen[:, :3], frames[:4])
    torch.testing.assert_close(net.seen[:, 3:], frames[4:].expand(4, -1, -1, -1))
    # a clamped network's outputs are clamped first: [10, 60] -> 20, 45, 58, 60
    clamped = EvalModel("depthnet-tiny", registry.DEPTH, _PerPair([5.0, 70.0, 80.0, 90.0]),
                        d0=0.1, clamp=(10.0, 60.0))  # fmt: skip
    out = predict(clamped, w, CPU)  # 60 (ref 1..3) ties: ref 1, 0.3 m: 60 × 3 = 180 m
    assert out["shifts"][SCALE_P] == 3
    torch.testing.assert_close(out[SCALE_P], torch.full((H, W), 180.0), rtol=1e-6, atol=0)


def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def test_upside_down_flips_frames_depth_and_camera_geometry_consistently():
    """Rows of frames and depth reversed; and a 3-D point seen at row y in frame i is, in the
    flipped window's geometry (K', R', positions'), seen at row H − 1 − y, same column."""
    rot = np.stack([_rx(0.05 * (4 - i)) @ _ry(-0.03 * (4 - i)) for i in range(5)])
    w = _window(rot, cy=3.0)  # an off-centre principal point
    f = upside_down(w)
    np.testing.assert_array_equal(f.frames, w.frames[:, ::-1])
    np.testing.assert_array_equal(f.depth, w.depth[::-1])
    assert f.K[1, 2] == H - 1 - 3.0 and f.K[0, 2] == w.K[0, 2]
    assert not f.stabilised and f.last == w.last
    flip = np.diag([1.0, -1.0, 1.0])
    for i in range(5):
        np.testing.assert_allclose(f.rotation[i], flip @ rot[i] @ flip, atol=1e-15)
        assert np.linalg.det(f.rotation[i]) == pytest.approx(1.0)
    x_t = np.array([0.7, -1.1, 6.0])  # a point in t's camera axes
    for i in range(5):
        tau = -w.rotation[i] @ w.position[i]  # X_i = R·X_t + τ, camera i at −Rᵀτ
        seen = w.K @ (w.rotation[i] @ x_t + tau)
        tau_f = -f.rotation[i] @ f.position[i]
        seen_f = f.K @ (f.rotation[i] @ (flip @ x_t) + tau_f)
        x, y = seen[:2] / seen[2]
        np.testing.assert_allclose(seen_f[:2] / seen_f[2], [x, H - 1 - y], atol=1e-12)
    back = upside_down(f)
    for a, b in zip(
        (back.frames, back.depth, back.K, back.rotation, back.position),
        (w.frames, w.depth, w.K, w.rotation, w.position),
        strict=True,
    ):
        np.testing.assert_allclose(a, b, atol=1e-15)


class _Sfm(torch.nn.Module):
    """An SfmLearnerNet stand-in: depth 2 everywhere (full resolution); PoseNet's positions."""

    frames = 5

    def __init__(self, poses):
        super().__init__()
        self.poses = poses

    def forward(self, pair):
        return [torch.full_like(pair[:, :1], 2.0)]

    def pose(self, sequence):
        assert sequence.shape == (1, 15, H, W)
        return self.poses


def test_sfmlearner_p_and_gt_scales_and_the_constant_plane():
    """P: measured 0.4 m between the window's first and last frames over PoseNet's 0.8 units:
    2 × 0.5 = 1 m; GT: the ground truth's median (48.5 for 1..96) over the prediction's (2),
    × 2; the constant plane: that median everywhere."""
    poses = torch.zeros(1, 5, 3)
    poses[0, 0] = torch.tensor([0.0, 0.0, -0.8])
    m = EvalModel("sfmlearner-tiny", registry.SCALE_FREE, _Sfm(poses))
    assert m.scales == (SCALE_P, SCALE_GT) and m.stabilise == "none"
    out = predict(m, _window(), CPU)
    p = 0.4 / (EPSILON + 0.8)
    torch.testing.assert_close(out[SCALE_P], torch.full((H, W), 2.0 * p), rtol=1e-6, atol=0)
    torch.testing.assert_close(out[SCALE_GT], torch.full((H, W), 48.5), rtol=1e-6, atol=0)
    const = predict(constant_plane(), _window(), CPU)
    assert constant_plane().scales == (SCALE_GT,)
    torch.testing.assert_close(const[SCALE_GT], torch.full((H, W), 48.5))
    assert float(median_scale(torch.ones(1, H, W), torch.from_numpy(_window().depth)[None])) == 48.5


def test_a_6dof_network_is_stabilised_by_its_posenet_rotation():
    """depthnet-unsup-6dof-tiny whose PoseNet answers fixed Euler angles (zero weights, its
    bias): the references DepthNet reads are those warped by K·R·K⁻¹ with that R_{t→r}."""
    torch.manual_seed(0)
    net = registry.build_model("depthnet-unsup-6dof-tiny").eval()
    angles = torch.tensor([[0.02, -0.04, 0.01], [0.0, 0.03, 0.0], [-0.01, 0.0, 0.02], [0.0] * 3])
    bias = torch.cat([torch.zeros(4, 3), angles], 1).reshape(-1) / POSE_SCALE
    with torch.no_grad():
        net.pose.predict.weight.zero_()
        net.pose.predict.bias.copy_(bias)
    seen = {}

    def record(_, args):
        seen["pair"] = args[0]

    net.depth.register_forward_pre_hook(record)
    m = EvalModel("depthnet-unsup-6dof-tiny", registry.UNSUPERVISED, net, d0=0.3, pose="6dof")
    assert m.stabilise == "posenet"
    K = np.array([[32.0, 0, 31.5], [0, 32.0, 31.5], [0, 0, 1]])
    w = _window()
    w = replace(w, frames=np.resize(w.frames, (5, 64, 64, 3)), depth=np.full((64, 64), 9.0), K=K)
    predict(m, w, CPU)
    frames = (torch.from_numpy(w.frames).permute(0, 3, 1, 2).float() / 255 - 0.5) / 0.2
    R = euler_matrix(torch.cat([angles, torch.zeros(1, 3)]))  # R_i: X_i = R_i·X_last
    for r in range(4):  # R_{t→r} = R_r·R_tᵀ with t the last frame (R_t = I)
        warped, valid = rotate_frame(frames[r : r + 1], R[r : r + 1], torch.tensor(w.K).float())
        expected = torch.where(valid, warped, torch.zeros_like(warped))
        torch.testing.assert_close(seen["pair"][r : r + 1, :3], expected, atol=1e-5, rtol=0)
    assert not torch.equal(seen["pair"][0, :3], frames[0])


class _Oracle(torch.nn.Module):
    """A DepthNet that knows the truth: for each window (in the order evaluate reads them) the
    pair (r, t) gets t's true depth × d0 / ‖t_r‖, at full resolution."""

    def __init__(self, windows, d0):
        super().__init__()
        self.windows, self.d0 = list(windows), d0

    def forward(self, pair):
        w = self.windows.pop(0)
        depth = torch.from_numpy(np.ascontiguousarray(w.depth)).float()
        ratio = torch.tensor(self.d0 / np.linalg.norm(w.position[:4], axis=1)).float()
        return [depth.clamp(max=1e4)[None, None] * ratio.view(-1, 1, 1, 1)]


def test_a_network_answering_the_truth_scores_no_error(rotating_dataset):
    """On a rendered rotating set, upright and upside down (the known orientation stabilises
    the references): the oracle's chosen pair, rescaled, is the truth."""
    scenes = Dataset(rotating_dataset).scenes("test")
    order = [v for s in scenes for w in scene_windows(s) for v in (w, upside_down(w))]
    oracle = EvalModel("depthnet-tiny", registry.DEPTH, _Oracle(order, 0.3), d0=0.3)
    rows = evaluate([constant_plane(), oracle], scenes, CPU, (UPRIGHT, UPSIDE_DOWN), False)
    assert not oracle.net.windows
    assert [(r["orientation"], r["model"], r["scale"]) for r in rows] == [
        (o, m, s) for o in (UPRIGHT, UPSIDE_DOWN)
        for m, s in (("constant", "GT"), ("depthnet-tiny", SCALE_P),
                     ("depthnet-tiny", SCALE_P_FIXED))
    ]  # fmt: skip
    windows = sum(s.frames - 4 for s in scenes)
    for r in rows:
        assert r["images"] == r["sequences"] == windows
    for r in (r for r in rows if r["model"] != "constant"):
        assert r["mae"] < 1e-4 and r["mle"] < 1e-6 and r["p1.25"] == 1.0, r
        assert sum(int(c.split(":")[1]) for c in r["shifts_used"].split()) == windows
    # the constant plane scores the error of each window's median plane, computed here in numpy
    errors = []
    for w in (w for s in scenes for w in scene_windows(s)):
        g = np.minimum(w.depth[np.isfinite(w.depth) & (w.depth > 0)].astype(np.float64), 100.0)
        errors.append(np.abs(np.median(g) - g).mean())
    assert rows[0]["mae"] == pytest.approx(np.mean(errors), rel=1e-9) and rows[0]["mae"] > 1.0
    assert rows[0]["mae"] == pytest.approx(rows[3]["mae"])  # a plane has no up and down


def test_the_thesis_rows_beside_ours():
    assert len(THESIS_ROWS) == 7 + 6 and all(len(t.values) == 8 for t in THESIS_ROWS)
    row = {"orientation": UPRIGHT, "model": "depthnet-unsup-tiny", "scale": "P",
           "pose": "orientation", "occlusion": True}  # fmt: skip
    assert thesis_row(row).values[0] == 5.060
    assert thesis_row({**row, "pose": "6dof", "occlusion": False}).values[0] == 10.356
    assert thesis_row({**row, "orientation": UPSIDE_DOWN}).values[0] == 7.731
    sfm = {**row, "model": "sfmlearner-tiny", "pose": "translation", "scale": "GT", "occlusion": 0}
    assert thesis_row(sfm).values[1] == 0.593
    assert thesis_row({**sfm, "orientation": UPSIDE_DOWN, "scale": "P"}).values[1] == 1.511
    assert thesis_row({**sfm, "model": "depthnet-tiny", "scale": "P"}).values[0] == 3.822


def _one_line(proc, *words: str) -> None:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0].startswith("stillbox-bench: error: ") and all(w in lines[0] for w in words)


def test_eval_sequences_end_to_end(tiny_dataset, rotating_dataset, tmp_path):
    """1-step depthnet-unsup-tiny and sfmlearner-tiny runs (stabilised data), scored on the
    rotating set upright and upside down: results.md/.csv/.json with the thesis' rows beside;
    bad input is one line naming the flag, and nothing is written."""
    ckpts = []
    for model in ("depthnet-unsup-tiny", "sfmlearner-tiny"):
        run = tmp_path / model
        bench("run", model, "--data", tiny_dataset, "--out", run, "--batch-size", 2,
              "--max-steps", 1, "--quiet")  # fmt: skip
        ckpts += ["--ckpt", run / "checkpoints" / "best.pt"]
    out = tmp_path / "seq"
    proc = bench("eval-sequences", *ckpts, "--data", rotating_dataset, "--out", out,
                 "--upside-down", "--quiet")  # fmt: skip
    assert "Results in" in proc.stdout and "lowest upright MAE" in proc.stdout
    rows = list(csv.DictReader((out / "results.csv").read_text().splitlines()))
    assert [(r["orientation"], r["model"], r["scale"]) for r in rows] == [
        (o, m, s) for o in (UPRIGHT, UPSIDE_DOWN)
        for m, s in (("constant", "GT"), ("depthnet-unsup-tiny", "P"),
                     ("depthnet-unsup-tiny", SCALE_P_FIXED), ("sfmlearner-tiny", "P"),
                     ("sfmlearner-tiny", "GT"))
    ]  # fmt: skip
    windows = sum(s.frames - 4 for s in Dataset(rotating_dataset).scenes("test"))
    for r in rows:
        assert int(r["images"]) == windows and all(
            np.isfinite(float(r[k])) for k in ("mae", "mre", "mle", "sae", "sle", "p1.25")
        )
    assert rows[1]["stabilisation"] == "known" and rows[1]["supervision"] == "✗"
    assert rows[1]["thesis_table"] == "5.2" and float(rows[1]["thesis_mae"]) == 10.356
    assert rows[2]["thesis_table"] == "" and rows[2]["stabilisation"] == "known"  # fixed pair
    assert rows[9]["thesis_table"] == "5.3" and float(rows[9]["thesis_mae"]) == 8.433
    info = json.loads((out / "results.json").read_text())
    assert info["rotating"] and info["orientations"] == [UPRIGHT, UPSIDE_DOWN]
    md = (out / "results.md").read_text()
    assert "| Unsupervised DepthNet | depthnet-unsup-tiny | tiny | P | ✗ | ✗ |" in md
    assert "| *thesis Table 5.3* | | S → K | P | ✗ |" in md and "## Upside down" in md
    # PoseNet's translation direction: a cosine and a share for the networks with a PoseNet,
    # empty for the constant plane (null in results.json); a row without the columns (an older
    # results file) shows an empty cell
    for r, j in zip(rows, info["rows"], strict=True):
        if r["model"] == "constant":
            assert r["pose_cosine"] == r["pose_cosine_gt_0.9"] == "" and j["pose_cosine"] is None
        else:
            assert -1 <= float(r["pose_cosine"]) <= 1 and 0 <= float(r["pose_cosine_gt_0.9"]) <= 1
            assert j["pose_cosine"] == pytest.approx(float(r["pose_cosine"]))
    assert f"| {POSE_HEADER} | pair chosen" in md
    old = [{k: v for k, v in r.items() if not k.startswith("pose_cosine")} for r in info["rows"]]
    assert f"{old[1]['p1.25^3']:.3f} |  | " in markdown(old, info)
    # bad input: one line naming the flag, --out not created
    no = tmp_path / "no"
    base = ["--data", rotating_dataset, "--out", no]
    _one_line(bench("eval-sequences", "--ckpt", tmp_path / "x.pt", *base, check=False), "--ckpt")
    _one_line(bench("eval-sequences", *ckpts, *base, "--scenes", 0, check=False), "--scenes")
    _one_line(bench("eval-sequences", *ckpts, "--data", tmp_path, "--out", no, check=False),
              "--data")  # fmt: skip
    assert not no.exists()
