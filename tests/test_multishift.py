"""Multi-shift depth (thesis §6.1–6.3) against hand-computed cases: weights, fusion of a two-plane
scene, shift planning with one and two clusters, the moving average, saturated pixels, k-means."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmark.core.multishift import (
    BETA_MAX,
    BETA_MEAN,
    BETA_MIN,
    EPSILON,
    DepthScale,
    ShiftPlanner,
    closest_shift,
    fuse,
    kmeans_1d,
    trimmed,
    weight,
)

SCALE = DepthScale(theta_max=100.0, d0=0.3)  # DepthNet on StillBox: α = 333.3
STEP = 0.1  # metres per frame of the "video": shift k has displacement 0.1·k
AVAILABLE = STEP * np.arange(1, 9)  # shifts 1..8


def two_planes(near: float = 10.0, far: float = 100.0) -> torch.Tensor:
    """A 4×4 depth map (m): left half at ``near``, right half at ``far``."""
    depth = torch.full((4, 4), far, dtype=torch.float64)
    depth[:, :2] = near
    return depth


def perfect_output(depth: torch.Tensor, d: float) -> torch.Tensor:
    """What an exact network trained for d0 = 0.3 m outputs for a pair of displacement d: the
    depth seen at the nominal displacement, depth·d0/d, saturating at θ_max = 100 m."""
    return (depth * SCALE.d0 / d).clamp(max=SCALE.theta_max)


def test_depth_scale_is_equation_6_1():
    assert SCALE.alpha == pytest.approx(1000 / 3)
    assert SCALE.beta(torch.tensor(50.0)).item() == pytest.approx(0.5)
    # depth = α β d = 333.3 · 0.5 · 0.6 = 100 m = output · d / d0 = 50 · 0.6 / 0.3
    assert SCALE.depth(torch.tensor(50.0), 0.6).item() == pytest.approx(100.0)


@pytest.mark.parametrize(
    ("beta", "expected"),
    [
        (0.0, EPSILON),
        (0.05, EPSILON),
        (BETA_MIN, EPSILON),  # rising branch starts at ε
        (0.3, EPSILON + 0.5 * (1 - EPSILON)),  # halfway to β_mean: 0.5005
        (BETA_MEAN, 1.0),
        (0.7, 0.5),  # halfway down to β_max
        (BETA_MAX, 0.0),
        (1.2, 0.0),
    ],
)
def test_weight_at_breakpoints_and_midpoints(beta, expected):
    assert weight(torch.tensor(beta, dtype=torch.float64)).item() == pytest.approx(expected)


def test_weight_is_elementwise():
    w = weight(torch.tensor([[0.0, 0.5], [0.7, 1.0]], dtype=torch.float64))
    assert torch.allclose(w, torch.tensor([[EPSILON, 1.0], [0.5, 0.0]], dtype=torch.float64))


def test_fuse_two_planes_recovers_the_true_depth():
    """Shift 1 (0.1 m) and shift 6 (0.6 m) on planes at 10 m and 100 m.

    Shift 1: outputs 30 (β 0.3, w 0.5005) and 300 → saturates at 100 (β 1, w 0).
    Shift 6: outputs 5 (β 0.05, w ε) and 50 (β 0.5, w 1).
    Estimates: near 10 and 10; far 33.3 (shift 1, weight 0) and 100 (shift 6, weight 1)."""
    truth = two_planes()
    outputs = torch.stack([perfect_output(truth, 0.1), perfect_output(truth, 0.6)])
    assert outputs[0, 0, 0] == 30 and outputs[0, 0, 3] == 100
    assert outputs[1, 0, 0] == 5 and outputs[1, 0, 3] == 50
    depth, saturated = fuse(outputs, [0.1, 0.6], SCALE)
    assert torch.allclose(depth, truth)
    assert not saturated.any()
    # an unweighted mean would put the far plane at (33.3 + 100) / 2
    plain = (SCALE.depth(outputs[0], 0.1) + SCALE.depth(outputs[1], 0.6)) / 2
    assert plain[0, 3].item() == pytest.approx(200 / 3)


def test_fuse_weighs_each_estimate_by_its_beta():
    """Near pixel with an imperfect shift-1 output of 33 (estimate 11 m, β 0.33, w = ε + 0.575
    (1 − ε) = 0.575425) and shift-6 output 5 (estimate 10 m, w ε):
    (0.575425·11 + 0.001·10) / 0.576425 = 10.998265 m."""
    outputs = torch.tensor([[[33.0]], [[5.0]]], dtype=torch.float64)
    depth, saturated = fuse(outputs, [0.1, 0.6], SCALE)
    assert depth.item() == pytest.approx((0.575425 * 11 + 0.001 * 10) / 0.576425)
    assert not saturated.item()


def test_fuse_saturated_pixel_takes_the_plain_mean():
    """A pixel at 1000 m saturates both pairs (β = 1): estimates 100·0.1/0.3 = 33.3 and
    100·0.6/0.3 = 200 m, plain mean 116.7 m, marked saturated."""
    truth = torch.tensor([[10.0, 1000.0]], dtype=torch.float64)
    outputs = torch.stack([perfect_output(truth, 0.1), perfect_output(truth, 0.6)])
    depth, saturated = fuse(outputs, [0.1, 0.6], SCALE)
    assert saturated.tolist() == [[False, True]]
    assert depth[0, 0].item() == pytest.approx(10.0)
    assert depth[0, 1].item() == pytest.approx((100 / 3 + 200) / 2)


def test_fuse_one_pair_is_its_estimate():
    outputs = torch.tensor([[[30.0, 95.0, 3.0]]], dtype=torch.float64)
    depth, saturated = fuse(outputs, [0.2], SCALE)
    assert torch.allclose(depth, outputs[0] * 0.2 / 0.3)
    assert saturated.tolist() == [[False, True, False]]  # β 0.95 ≥ β_max


def test_fuse_checks_shapes():
    with pytest.raises(ValueError, match="n = 2"):
        fuse(torch.ones(3, 2, 2), [0.1, 0.2], SCALE)


def test_trimmed_drops_the_extreme_quantiles():
    """0..99: the 5 % quantile is 4.95 and the 90 % one 89.1, so 5..89 stay (85 values)."""
    kept = trimmed(torch.arange(100, dtype=torch.float64))
    assert kept.min().item() == 5 and kept.max().item() == 89 and kept.numel() == 85
    assert trimmed(torch.zeros(0)).numel() == 0


def test_kmeans_finds_both_modes():
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.normal(10, 1, 300), rng.normal(60, 3, 100)])
    c = kmeans_1d(torch.from_numpy(values), 2)
    assert c.tolist() == pytest.approx([10, 60], abs=0.5)
    assert torch.equal(c, kmeans_1d(torch.from_numpy(values), 2))  # deterministic


def test_kmeans_edge_cases():
    # 90 % at 10 m: both initial quantiles are 10, one cluster empties and takes the far value
    values = torch.tensor([10.0] * 90 + [100.0] * 10)
    assert kmeans_1d(values, 2).tolist() == [10.0, 100.0]
    # fewer distinct values than clusters: fewer centroids
    assert kmeans_1d(torch.tensor([5.0, 5.0, 7.0]), 3).tolist() == [5.0, 7.0]
    assert kmeans_1d(torch.tensor([20.0] * 8), 2).tolist() == [20.0]
    assert kmeans_1d(torch.tensor([1.0, 2.0, 3.0, 10.0, 11.0, 12.0]), 1).tolist() == [6.5]


def test_closest_shift():
    assert closest_shift(0.33, AVAILABLE) == 3
    assert closest_shift(0.06, AVAILABLE) == 1
    assert closest_shift(5.0, AVAILABLE) == 8
    assert closest_shift(2.5, np.array([1.0, 2.0, 3.0])) == 2  # tie -> smaller shift
    assert closest_shift(0.0, np.array([0.0, 0.0, 0.3])) == 3  # no motion is never chosen
    with pytest.raises(ValueError, match="non-zero"):
        closest_shift(0.3, np.zeros(3))


def test_planner_one_cluster_uses_the_trimmed_mean():
    """Two planes: trimmed mean (nothing trimmed: the 5 % / 90 % quantiles are 10 and 100) is
    55 m → d_opt = 55 / (α·0.5) = 55 / 166.7 = 0.33 m → shift 3 at 0.1 m per frame."""
    planner = ShiftPlanner(1, SCALE)
    assert planner.plan(AVAILABLE) == [3]  # nothing known yet: d0 = 0.3 m
    assert planner.plan(0.05 * np.arange(1, 9)) == [6]
    planner.update(two_planes(), torch.zeros(4, 4, dtype=torch.bool))
    assert planner.d_opt.tolist() == pytest.approx([0.33])
    assert planner.plan(AVAILABLE) == [3]
    assert planner.plan(0.05 * np.arange(1, 9)) == [7]  # 0.35 is 0.02 away, 0.30 0.03


def test_planner_two_clusters_pick_one_shift_per_plane():
    """Centroids 10 m and 100 m → d_opt 10/166.7 = 0.06 m and 100/166.7 = 0.6 m → shifts 1, 6."""
    planner = ShiftPlanner(2, SCALE)
    planner.update(two_planes(), torch.zeros(4, 4, dtype=torch.bool))
    assert planner.d_opt.tolist() == pytest.approx([0.06, 0.6])
    assert planner.plan(AVAILABLE) == [1, 6]
    assert planner.plan(AVAILABLE[:3]) == [1, 3]  # only 3 frames back: the farthest available


def test_planner_moving_average():
    """λ = 0.5: 0.33 m, then a uniform 20 m frame (target 20/166.7 = 0.12 m) → 0.225 m."""
    none = torch.zeros(4, 4, dtype=torch.bool)
    planner = ShiftPlanner(1, SCALE, ema=0.5)
    planner.update(two_planes(), none)
    planner.update(torch.full((4, 4), 20.0), none)
    assert planner.d_opt.tolist() == pytest.approx([0.5 * 0.33 + 0.5 * 0.12])
    no_smoothing = ShiftPlanner(1, SCALE, ema=0.0)
    no_smoothing.update(two_planes(), none)
    no_smoothing.update(torch.full((4, 4), 20.0), none)
    assert no_smoothing.d_opt.tolist() == pytest.approx([0.12])
    # two centroids, then a frame with a single depth: one centroid, d_opt restarts
    two = ShiftPlanner(2, SCALE)
    two.update(two_planes(), none)
    two.update(torch.full((4, 4), 20.0), none)
    assert two.d_opt.tolist() == pytest.approx([0.12])


def test_planner_ignores_saturated_pixels():
    """The 100 m half saturated: only the 10 m half counts → d_opt 0.06 m; a frame with every pixel
    saturated leaves d_opt unchanged."""
    saturated = two_planes() > 50
    planner = ShiftPlanner(1, SCALE)
    planner.update(two_planes(), saturated)
    assert planner.d_opt.tolist() == pytest.approx([0.06])
    planner.update(two_planes(), torch.ones(4, 4, dtype=torch.bool))
    assert planner.d_opt.tolist() == pytest.approx([0.06])


def test_planner_trims_the_sky():
    """95 pixels at 20 m and 5 at 1000 m (not saturated): the 90 % quantile is 20 m, the sky is
    left out, d_opt = 20/166.7 = 0.12 m (with the sky the mean would be 69 m)."""
    depth = torch.tensor([20.0] * 95 + [1000.0] * 5).reshape(10, 10)
    planner = ShiftPlanner(1, SCALE)
    planner.update(depth, torch.zeros(10, 10, dtype=torch.bool))
    assert planner.d_opt.tolist() == pytest.approx([0.12])


def test_planner_fixed_shift_and_arguments():
    planner = ShiftPlanner(1, SCALE, fixed_shift=5)
    assert planner.plan(AVAILABLE) == [5]
    assert planner.plan(AVAILABLE[:2]) == [2]  # clipped to the frames available
    planner.update(two_planes(), torch.zeros(4, 4, dtype=torch.bool))
    assert planner.plan(AVAILABLE) == [5]
    for bad in ({"n": 0}, {"n": 5}, {"n": 1, "ema": 1.0}, {"n": 1, "fixed_shift": 0}):
        with pytest.raises(ValueError):
            ShiftPlanner(scale=SCALE, **bad)


def test_beta_mean_moves_the_target_and_the_weight_peak():
    """β_mean = 0.25: the two planes' mean 55 m → d_opt = 55 / (333.3·0.25) = 0.66 m (twice the
    0.33 m of β_mean = 0.5) → shift 7; the weight peaks at 0.25 and is halfway up at 0.175."""
    planner = ShiftPlanner(1, SCALE, beta_mean=0.25)
    planner.update(two_planes(), torch.zeros(4, 4, dtype=torch.bool))
    assert planner.d_opt.tolist() == pytest.approx([0.66])
    assert planner.plan(AVAILABLE) == [7]
    w = weight(torch.tensor([0.175, 0.25, 0.575, 0.9], dtype=torch.float64), beta_mean=0.25)
    assert w.tolist() == pytest.approx([EPSILON + 0.5 * (1 - EPSILON), 1.0, 0.5, 0.0])
    out = torch.stack([perfect_output(two_planes(), d) for d in (0.1, 0.6)])
    fused, saturated = fuse(out, [0.1, 0.6], SCALE, beta_mean=0.25)
    # near plane: both estimates 10 m; far plane: 0.1 m saturates (β = 1, weight 0), 0.6 m gives
    # β = 0.5 (weight (0.9 − 0.5)/(0.9 − 0.25)) and 100 m
    assert torch.allclose(fused, two_planes()) and not saturated.any()
    for bad in (BETA_MIN, BETA_MAX, 1.0):
        with pytest.raises(ValueError, match="beta_mean"):
            ShiftPlanner(1, SCALE, beta_mean=bad)
        with pytest.raises(ValueError, match="beta_mean"):
            weight(torch.tensor([0.5]), beta_mean=bad)
