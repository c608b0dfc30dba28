"""benchmark.plots: every figure is written as a readable, non-empty PNG."""

from __future__ import annotations

import matplotlib.image as mpimg
import numpy as np
import pytest

from benchmark import plots


def assert_png(path) -> None:
    assert path.exists() and path.stat().st_size > 0
    image = mpimg.imread(path)
    assert image.ndim == 3 and image.shape[0] > 50 and image.shape[1] > 50
    assert image.std() > 0  # not a blank canvas
    assert not list(path.parent.glob(".*.tmp"))  # temp file renamed away


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


def test_error_vs_depth(tmp_path, rng):
    gt = rng.uniform(0, 120, 2000)
    gt[:20] = np.nan
    err = np.abs(rng.normal(0, 1, 2000)) * gt / 10
    path = tmp_path / "depth.png"
    plots.error_vs_depth(gt, err, path, label="DepthNet")
    assert_png(path)


def test_error_vs_depth_sparse_bins(tmp_path):
    # fewer than 10 pixels in every bin: written anyway, with a "no bin" note
    path = tmp_path / "sub" / "sparse.png"
    plots.error_vs_depth(np.array([1.0, 50.0]), np.array([0.1, 2.0]), path)
    assert_png(path)


def test_error_vs_foe_distance(tmp_path, rng):
    d1 = rng.uniform(0, 90, 1500)
    d2 = np.concatenate([rng.uniform(0, 60, 1000), np.full(200, np.inf)])
    curves = {
        "DepthNet": (d1, rng.gamma(2.0, 1.0, d1.size)),
        "flow + T": (d2, rng.gamma(2.0, 1.0, d2.size) + 20 / (d2 + 1)),
    }
    path = tmp_path / "foe.png"
    plots.error_vs_foe_distance(curves, path, bins=15)
    assert_png(path)


def test_error_vs_foe_distance_only_lateral(tmp_path):
    path = tmp_path / "lateral.png"
    plots.error_vs_foe_distance({"m": (np.full(50, np.inf), np.ones(50))}, path)
    assert_png(path)


def test_error_vs_estimate(tmp_path, rng):
    gt = rng.uniform(0.5, 100, 2000)
    pred = gt * np.exp(rng.normal(0, 0.2, gt.size))
    pred[:10] = -3.0  # clamped to 0.1 m
    path = tmp_path / "estimate.png"
    plots.error_vs_estimate(pred.reshape(40, 50), gt.reshape(40, 50), path)
    assert_png(path)


def test_sample_grid(tmp_path, rng):
    samples = []
    for foe in [(10.0, 8.0), None, (100.0, -40.0)]:
        gt = rng.uniform(1, 100, (16, 24))
        gt[0, :3] = 0.0  # invalid pixels
        samples.append(
            {
                "img1": rng.integers(0, 256, (16, 24, 3), dtype=np.uint8),
                "img2": rng.integers(0, 256, (16, 24, 3), dtype=np.uint8),
                "gt": gt,
                "pred": gt + rng.normal(0, 5, gt.shape),
                "foe": foe,
            }
        )
    path = tmp_path / "samples.png"
    plots.sample_grid(samples, path)
    assert_png(path)
    with pytest.raises(ValueError):
        plots.sample_grid([], tmp_path / "none.png")
