"""benchmark.core.metrics: hand-computed values, validity, clamping, batch invariance, DepthNet
error."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from benchmark.core.metrics import (
    DEPTH_BANDS,
    DEPTH_METRICS,
    METRICS,
    aggregate,
    image_metrics,
    original_depth_error,
    upsample_to,
)

# Image A: pred [[1, 2], [4, 8]] vs gt 2 everywhere.
#   |θ̃−θ| = 1, 0, 2, 6            -> MAE = 9/4 = 2.25, SAE = sqrt((1+0+4+36)/4) = sqrt(10.25)
#   |θ̃−θ|/θ = 0.5, 0, 1, 3         -> MRE = 4.5/4 = 1.125
#   |log θ̃/θ| = ln2, 0, ln2, 2 ln2  -> MLE = 4 ln2 / 4 = ln2, SLE = sqrt(6 ln2² / 4) = ln2·sqrt(1.5)
#   max ratio = 2, 1, 2, 4          -> P_1.25 = P_1.5625 = P_1.953125 = 1/4
# Image B: pred [[2.4, 3.0], [3.8, 5.0]] vs gt 2 everywhere.
#   |θ̃−θ| = 0.4, 1, 1.8, 3 -> MAE = 6.2/4 = 1.55, SAE = sqrt((0.16+1+3.24+9)/4) = sqrt(3.35)
#   MRE = MAE / 2 = 0.775
#   log ratios = ln1.2, ln1.5, ln1.9, ln2.5 -> MLE = ln(1.2·1.5·1.9·2.5)/4 = ln(8.55)/4
#   SLE = sqrt((0.18232² + 0.40547² + 0.64185² + 0.91629²)/4)
#   max ratio = 1.2, 1.5, 1.9, 2.5  -> P_1.25 = 1/4, P_1.5625 = 2/4, P_1.953125 = 3/4
EXPECTED = {
    "mae": [2.25, 1.55],
    "mre": [1.125, 0.775],
    "mle": [0.6931471805599453, 0.5364828207371672],  # ln 2, ln(8.55)/4
    "sae": [3.2015621187164243, 1.8303005217723125],  # sqrt(10.25), sqrt(3.35)
    "sle": [0.8489284545103327, 0.6019153222169247],  # ln2·sqrt(1.5), see above
    "p1.25": [0.25, 0.25],
    "p1.25^2": [0.25, 0.5],
    "p1.25^3": [0.25, 0.75],
    # The field's three others, from the same differences:
    #   A: (θ̃−θ)²/θ = 0.5, 0, 2, 18 -> SqRel = 20.5/4; |log10 θ̃/θ| -> log10 2 (as MLE / ln 10);
    #      e = −ln2, 0, ln2, 2 ln2: E e² − (E e)² = 1.5 ln2² − 0.25 ln2² -> SILog = 100 ln2 √1.25
    #   B: (θ̃−θ)²/θ = 0.08, 0.5, 1.62, 4.5 -> SqRel = 6.7/4; log10 = log10(8.55)/4;
    #      SILog = 100 sqrt(E e² − (E e)²), e = ln 1.2, ln 1.5, ln 1.9, ln 2.5
    "sqrel": [5.125, 1.675],
    "log10": [0.3010299956639812, 0.23299152868204315],
    "silog": [77.49621070721791, 27.29253344293942],
    # gt = 2 m is within the 15 m sensing range everywhere: 8 m is not beyond it (missed 0), and
    # no pixel is truly beyond it (phantom undefined)
    "missed_near": [0.0, 0.0],
    "phantom_near": [math.nan, math.nan],
}


def hand_batch() -> tuple[torch.Tensor, torch.Tensor]:
    pred = torch.tensor([[[1.0, 2.0], [4.0, 8.0]], [[2.4, 3.0], [3.8, 5.0]]])
    gt = torch.full((2, 2, 2), 2.0)
    return pred, gt


def test_precision_thresholds_are_strict_and_symmetric():
    """P_δ counts max(θ̃/θ, θ/θ̃) < δ: a ratio of exactly 1.25 (either way) is not within 1.25
    but within 1.25²; 1.5625 = 1.25² exactly is within 1.25³ only."""
    gt = torch.tensor([[[2.0, 2.5, 2.0, 2.0]]])
    pred = torch.tensor([[[2.5, 2.0, 3.125, 2.2]]])  # ratios 1.25, 1.25 (gt/pred), 1.5625, 1.1
    m = image_metrics(pred, gt)
    assert m["p1.25"].item() == pytest.approx(1 / 4)
    assert m["p1.25^2"].item() == pytest.approx(3 / 4)
    assert m["p1.25^3"].item() == pytest.approx(1.0)
    # natural logs: |ln 1.25| twice, ln 1.5625, ln 1.1
    mle = (2 * math.log(1.25) + math.log(1.5625) + math.log(1.1)) / 4
    assert m["mle"].item() == pytest.approx(mle)


def test_hand_computed_values():
    pred, gt = hand_batch()
    m = image_metrics(pred, gt)
    for name in METRICS:
        assert m[name].dtype == torch.float64 and m[name].shape == (2,)
        np.testing.assert_allclose(m[name].numpy(), EXPECTED[name], rtol=1e-6, err_msg=name)
    assert m["valid_pixels"].dtype == torch.int64
    assert m["valid_pixels"].tolist() == [4, 4]
    summary = aggregate(m)
    for name in METRICS:
        assert summary[name] == pytest.approx(sum(EXPECTED[name]) / 2, rel=1e-6, nan_ok=True)
    assert summary["images"] == 2 and summary["images_without_valid_pixels"] == 0


def test_field_metrics_against_numpy():
    """SqRel, log10 and SILog against a numpy transcription of their definitions (KITTI
    devkit, Monodepth2) on random maps with invalid pixels, clamping and clipping."""
    pred, gt = random_batch()
    m = image_metrics(pred, gt)
    for b in range(len(gt)):
        g = gt[b].double().numpy()
        ok = np.isfinite(g) & (g > 0)
        if not ok.any():
            continue
        p = np.clip(pred[b].double().numpy()[ok], 0.1, 100.0)
        g = np.minimum(g[ok], 100.0)
        e = np.log(p) - np.log(g)
        assert m["sqrel"][b].item() == pytest.approx(np.mean((p - g) ** 2 / g), rel=1e-10)
        assert m["log10"][b].item() == pytest.approx(np.mean(np.abs(np.log10(p / g))), rel=1e-10)
        silog = 100 * np.sqrt(np.mean(e**2) - np.mean(e) ** 2)
        assert m["silog"][b].item() == pytest.approx(silog, rel=1e-9)
        near = g <= 15.0
        assert m["missed_near"][b].item() == pytest.approx(np.mean(p[near] > 15.0))
        assert m["phantom_near"][b].item() == pytest.approx(np.mean(p[~near] <= 15.0))


def test_silog_ignores_a_global_scale_and_range_metrics_count_each_side():
    """SILog is scale invariant (θ̃ = 2θ scores 0); missed and phantom count the pixels put on
    the wrong side of the sensing range, each among the pixels truly on their side, and are
    left out of the mean for an image with no pixel on that side."""
    gt = torch.tensor([[[5.0, 10.0], [20.0, 40.0]], [[20.0, 30.0], [40.0, 50.0]]])
    m = image_metrics(gt * 2, gt)
    assert m["silog"].tolist() == pytest.approx([0.0, 0.0], abs=1e-6)
    assert m["mre"].tolist() == pytest.approx([1.0, 1.0])
    # image 0: 10 m -> 20 m is missed (1 of 2 near pixels); no far pixel comes within 15 m
    assert m["missed_near"][0].item() == 0.5 and m["phantom_near"][0].item() == 0.0
    assert math.isnan(m["missed_near"][1].item())  # no pixel within 15 m
    pred = torch.tensor([[[20.0, 10.0], [11.0, 16.0]]])  # 5 m missed, 20 m a phantom
    m = image_metrics(pred, gt[:1], sensing_range=12.0)
    assert m["missed_near"].item() == 0.5 and m["phantom_near"].item() == 0.5
    summary = aggregate(image_metrics(gt * 2, gt))
    assert summary["missed_near"] == 0.5 and summary["images"] == 2


def test_relative_error_divides_by_ground_truth():
    # pred 1 vs gt 2: |1-2|/2 = 0.5 (dividing by the prediction would give 1)
    m = image_metrics(torch.tensor([[[1.0]]]), torch.tensor([[[2.0]]]))
    assert m["mre"].item() == pytest.approx(0.5)


def test_perfect_prediction():
    gt = torch.rand(3, 5, 7) * 90 + 1
    m = image_metrics(gt.clone(), gt)
    for name in ("mae", "mre", "mle", "sae", "sle"):
        assert torch.all(m[name] == 0), name
    for name in ("p1.25", "p1.25^2", "p1.25^3"):
        assert torch.all(m[name] == 1), name


def test_invalid_pixels_and_images():
    pred, gt = hand_batch()
    gt_bad = torch.stack([gt[0], torch.zeros(2, 2), torch.full((2, 2), math.nan), gt[1]])
    pred_bad = torch.stack([pred[0], pred[0], pred[0], pred[1]])
    m = image_metrics(pred_bad, gt_bad)
    assert m["valid_pixels"].tolist() == [4, 0, 0, 4]
    for name in METRICS:
        assert torch.isnan(m[name][1:3]).all(), name
    for name in DEPTH_METRICS:
        assert not torch.isnan(m[name][[0, 3]]).any(), name
    summary = aggregate(m)
    assert summary["images"] == 2 and summary["images_without_valid_pixels"] == 2
    for name in METRICS:
        assert summary[name] == pytest.approx(sum(EXPECTED[name]) / 2, rel=1e-6, nan_ok=True)
    # without the valid_pixels column the NaN rows are still recognised and excluded
    no_count = {k: v.numpy() for k, v in m.items() if k != "valid_pixels"}
    assert aggregate(no_count) == summary


def test_partially_invalid_image_ignores_bad_pixels():
    # one NaN, one inf, one negative ground-truth pixel: only the pixel (0, 0) is scored
    gt = torch.tensor([[[4.0, math.nan], [math.inf, -1.0]]])
    pred = torch.tensor([[[5.0, 1.0], [1.0, 1.0]]])
    m = image_metrics(pred, gt)
    assert m["valid_pixels"].item() == 1
    assert m["mae"].item() == pytest.approx(1.0)
    assert m["mre"].item() == pytest.approx(0.25)


def test_all_invalid_batch_aggregates_to_nan():
    m = image_metrics(torch.ones(2, 3, 3), torch.zeros(2, 3, 3))
    summary = aggregate(m)
    assert all(math.isnan(summary[name]) for name in METRICS)
    assert summary["images"] == 0 and summary["images_without_valid_pixels"] == 2


def test_clamping_and_clipping():
    # pred 0 -> 0.1 (vs gt 1: error 0.9); pred 1000 -> 100 (vs gt 50: error 50);
    # pred -5 -> 0.1 (vs gt 0.1: error 0); gt 150 -> 100 (vs pred 100: error 0)
    pred = torch.tensor([[[0.0]], [[1000.0]], [[-5.0]], [[100.0]]], dtype=torch.float64)
    gt = torch.tensor([[[1.0]], [[50.0]], [[0.1]], [[150.0]]], dtype=torch.float64)
    m = image_metrics(pred, gt)
    np.testing.assert_allclose(m["mae"].numpy(), [0.9, 50.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(m["mle"].numpy(), [math.log(10), math.log(2), 0, 0], atol=1e-12)
    # custom bounds
    m = image_metrics(pred, gt, max_depth=80.0, min_depth=0.5)
    np.testing.assert_allclose(m["mae"].numpy(), [0.5, 30.0, 0.4, 0.0], atol=1e-12)


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="upsample_to"):
        image_metrics(torch.ones(1, 1, 4, 4), torch.ones(1, 4, 4))
    with pytest.raises(ValueError):
        image_metrics(torch.ones(1, 4, 4), torch.ones(1, 4, 5))


def random_batch(n: int = 8, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(n, 24, 32, generator=g) * 120  # some above 100 m
    gt[torch.rand(n, 24, 32, generator=g) < 0.1] = 0.0  # some invalid pixels
    gt[3] = math.nan  # one all-invalid image
    pred = gt + torch.randn(n, 24, 32, generator=g) * 10  # some negative predictions
    return pred.float(), gt.float()


def test_batch_size_invariance():
    pred, gt = random_batch()
    full = image_metrics(pred, gt)
    splits = {
        "3+5": [image_metrics(pred[:3], gt[:3]), image_metrics(pred[3:], gt[3:])],
        "1x8": [image_metrics(pred[i : i + 1], gt[i : i + 1]) for i in range(8)],
    }
    full_summary = aggregate(full)
    for label, parts in splits.items():
        joined = {k: torch.cat([p[k] for p in parts]) for k in full}
        for k in full:
            torch.testing.assert_close(joined[k], full[k], rtol=0, atol=1e-12, equal_nan=True)
        summary = aggregate(joined)
        assert summary.keys() == full_summary.keys()
        for k, v in summary.items():
            assert v == pytest.approx(full_summary[k], rel=0, abs=1e-12), (label, k)
    assert full_summary["images"] == 7 and full_summary["images_without_valid_pixels"] == 1


def test_aggregate_accepts_numpy_and_extra_columns():
    per_image = {
        "mae": np.array([1.0, np.nan, 3.0]),
        "depth_error": np.array([2.0, 5.0, 4.0]),
        "valid_pixels": np.array([10, 0, 10]),
    }
    summary = aggregate(per_image)
    assert summary["mae"] == 2.0 and summary["depth_error"] == 3.0
    assert summary["images"] == 2 and summary["images_without_valid_pixels"] == 1
    with pytest.raises(ValueError):
        aggregate({"mae": np.ones(2), "mre": np.ones(3)})


def test_original_depth_error_constant_offset():
    g = torch.Generator().manual_seed(1)
    gt = torch.rand(3, 16, 24, generator=g) * 60 + 1
    pred_quarter = F.avg_pool2d(gt[:, None], 4) + 0.7
    err = original_depth_error(pred_quarter, gt)
    assert err.dtype == torch.float64 and err.shape == (3,)
    np.testing.assert_allclose(err.numpy(), 0.7, atol=1e-5)  # float32 inputs


def test_original_depth_error_uses_area_downsampling_after_clipping():
    # Each 4x4 block: 15 pixels at 4 m and its top-left pixel at 160 m (clipped to 100 m).
    # Area mean after clipping = (15·4 + 100)/16 = 10 m; without clipping (15·4 + 160)/16 = 13.75;
    # nearest sampling would give 100 or 4, bilinear (align_corners=False) 4.
    gt = torch.full((1, 8, 12), 4.0)
    gt[:, ::4, ::4] = 160.0
    assert original_depth_error(torch.full((1, 1, 2, 3), 10.0), gt).item() == pytest.approx(0.0)
    assert original_depth_error(torch.full((1, 1, 2, 3), 13.75), gt).item() == pytest.approx(3.75)
    # accepts (B, h, w) too
    assert original_depth_error(torch.full((1, 2, 3), 10.0), gt).item() == pytest.approx(0.0)


def test_upsample_to():
    pred = torch.arange(6.0).reshape(1, 1, 2, 3)
    up = upsample_to(pred, 8, 12)
    assert up.shape == (1, 8, 12) and up.dtype == pred.dtype
    assert torch.allclose(upsample_to(torch.full((2, 1, 4, 4), 7.0), 16, 16), torch.tensor(7.0))
    # align_corners=False: output pixel centre i maps to input (i + 0.5)/4 − 0.5 (clamped at the
    # border), so output (0, 2) samples input (y=0, x=0.125) -> 0.125 (align_corners=True: 4/11)
    assert up[0, 0, 2].item() == pytest.approx(0.125)
    assert up[0, 0, 0].item() == 0.0 and up[0, -1, -1].item() == 5.0
    with pytest.raises(ValueError):
        upsample_to(torch.ones(1, 4, 4), 8, 8)


def test_error_by_depth_band_is_each_bands_pixels_alone():
    """report.depth_bins: a band's MAE / MRE / MLE are those of its own pixels, worked by hand;
    invalid ground truth (0, NaN) and a ground truth at the far bound (100 m) are in no band."""
    from benchmark.engine.report import depth_bins, depth_table

    gt = np.array([2.0, 5.0, 20.0, 30.0, 80.0, 100.0, 0.0, np.nan], np.float32)
    pred = np.array([4.0, 5.0, 10.0, 60.0, 40.0, 1.0, 3.0, 3.0], np.float32)
    rows = {(r["from_m"], r["to_m"]): r for r in depth_bins(gt, pred)}
    assert list(rows) == list(DEPTH_BANDS)
    near = rows[(0.0, 10.0)]  # errors 2 and 0 m, relative 1 and 0, log ln 2 and 0
    assert near["pixels"] == 2 and near["mae"] == pytest.approx(1.0)
    assert near["mre"] == pytest.approx(0.5) and near["mle"] == pytest.approx(math.log(2) / 2)
    mid = rows[(10.0, 25.0)]
    assert (mid["pixels"], mid["mae"], mid["mre"]) == (1, pytest.approx(10.0), pytest.approx(0.5))
    assert rows[(25.0, 50.0)]["mle"] == pytest.approx(math.log(2))
    far = rows[(50.0, 100.0)]
    assert far["pixels"] == 1 and far["mae"] == pytest.approx(40.0)
    empty = depth_bins(np.array([5.0], np.float32), np.array([5.0], np.float32))[3]
    assert empty["pixels"] == 0 and empty["mae"] is None
    assert "| [50, 100) | 0 | – | – | – |" in depth_table([empty])
