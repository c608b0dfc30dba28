"""benchmark.core.flow: exact flow from depth and translation, depth back from flow
(thesis 3.3.1)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmark.core.data import FrameStore, load_scenes
from benchmark.core.flow import (
    depth_from_flow,
    endpoint_error,
    flow_errors,
    flow_from_depth,
    warp,
)
from benchmark.core.geometry import distance_to_foe, focus_of_expansion

H, W = 48, 64


def intrinsics(f: float = 32.0, cx: float = (W - 1) / 2, cy: float = (H - 1) / 2) -> torch.Tensor:
    return torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)


def grid() -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    return xs, ys


def slanted_scene(K: torch.Tensor) -> np.ndarray:
    """Depth (frame a) of a plane n·X = d seen by the camera: Z = d / (n·K⁻¹p), 4 to 20 m."""
    xs, ys = grid()
    rays = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(K.numpy()).T
    n, d = np.array([0.15, -0.1, 1.0]), 8.0
    return d / (rays @ n)


# translations a -> b: forward, backward, lateral (x, y), diagonal; FOE inside and outside
MOTIONS = {
    "forward": [0.0, 0.0, 0.3],
    "backward": [0.0, 0.0, -0.3],
    "lateral-x": [0.3, 0.0, 0.0],
    "lateral-y": [0.0, -0.25, 0.0],
    "diagonal-foe-inside": [0.05, -0.04, 0.25],
    "diagonal-foe-outside": [0.25, 0.2, 0.1],
    "backward-foe-outside": [-0.2, 0.1, -0.05],
    "nearly-lateral": [0.3, 0.1, 1e-7],
}


def test_fronto_parallel_plane_matches_the_analytic_flow():
    """A wall at depth Z in frame a, camera moving by T:
    F = (−f·Tx + Tz·(x − cx), −f·Ty + Tz·(y − cy)) / (Z − Tz),
    derived by hand from x_b = cx + f·(X − Tx)/(Z − Tz) with X = (x − cx)·Z/f."""
    K = intrinsics(f=40.0, cx=30.0, cy=20.0)
    z, t = 5.0, np.array([0.2, -0.1, 0.5])
    flow = flow_from_depth(torch.full((H, W), z, dtype=torch.float64), K, torch.tensor(t))
    assert flow.shape == (2, H, W) and flow.dtype == torch.float64
    xs, ys = grid()
    u = (40.0 * -t[0] + t[2] * (xs - 30.0)) / (z - t[2])
    v = (40.0 * -t[1] + t[2] * (ys - 20.0)) / (z - t[2])
    np.testing.assert_allclose(flow[0].numpy(), u, atol=1e-12)
    np.testing.assert_allclose(flow[1].numpy(), v, atol=1e-12)
    # values by hand: the pixel (30, 20) on the axis moves by f·(−Tx, −Ty)/(Z − Tz) = (−16/9, 8/9)
    assert flow[:, 20, 30].tolist() == pytest.approx([-16 / 9, 8 / 9])
    # the FOE (30 + 40·0.4, 20 − 40·0.2) = (46, 12) does not move
    assert focus_of_expansion(K.numpy(), t) == pytest.approx((46.0, 12.0))
    assert flow[:, 12, 46].abs().max() < 1e-12
    # a point behind camera b (Z − Tz ≤ 0) has no flow
    bad = flow_from_depth(torch.full((2, 3), 0.4, dtype=torch.float64), K, torch.tensor(t))
    assert torch.isnan(bad).all()


def test_flow_moves_points_to_their_projection_in_frame_b():
    K = intrinsics()
    depth = slanted_scene(K)
    t = np.array([0.1, 0.05, -0.3])
    flow = flow_from_depth(torch.from_numpy(depth), K, torch.tensor(t)).numpy()
    xs, ys = grid()
    X = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(K.numpy()).T * depth[..., None]
    p = (X - t) @ K.numpy().T
    np.testing.assert_allclose(flow[0], p[..., 0] / p[..., 2] - xs, atol=1e-10)
    np.testing.assert_allclose(flow[1], p[..., 1] / p[..., 2] - ys, atol=1e-10)


@pytest.mark.parametrize("motion", list(MOTIONS))
def test_depth_from_flow_recovers_the_scene(motion):
    K = intrinsics()
    t = torch.tensor(MOTIONS[motion], dtype=torch.float64)
    depth = torch.from_numpy(slanted_scene(K))
    flow = flow_from_depth(depth, K, t)
    back = depth_from_flow(flow, K, t, clamp=False)
    dist = distance_to_foe(K.numpy(), t.numpy(), H, W)
    away = dist > 0.5
    np.testing.assert_allclose(back.numpy()[away], depth.numpy()[away], rtol=1e-9)
    assert away.mean() > 0.99  # nearly every pixel tested
    foe = focus_of_expansion(K.numpy(), t.numpy())
    inside = foe is not None and 0 <= foe[0] <= W - 1 and 0 <= foe[1] <= H - 1
    assert inside == (motion in ("forward", "backward", "diagonal-foe-inside"))
    # clamped output: finite, within [0.1, 100], equal to the truth away from the FOE
    clamped = depth_from_flow(flow, K, t)
    assert torch.isfinite(clamped).all() and clamped.min() >= 0.1 and clamped.max() <= 100
    np.testing.assert_allclose(clamped.numpy()[away], depth.numpy()[away], rtol=1e-9)


def test_depth_from_flow_batched_and_float32():
    K = intrinsics()
    ts = torch.tensor([MOTIONS["forward"], MOTIONS["lateral-x"]], dtype=torch.float64)
    depth = torch.from_numpy(slanted_scene(K)).expand(2, H, W)
    flow = flow_from_depth(depth, K.expand(2, 3, 3), ts)
    assert flow.shape == (2, 2, H, W)
    back = depth_from_flow(flow.float(), K.float(), ts.float())
    assert back.dtype == torch.float32 and back.shape == (2, H, W)
    away = torch.from_numpy(distance_to_foe(K.numpy(), ts[0].numpy(), H, W) > 2)
    np.testing.assert_allclose(back[0][away], depth[0][away], rtol=1e-3)
    np.testing.assert_allclose(back[1], depth[1], rtol=1e-4)


def test_depth_from_flow_conventions_at_the_edges():
    """No parallax -> far (100 m); flow against the epipolar direction -> negative -> 0.1 m;
    NaN flow -> 100 m. Every pixel keeps a finite value."""
    K = intrinsics()
    t = torch.tensor(MOTIONS["forward"], dtype=torch.float64)
    zero = depth_from_flow(torch.zeros(2, H, W, dtype=torch.float64), K, t)
    assert torch.all(zero == 100.0)
    flow = flow_from_depth(torch.full((H, W), 10.0, dtype=torch.float64), K, t)
    assert torch.all(depth_from_flow(-flow, K, t)[distance_to_foe(K.numpy(), t, H, W) > 1] == 0.1)
    nan = depth_from_flow(torch.full((2, H, W), float("nan"), dtype=torch.float64), K, t)
    assert torch.all(nan == 100.0)
    # no motion at all: every pixel "at infinity"
    still = depth_from_flow(flow, K, torch.zeros(3, dtype=torch.float64))
    assert torch.all(still == 100.0)


def test_error_near_the_foe_grows_with_a_flow_error():
    """A constant 0.01 px flow error costs little far from the FOE and a lot near it."""
    K = intrinsics()
    t = torch.tensor(MOTIONS["forward"], dtype=torch.float64)
    depth = torch.full((H, W), 20.0, dtype=torch.float64)
    flow = flow_from_depth(depth, K, t) + 0.01
    err = (depth_from_flow(flow, K, t) - depth).abs().numpy()
    dist = distance_to_foe(K.numpy(), t.numpy(), H, W)
    assert np.median(err[dist < 3]) > 5 * np.median(err[dist > 20])


def test_endpoint_error():
    gt = torch.zeros(1, 2, 2, 2, dtype=torch.float64)
    gt[0, :, 1, 1] = float("nan")  # left out
    pred = torch.zeros(1, 2, 2, 2)
    pred[0, 0, 0, 0], pred[0, 1, 0, 0] = 3.0, 4.0  # EPE 5 at one of 3 valid pixels
    pred[0, 0, 1, 1] = 100.0
    assert endpoint_error(pred, gt).tolist() == pytest.approx([5 / 3])


def test_warp_with_exact_flow_reproduces_a_synthetic_frame():
    """Frame b of a textured wall, sampled with the flow, gives frame a back."""
    K = intrinsics()
    t = torch.tensor([0.1, 0.0, 0.4], dtype=torch.float64)
    z = 6.0

    def texture(u, v):  # on the wall, metres
        return np.sin(3 * u) * np.cos(2 * v)

    xs, ys = grid()
    img_a = texture((xs - K[0, 2].item()) * z / 32, (ys - K[1, 2].item()) * z / 32)
    zb = z - t[2].item()
    img_b = texture(
        (xs - K[0, 2].item()) * zb / 32 + t[0].item(), (ys - K[1, 2].item()) * zb / 32 + t[1].item()
    )
    flow = flow_from_depth(torch.full((1, H, W), z, dtype=torch.float64), K, t)
    warped, inside = warp(torch.from_numpy(img_b)[None, None], flow)
    err = np.abs(warped[0, 0].numpy() - img_a)[inside[0].numpy()]
    assert inside.float().mean() > 0.7 and err.max() < 0.05


@pytest.mark.render
def test_gt_flow_warps_rendered_frames(default_dataset):
    """Warping rendered frame i+3 into frame i with the exact flow (depth of frame i, the known
    translation) reduces the photometric error against frame i on moving pixels."""
    scenes = load_scenes(default_dataset, "train") + load_scenes(default_dataset, "val")
    scenes += load_scenes(default_dataset, "test")
    store = FrameStore(scenes, progress=False)
    checked = 0
    for k, scene in enumerate(scenes):
        i, j = 2, 5
        depth = torch.from_numpy(store.depth(k, i).astype(np.float64))
        K = torch.from_numpy(scene.K)
        flow = flow_from_depth(depth, K, torch.from_numpy(scene.translation(i, j)))[None]
        img_i = torch.from_numpy(store.rgb(k, i).astype(np.float64)).permute(2, 0, 1)
        img_j = torch.from_numpy(store.rgb(k, j).astype(np.float64)).permute(2, 0, 1)
        warped, inside = warp(img_j[None], flow)
        moving = inside[0] & (flow[0].norm(dim=0) > 0.5)
        if moving.sum() < 50:
            continue
        before = (img_j - img_i).abs().mean(0)[moving].mean()
        after = (warped[0] - img_i).abs().mean(0)[moving].mean()
        assert after < 0.8 * before, (scene.index, float(before), float(after))
        checked += 1
    assert checked >= 2


def test_flow_outlier_rates_against_numpy():
    """Fl-all (KITTI 2015: error > 3 px and > 5 % of the true flow) and the 1/3/5 px outlier
    rates against a numpy transcription, NaN truth left out; a hand case at the boundaries."""

    g = torch.Generator().manual_seed(0)
    gt = torch.randn(3, 2, 8, 9, generator=g, dtype=torch.float64) * 40
    pred = gt + torch.randn(3, 2, 8, 9, generator=g, dtype=torch.float64) * 3
    gt[0, :, :2] = float("nan")
    m = flow_errors(pred, gt)
    for b in range(3):
        t, p = gt[b].numpy(), pred[b].numpy()
        ok = np.isfinite(t).all(0)
        err = np.hypot(*(p - t))[ok]
        mag = np.hypot(*t)[ok]
        assert m["epe"][b].item() == pytest.approx(err.mean())
        assert m["fl_all"][b].item() == pytest.approx(np.mean((err > 3) & (err > 0.05 * mag)))
        for px in (1, 3, 5):
            assert m[f"out{px}"][b].item() == pytest.approx(np.mean(err > px))
    # errors 4 px on a 100 px flow (4 % < 5 %: not Fl), 4 px on a 50 px flow (8 %: Fl), 3 px
    # exactly (not > 3 px)
    gt = torch.tensor([[[[100.0, 50.0, 10.0]], [[0.0, 0.0, 0.0]]]])
    pred = gt + torch.tensor([[[[4.0, 4.0, 3.0]], [[0.0, 0.0, 0.0]]]])
    m = flow_errors(pred, gt)
    assert m["fl_all"].item() == pytest.approx(1 / 3) and m["out3"].item() == pytest.approx(2 / 3)
    assert m["out1"].item() == 1.0 and m["out5"].item() == 0.0
