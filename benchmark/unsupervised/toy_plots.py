"""Figures of the toy-problem study (:mod:`benchmark.toy`; thesis Figs. 4.13-4.18).

- :func:`heatmaps`: M and each scene's LE over the (λ, κ) grid, one column per smooth loss
  (Figs. 4.14 and 4.15 in one figure, one figure per ODM setting);
- :func:`panels`: for each run given, the final depth, its log error against the truth and the
  two references warped to the centre frame with it, pixels dropped from the photometric loss
  in black (Figs. 4.13, 4.16-4.18);
- :func:`le_curves`: LE against iterations at each loss's optimum (what §4.6.2 reads off Fig.
  4.17: diffusion worsens after a minimum, gradient diffusion keeps improving).

Written with benchmark.plots' saver (Agg canvas, atomic PNG writes, no pyplot state).
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from stillbox_gen.conventions import MAX_DEPTH

from ..core.metrics import MIN_DEPTH
from ..core.runfolder import save_figure
from .toy import SCENES, BestRun, ToyScene, run_key, scene_warps

#: Colour scale of the depth panels (metres, log) and of the log-error panels.
DEPTH_RANGE = (1.0, MAX_DEPTH)
LOG_ERROR_MAX = 1.0
#: Resolution of the panel figures (200 px frames drawn at about their own size).
PANEL_DPI = 60


def heatmaps_figure(results: dict, odm: bool) -> Figure:
    """Rows M, LE (Horizon), LE (Flower); one column per smooth loss run with ``odm``; λ on the
    vertical axis, κ on the horizontal one; the optimum of M marked with a cross."""
    keys = [k for k in results["runs"] if k.endswith(run_key("", odm))]
    lambdas, kappas = results["lambdas"], results["kappas"]
    rows = [("M", None)] + [(f"LE ({n})", n) for n in SCENES]
    fig = Figure(figsize=(2.6 * max(1, len(keys)), 2.4 * len(rows)), layout="constrained")
    axes = fig.subplots(len(rows), max(1, len(keys)), squeeze=False)
    for c, key in enumerate(keys):
        block = results["runs"][key]
        bi, bj = divmod(block["best"]["index"], len(kappas))
        for r, (label, scene) in enumerate(rows):
            ax = axes[r, c]
            values = np.array(block["m"] if scene is None else block["le"][scene])
            vmax = 1.0 if scene is None else max(1e-6, 1.5 * results["le0"][scene])
            im = ax.imshow(values, origin="lower", cmap="viridis" if scene is None else "magma_r",
                           vmin=0, vmax=vmax, aspect="auto")  # fmt: skip
            ax.plot(bj, bi, "x", color="red")
            ax.set_xticks(range(len(kappas)), [f"{k:g}" for k in kappas], fontsize=7)
            ax.set_yticks(range(len(lambdas)), [f"{v:g}" for v in lambdas], fontsize=7)
            ax.set_xlabel("κ", fontsize=8)
            ax.set_ylabel("λ", fontsize=8)
            ax.set_title(f"{key.split('/')[0]}: {label}", fontsize=8)
            fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(f"M and LE over (λ, κ), ODM {'on' if odm else 'off'} (thesis Figs. 4.14-4.15)")
    return fig


def heatmaps(results: dict, odm: bool, path: str | os.PathLike) -> None:
    """:func:`heatmaps_figure` written to ``path``."""
    save_figure(heatmaps_figure(results, odm), path)


def panels_figure(scene: ToyScene, runs: Sequence[BestRun], title: str) -> Figure:
    """One row per run: depth (log scale, metres), |log θ − log θ̃| (0 to LOG_ERROR_MAX, grey
    where the truth is not scored), and the warps of t-1 and t+1 (black: dropped pixels)."""
    fig = Figure(figsize=(10, 2.5 * (len(runs) + 1)), layout="constrained")
    axes = fig.subplots(len(runs) + 1, 4, squeeze=False)
    truth = scene.depth[0, 0].clamp(MIN_DEPTH, MAX_DEPTH).numpy()
    axes[0, 0].imshow(truth, cmap="magma_r", norm=LogNorm(*DEPTH_RANGE))
    axes[0, 0].set_title("true depth (m, log)", fontsize=8)
    for frame in (0, 1, 2):
        axes[0, frame + 1].imshow(scene.frames[frame].permute(1, 2, 0).numpy())
        axes[0, frame + 1].set_title(f"frame {('t-1', 't', 't+1')[frame]}", fontsize=8)
    for r, run in enumerate(runs, start=1):
        depth = run.depth[scene.name]
        d = depth[0, 0].numpy()
        err = np.abs(np.log(d) - np.log(truth))
        err = np.where(scene.valid[0, 0].numpy(), err, np.nan)
        axes[r, 0].imshow(d, cmap="magma_r", norm=LogNorm(*DEPTH_RANGE))
        axes[r, 0].set_title(f"{run.label}: depth", fontsize=8)
        axes[r, 1].imshow(err, cmap="inferno", vmin=0, vmax=LOG_ERROR_MAX)
        axes[r, 1].set_title(f"log error (mean {np.nanmean(err):.3f})", fontsize=8)
        for i, (warped, kept) in enumerate(scene_warps(scene, depth, run.occluded[scene.name])):
            image = (warped[0] * kept[0]).permute(1, 2, 0).clamp(0, 1).numpy()
            axes[r, 2 + i].imshow(image)
            axes[r, 2 + i].set_title(f"{('t-1', 't+1')[i]} warped to t", fontsize=8)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(title)
    return fig


def panels(scene: ToyScene, runs: Sequence[BestRun], title: str, path: str | os.PathLike) -> None:
    """:func:`panels_figure` written to ``path``."""
    save_figure(panels_figure(scene, runs, title), path, dpi=PANEL_DPI)


def le_curves_figure(runs: Sequence[BestRun], le0: dict[str, float]) -> Figure:
    """LE against iterations at each run's optimum, one panel per scene (dashed: LE_0)."""
    fig = Figure(figsize=(11, 4), layout="constrained")
    axes = fig.subplots(1, len(SCENES), squeeze=False)[0]
    for ax, name in zip(axes, SCENES, strict=True):
        for run in runs:
            style = "-" if run.label.endswith("odm-on") else "--"
            ax.plot(run.history_iterations, run.history[name], style, label=run.label)
        ax.axhline(le0[name], color="grey", linestyle=":", label="LE_0")
        ax.set_xlabel("iteration")
        ax.set_ylabel("LE")
        ax.set_title(name)
    axes[-1].legend(fontsize=6)
    return fig


def le_curves(runs: Sequence[BestRun], le0: dict[str, float], path: str | os.PathLike) -> None:
    """:func:`le_curves_figure` written to ``path``."""
    save_figure(le_curves_figure(runs, le0), path)
