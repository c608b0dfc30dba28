"""Benchmark figures: binned error curves (thesis Figs. 3.11, 3.14, 6.1) and a sample grid.

Each ``<name>_figure`` function builds a figure (its axes hold the plotted data, which tests
read back) and ``<name>`` writes it as one PNG (runfolder.atomic_write_binary: a reader never sees
a half-written file). Figures are built with matplotlib's object API on the Agg canvas, never
through pyplot, so no global figure state is created or left open.

Binned curves: the x values are cut into ``bins`` equal-width bins; each bin with at least
:data:`MIN_BIN_COUNT` pixels shows the median of y (line) and the 25–75 % quartile band (shade),
computed with ``np.percentile``. Depths are in metres, distances in pixels.
"""

from __future__ import annotations

import os

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from stillbox_gen.conventions import MAX_DEPTH

from ..core.metrics import MIN_DEPTH
from ..core.models import FLOW_DIV
from ..core.runfolder import save_figure

MIN_BIN_COUNT = 10  # bins with fewer pixels are not drawn
QUARTILE_NOTE = "median, shaded 25–75 %"


def _binned_quartiles(
    x: np.ndarray, y: np.ndarray, edges: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bin centres and 25/50/75 % percentiles of ``y`` per bin of ``x`` (populated bins only).

    ``x`` outside ``[edges[0], edges[-1]]`` is ignored; the last bin includes its right edge.
    """
    inside = (x >= edges[0]) & (x <= edges[-1])
    x, y = x[inside], y[inside]
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    centres, q25, q50, q75 = [], [], [], []
    for i in range(len(edges) - 1):
        values = y[idx == i]
        if values.size < MIN_BIN_COUNT:
            continue
        lo, med, hi = np.percentile(values, [25, 50, 75])
        centres.append(0.5 * (edges[i] + edges[i + 1]))
        q25.append(lo)
        q50.append(med)
        q75.append(hi)
    return np.array(centres), np.array(q25), np.array(q50), np.array(q75)


def _draw_band(ax, x: np.ndarray, y: np.ndarray, edges: np.ndarray, label: str | None, color=None):
    """Median line + quartile band of ``y`` binned by ``x``; returns False if no bin was drawn."""
    centres, q25, q50, q75 = _binned_quartiles(x, y, edges)
    if centres.size == 0:
        return False
    (line,) = ax.plot(centres, q50, marker="o", markersize=3, label=label, color=color)
    ax.fill_between(centres, q25, q75, color=line.get_color(), alpha=0.25, linewidth=0)
    return True


def _no_data(ax) -> None:
    ax.text(
        0.5,
        0.5,
        f"no bin with ≥ {MIN_BIN_COUNT} pixels",
        transform=ax.transAxes,
        ha="center",
        va="center",
    )


def _flat(a: np.ndarray) -> np.ndarray:
    return np.asarray(a, dtype=np.float64).reshape(-1)


def error_vs_depth(gt: np.ndarray, abs_err: np.ndarray, path: str | os.PathLike, **kw) -> None:
    """:func:`error_vs_depth_figure` written to the PNG ``path``."""
    save_figure(error_vs_depth_figure(gt, abs_err, **kw), path)


def error_vs_depth_figure(
    gt: np.ndarray,
    abs_err: np.ndarray,
    bins: int = 20,
    max_depth: float = MAX_DEPTH,
    label: str | None = None,
) -> Figure:
    """Absolute error vs ground-truth depth (thesis Fig. 3.11).

    Args:
        gt: ground-truth depth per pixel, metres (any shape, flattened). Pixels that are not
            finite or ≤ 0 are ignored; depths above ``max_depth`` are clipped to it.
        abs_err: ``|pred − gt|`` per pixel, metres, same size as ``gt``.
        bins: number of equal-width depth bins over ``[0, max_depth]``.
        max_depth: metres.
        label: legend entry for the curve (no legend when None).
    """
    gt, err = _flat(gt), _flat(abs_err)
    if gt.shape != err.shape:
        raise ValueError(f"gt and abs_err sizes differ: {gt.size} vs {err.size}")
    keep = np.isfinite(gt) & (gt > 0) & np.isfinite(err)
    x = np.minimum(gt[keep], max_depth)
    fig = Figure(figsize=(6, 4))
    ax = fig.add_subplot()
    if not _draw_band(ax, x, err[keep], np.linspace(0.0, max_depth, bins + 1), label):
        _no_data(ax)
    ax.set_xlim(0, max_depth)
    ax.set_xlabel("ground-truth depth θ (m)")
    ax.set_ylabel("absolute error |θ̃ − θ| (m)")
    ax.set_title(f"Error vs ground-truth depth ({QUARTILE_NOTE})")
    ax.grid(alpha=0.3)
    if label is not None and ax.get_legend_handles_labels()[0]:
        ax.legend()
    fig.tight_layout()
    return fig


def error_vs_foe_distance(
    curves: dict[str, tuple[np.ndarray, np.ndarray]], path: str | os.PathLike, **kw
) -> None:
    """:func:`error_vs_foe_distance_figure` written to the PNG ``path``."""
    save_figure(error_vs_foe_distance_figure(curves, **kw), path)


def error_vs_foe_distance_figure(
    curves: dict[str, tuple[np.ndarray, np.ndarray]], bins: int = 20
) -> Figure:
    """Absolute error vs distance to the focus of expansion, several methods (thesis Fig. 3.14).

    Args:
        curves: ``{method name: (distance_px, abs_err)}``, per-pixel arrays (flattened) of the
            pixel distance to the FOE and ``|pred − gt|`` in metres. Infinite distances (lateral
            motion, FOE at infinity) and non-finite errors are ignored.
        bins: number of log-spaced distance bins from 0.5 px to the largest finite distance
            (plus one bin [0, 0.5) px), shared by all methods; the x axis is logarithmic above
            1 px, so the few pixels near the FOE are not squeezed against the axis by the
            thousands-of-pixels distances of nearly lateral motions.
    """
    data = {}
    for name, (dist, err) in curves.items():
        dist, err = _flat(dist), _flat(err)
        if dist.shape != err.shape:
            raise ValueError(f"{name}: distance and error sizes differ: {dist.size} vs {err.size}")
        keep = np.isfinite(dist) & np.isfinite(err)
        data[name] = (dist[keep], err[keep])
    finite_max = [d.max() for d, _ in data.values() if d.size]
    hi = max(max(finite_max) if finite_max else 1.0, 1.0)
    edges = np.concatenate([[0.0], np.geomspace(0.5, hi, bins)])

    fig = Figure(figsize=(6, 4))
    ax = fig.add_subplot()
    drawn = [_draw_band(ax, d, e, edges, name) for name, (d, e) in data.items()]
    if not any(drawn):
        _no_data(ax)
    else:
        ax.legend()
    ax.set_xscale("symlog", linthresh=1.0)
    ax.set_xlim(0, hi)
    ax.set_xlabel("distance to the focus of expansion (px, log scale above 1)")
    ax.set_ylabel("absolute error |θ̃ − θ| (m)")
    ax.set_title(f"Error vs distance to FOE ({QUARTILE_NOTE})")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def error_vs_estimate(pred: np.ndarray, gt: np.ndarray, path: str | os.PathLike, **kw) -> None:
    """:func:`error_vs_estimate_figure` written to the PNG ``path``."""
    save_figure(error_vs_estimate_figure(pred, gt, **kw), path)


def error_vs_estimate_figure(
    pred: np.ndarray, gt: np.ndarray, bins: int = 20, max_depth: float = MAX_DEPTH
) -> Figure:
    """Log error vs estimated depth (thesis Fig. 6.1).

    Uses the scoring conventions of :mod:`benchmark.core.metrics`: predictions clamped to
    ``[MIN_DEPTH, max_depth]``, ground truth clipped to ``max_depth``, pixels whose ground truth is
    not finite or ≤ 0 ignored.

    Args:
        pred: predicted depth per pixel, metres (any shape, flattened).
        gt: ground-truth depth per pixel, metres, same size.
        bins: number of equal-width bins of the estimate over ``[0, max_depth]``.
        max_depth: metres.
    """
    pred, gt = _flat(pred), _flat(gt)
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt sizes differ: {pred.size} vs {gt.size}")
    keep = np.isfinite(gt) & (gt > 0) & ~np.isnan(pred)
    p = np.clip(pred[keep], MIN_DEPTH, max_depth)
    g = np.minimum(gt[keep], max_depth)
    log_err = np.abs(np.log(p) - np.log(g))
    fig = Figure(figsize=(6, 4))
    ax = fig.add_subplot()
    if not _draw_band(ax, p, log_err, np.linspace(0.0, max_depth, bins + 1), None):
        _no_data(ax)
    ax.set_xlim(0, max_depth)
    ax.set_xlabel("estimated depth θ̃ (m)")
    ax.set_ylabel("log error |log θ̃ − log θ|")
    ax.set_title(f"Error vs estimated depth ({QUARTILE_NOTE})")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def _mark_foe(ax, foe: tuple[float, float] | None, height: int, width: int) -> None:
    """Cross at the FOE if it lies inside the image (pixel centres at integer coordinates)."""
    if foe is None:
        return
    x, y = foe
    if -0.5 <= x <= width - 0.5 and -0.5 <= y <= height - 0.5:
        xlim, ylim = ax.get_xlim(), ax.get_ylim()
        ax.plot([x], [y], marker="+", markersize=12, markeredgewidth=2, color="cyan")
        ax.set_xlim(xlim)
        ax.set_ylim(ylim)


def sample_grid(samples: list[dict], path: str | os.PathLike, **kw) -> None:
    """:func:`sample_grid_figure` written to the PNG ``path``."""
    save_figure(sample_grid_figure(samples, **kw), path)


def sample_grid_figure(samples: list[dict], max_depth: float = MAX_DEPTH) -> Figure:
    """Qualitative grid: one row per sample.

    Columns: frame 1, frame 2, ground truth and prediction (shared ``magma_r`` scale over
    ``[0, max_depth]`` m, with a colour bar), absolute error (own colour bar, metres; invalid
    ground-truth pixels shown grey). The FOE is marked with a cyan cross on the prediction and
    error panels when it lies inside the image.

    Args:
        samples: dicts with ``"img1"``, ``"img2"``: ``(H, W, 3)`` uint8 RGB; ``"gt"``, ``"pred"``:
            ``(H, W)`` depth in metres; ``"foe"``: ``(x, y)`` pixels (pixel-centre convention) or
            None. The error uses the scoring conventions of :mod:`benchmark.core.metrics`.
        max_depth: metres, top of the depth colour scale.
    """
    if not samples:
        raise ValueError("sample_grid needs at least one sample")
    depth_cmap = matplotlib.colormaps["magma_r"].with_extremes(bad="0.6")
    err_cmap = matplotlib.colormaps["viridis"].with_extremes(bad="0.6")
    titles = ("frame 1", "frame 2", "ground truth (m)", "prediction (m)", "|θ̃ − θ| (m)")
    fig = Figure(figsize=(5 * 2.8, 2.5 * len(samples)))
    axes = fig.subplots(len(samples), 5, squeeze=False)
    for row, sample in enumerate(samples):
        gt = np.asarray(sample["gt"], dtype=np.float64)
        pred = np.asarray(sample["pred"], dtype=np.float64)
        if gt.ndim != 2 or pred.shape != gt.shape:
            raise ValueError(f"sample {row}: gt and pred must be (H, W) of the same shape")
        height, width = gt.shape
        valid = np.isfinite(gt) & (gt > 0)
        err = np.abs(np.clip(pred, MIN_DEPTH, max_depth) - np.minimum(gt, max_depth))
        err = np.where(valid, err, np.nan)
        vmax_err = float(np.nanmax(err)) if valid.any() and np.nanmax(err) > 0 else 1.0

        ax = axes[row]
        ax[0].imshow(np.asarray(sample["img1"]))
        ax[1].imshow(np.asarray(sample["img2"]))
        ax[2].imshow(np.where(valid, gt, np.nan), cmap=depth_cmap, vmin=0, vmax=max_depth)
        im = ax[3].imshow(pred, cmap=depth_cmap, vmin=0, vmax=max_depth)
        fig.colorbar(im, ax=ax[3], fraction=0.046, pad=0.04)
        im = ax[4].imshow(err, cmap=err_cmap, vmin=0, vmax=vmax_err)
        fig.colorbar(im, ax=ax[4], fraction=0.046, pad=0.04)
        for a in (ax[3], ax[4]):
            _mark_foe(a, sample.get("foe"), height, width)
        for col, a in enumerate(ax):
            a.set_xticks([])
            a.set_yticks([])
            if row == 0:
                a.set_title(titles[col], fontsize=10)
    fig.suptitle("Samples (cyan cross: focus of expansion)")
    fig.tight_layout()
    return fig


#: learning-curve series per method output: (metrics.csv column, label); train loss first
LEARNING_CURVES = {
    "depth": (("train_loss", "train loss (multi-scale L1)"), ("val_mae", "validation MAE (m)")),
    "flow": (
        ("train_loss", f"train loss (multi-scale EPE on flow / {FLOW_DIV:g})"),
        ("val_epe", "validation EPE (px)"),
    ),
    "unsupervised-depth": (
        ("train_loss", "train loss (photometric + smooth, eq. 5.5)"),
        ("val_mae", "validation MAE (m)"),
    ),
    "scale-free-depth": (
        ("train_loss", "train loss (photometric + smooth, eq. 5.5)"),
        ("val_mae", "validation MAE, PoseNet's scale (m)"),
    ),
}


def learning_curve(rows: list[dict], output: str, path: str | os.PathLike) -> None:
    """:func:`learning_curve_figure` written to the PNG ``path`` (6 × 3.5 in, 110 dpi)."""
    save_figure(learning_curve_figure(rows, output), path, dpi=110)


def learning_curve_figure(rows: list[dict], output: str) -> Figure:
    """Training loss and validation score vs optimiser step, log scale.

    Args:
        rows: metrics.csv rows (``step`` and the columns of :data:`LEARNING_CURVES`; values
            as strings or numbers).
        output: the method's output, "depth" (loss: multi-scale L1; score: MAE in metres) or
            "flow" (loss: multi-scale EPE on flow / 20; score: EPE in pixels, what its best
            checkpoint is chosen by).
    """
    step = [float(r["step"]) for r in rows]
    fig = Figure(figsize=(6, 3.5))
    ax = fig.add_subplot()
    for (column, label), style in zip(LEARNING_CURVES[output], ("o-", "s-"), strict=True):
        ax.plot(step, [float(r[column]) for r in rows], style, label=label)
    ax.set_xlabel("optimiser step")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return fig
