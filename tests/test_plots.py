"""benchmark.engine.plots: the data each figure draws (read back from its axes), and the PNG
write."""

from __future__ import annotations

import numpy as np
import pytest

from benchmark.engine import plots


def curve(ax, i: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of the i-th line of ``ax``."""
    xy = ax.lines[i].get_xydata()
    return xy[:, 0], xy[:, 1]


def band(ax, i: int = 0) -> dict[float, tuple[float, float]]:
    """{x: (lowest, highest) y} of the i-th shaded band (quartiles) of ``ax``."""
    out: dict[float, tuple[float, float]] = {}
    for x, y in ax.collections[i].get_paths()[0].vertices:
        lo, hi = out.get(x, (y, y))
        out[float(x)] = (min(lo, y), max(hi, y))
    return out


def test_error_vs_depth_bins_medians_and_quartiles():
    """4 bins of 25 m: bin i holds 11 pixels with errors 10·i + 0…10 (median 10·i + 5,
    quartiles 10·i + 2.5 / 7.5); a bin with 9 pixels is not drawn; invalid ground truth is
    ignored and depth beyond 100 m counts as 100 m (last bin)."""
    gt, err = [], []
    for i, depth in ((0, 10.0), (1, 30.0), (3, 140.0)):  # 140 m: clipped into [75, 100]
        gt += [depth] * 11
        err += list(10.0 * i + np.arange(11.0))
    gt += [60.0] * 9 + [np.nan, 0.0, -1.0]  # too few for bin 2; three invalid pixels
    err += [99.0] * 9 + [1e6] * 3
    ax = plots.error_vs_depth_figure(np.array(gt), np.array(err), bins=4).axes[0]
    x, y = curve(ax)
    np.testing.assert_allclose(x, [12.5, 37.5, 87.5])
    np.testing.assert_allclose(y, [5.0, 15.0, 35.0])
    quartiles = band(ax)
    for centre, median in zip(x, y, strict=True):
        assert quartiles[centre] == pytest.approx((median - 2.5, median + 2.5))


def test_error_vs_depth_without_enough_pixels_draws_nothing():
    ax = plots.error_vs_depth_figure(np.array([1.0, 50.0]), np.array([0.1, 2.0])).axes[0]
    assert not ax.lines and "no bin" in ax.texts[0].get_text()


def test_error_vs_foe_distance_one_curve_per_method_on_shared_bins():
    """Lateral pairs (infinite distance) are left out; every method gets its own line and
    label; the first bin is [0, 0.5) px, the others log-spaced up to the largest distance."""
    near = np.concatenate([np.full(20, 0.25), np.full(20, 40.0)])
    curves = {
        "a": (near, np.concatenate([np.full(20, 9.0), np.full(20, 1.0)])),
        "b": (np.concatenate([near, np.full(50, np.inf)]), np.concatenate([near, np.ones(50)])),
    }
    ax = plots.error_vs_foe_distance_figure(curves, bins=5).axes[0]
    assert [line.get_label() for line in ax.lines] == ["a", "b"]
    x, y = curve(ax, 0)
    edges = np.concatenate([[0.0], np.geomspace(0.5, 40.0, 5)])
    np.testing.assert_allclose(x, [0.25, (edges[-2] + edges[-1]) / 2])
    np.testing.assert_allclose(y, [9.0, 1.0])
    np.testing.assert_allclose(curve(ax, 1)[1], [0.25, 40.0])  # b's error is its distance


def test_error_vs_estimate_uses_the_scoring_clamp():
    """Log error |log θ̃ − log θ| binned by the *clamped* estimate: −3 m counts as 0.1 m."""
    gt = np.full(30, 10.0)
    pred = np.concatenate([np.full(10, -3.0), np.full(10, 20.0), np.full(10, 200.0)])
    ax = plots.error_vs_estimate_figure(pred, gt, bins=4).axes[0]
    x, y = curve(ax)
    np.testing.assert_allclose(x, [12.5, 87.5])  # 0.1 and 20 m share the first bin; 200 -> 100
    np.testing.assert_allclose(y, [np.log(100) / 2 + np.log(2) / 2, np.log(10)])


def test_sample_grid_error_panel_follows_the_scoring_conventions():
    gt = np.array([[10.0, 150.0], [0.0, 50.0]])  # 0: invalid; 150 m scored as 100 m
    pred = np.array([[12.0, 90.0], [5.0, -1.0]])  # -1 m clamped to 0.1 m
    rgb = np.zeros((2, 2, 3), np.uint8)
    sample = {"img1": rgb, "img2": rgb, "gt": gt, "pred": pred, "foe": (0.0, 1.0)}
    fig = plots.sample_grid_figure([sample, {**sample, "foe": None}])
    axes = np.array(fig.axes[: 2 * 5]).reshape(-1)  # colour bars come after the panels
    error = np.ma.filled(axes[4].images[0].get_array().astype(float), np.nan)
    np.testing.assert_allclose(error, [[2.0, 10.0], [np.nan, 49.9]])
    assert [line.get_xydata().tolist() for line in axes[3].lines] == [[[0.0, 1.0]]]
    assert not axes[8].lines  # no FOE, no cross
    with pytest.raises(ValueError):
        plots.sample_grid_figure([])


@pytest.mark.parametrize(
    ("output", "column", "words"),
    [("depth", "val_mae", ("multi-scale L1", "MAE (m)")), ("flow", "val_epe", ("EPE", "EPE (px)"))],
)
def test_learning_curve_labels_and_data_follow_the_loss_and_score(output, column, words):
    rows = [
        {"step": "10", "train_loss": "4.0", "val_mae": "20.0", "val_epe": "2.0"},
        {"step": "20", "train_loss": "3.0", "val_mae": "18.0", "val_epe": "1.5"},
    ]
    ax = plots.learning_curve_figure(rows, output).axes[0]
    loss, score = (line.get_label() for line in ax.lines)
    assert words[0] in loss and words[1] in score
    assert curve(ax, 0)[1].tolist() == [4.0, 3.0]
    assert curve(ax, 1)[1].tolist() == [float(r[column]) for r in rows]


def test_png_is_written_atomically(tmp_path):
    path = tmp_path / "sub" / "depth.png"
    plots.error_vs_depth(np.full(20, 5.0), np.ones(20), path, label="DepthNet")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in path.parent.iterdir()] == ["depth.png"]  # no temporary left
