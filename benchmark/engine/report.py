"""Run reports: the content of summary.json / summary.md, the figures of a run, and comparison
tables across runs. Files are written by benchmark.core.runfolder (docs/RUNS.md)."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from stillbox_gen.conventions import MAX_DEPTH, NOMINAL_SHIFT

from ..core import flow, metrics, registry, runfolder, thesis
from ..core.registry import Scoring
from ..core.runfolder import plot_path
from . import plots
from .evaluate import EvalResult

#: summary and comparison columns: every measure of core.metrics, then the public code's
#: "depth error" and flow methods' end-point error and outlier rates
FLOW_COLUMNS = ("epe", "fl_all", *(f"out{t}" for t in flow.OUTLIER_PIXELS))
COLUMNS = (*metrics.METRICS, "depth_error", *FLOW_COLUMNS)
HEADERS = (
    *(metrics.header(m) for m in metrics.METRICS),
    "depth error (m)",
    "EPE (px)",
    "Fl-all",
    *(f"> {t} px" for t in flow.OUTLIER_PIXELS),
)
THESIS_64 = thesis.TABLE_3_4_64PX  # beside each run's scores in summary.md
DEPTH_ERROR_FORMULA = (
    "original DepthNet 'depth error': mean |θ̃_1/4 − area_downsample(min(θ, "
    f"{MAX_DEPTH:g}))| at 1/4 resolution, per image, then averaged like the other metrics "
    "(methods without a 1/4 depth output: their full-resolution depth area-downsampled by 4)"
)
EPE_FORMULA = (
    "EPE = E‖F̃ − F‖₂ (pixels) at full resolution (the 1/4 flow upsampled bilinearly) against the "
    "exact flow of the second frame's pixels towards the first frame (flow_ground_truth), over "
    "its valid pixels; per image, then averaged like the other metrics"
)
#: summary.json's "flow_ground_truth" of a flow method, by EvalResult.flow_truth
FLOW_TRUTH = {
    "stored": "the dataset's stored flow (stillbox-gen --flow: from depth and full poses), on "
    "its valid pixels (landing inside the first frame; occluded pixels included)",
    "computed": "the flow computed from the second frame's depth and the pair's translation "
    "(benchmark.core.flow.flow_from_depth; a stabilised camera), on pixels whose point is in "
    "front of both cameras",
}
_CLAMP = f"[{metrics.MIN_DEPTH:g}, {MAX_DEPTH:g}]"
#: summary.json's "scale": how each way of scoring (registry.Scoring) turns outputs into metres
SCALE_RULES = {
    Scoring.DEPTH: "prediction × |pair translation| / nominal displacement (known displacement; "
    "never the ground-truth median)",
    Scoring.FLOW: "depth from the predicted flow and the pair's known translation (FOE "
    f"geometry, benchmark.core.flow), clamped to {_CLAMP} m; every pixel scored, the FOE's "
    "included",
    Scoring.EXACT_FLOW: "depth from the exact flow and the pair's known translation (FOE "
    f"geometry), clamped to {_CLAMP} m; every pixel scored",
    Scoring.CONSTANT: "one depth everywhere: the training split's median depth (no scale needed)",
    Scoring.SCALE_FREE: "depth up to a scale: P (the metrics) = prediction × |pair translation| "
    "/ |PoseNet's translation between the pair's frames| (no ground truth); GT (the metrics "
    "prefixed gt_) = prediction × median(ground truth) / median(prediction) per image "
    "(benchmark.engine.scaling)",
    Scoring.GIVEN: "the prediction files' depth (metres), as given: no scaling",
}
#: what summary.json's "scale" adds when eval ran with --median-scaling
MEDIAN_SCALING_RULE = (
    "; then × median(ground truth) / median(prediction) per image over its valid pixels "
    "(median scaling: the scale is taken from the ground truth)"
)
FOE_BIN_EDGES = (0.0, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, np.inf)  # pixels


def foe_bins(distance: np.ndarray, abs_err: np.ndarray) -> list[dict]:
    """Error by distance to the FOE (pixels), over the scored pixel subsample: per bin
    ``[lo, hi)`` the pixel count, mean and median absolute error (m). Pixels with the FOE at
    infinity (lateral motion) are left out."""
    rows = []
    for lo, hi in zip(FOE_BIN_EDGES[:-1], FOE_BIN_EDGES[1:], strict=True):
        sel = (distance >= lo) & (distance < hi) & np.isfinite(abs_err)
        n = int(sel.sum())
        rows.append(
            {
                "from_px": lo,
                "to_px": None if np.isinf(hi) else hi,
                "pixels": n,
                "mae": float(abs_err[sel].mean()) if n else None,
                "median_abs_err": float(np.median(abs_err[sel])) if n else None,
            }
        )
    return rows


def depth_bins(gt: np.ndarray, pred: np.ndarray) -> list[dict]:
    """Error by ground-truth depth (metres), over the scored pixel subsample: per band
    ``[lo, hi)`` of metrics.DEPTH_BANDS the pixel count, MAE (m), MRE and MLE (per pixel, not
    per image: a band holds few pixels of most images)."""
    rows = []
    for lo, hi in metrics.DEPTH_BANDS:
        sel = (gt > 0) & (gt >= lo) & (gt < hi) & np.isfinite(pred)  # valid ground truth
        g, p = gt[sel].astype(np.float64), pred[sel].astype(np.float64)
        n = int(sel.sum())
        rows.append(
            {
                "from_m": lo,
                "to_m": hi,
                "pixels": n,
                "mae": float(np.abs(p - g).mean()) if n else None,
                "mre": float((np.abs(p - g) / g).mean()) if n else None,
                "mle": float(np.abs(np.log(p) - np.log(g)).mean()) if n else None,
            }
        )
    return rows


def depth_table(rows: list[dict]) -> str:
    lines = ["| ground-truth depth (m) | pixels | MAE (m) | MRE | MLE |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| [{r['from_m']:g}, {r['to_m']:g}) | {r['pixels']} | {_fmt(r['mae'])} | "
            f"{_fmt(r['mre'])} | {_fmt(r['mle'])} |"
        )
    return "\n".join(lines)


def foe_table(rows: list[dict]) -> str:
    lines = [
        "| distance to FOE (px) | pixels | MAE (m) | median abs. error (m) |",
        "|---|---|---|---|",
    ]
    for r in rows:
        hi = "∞" if r["to_px"] is None else f"{r['to_px']:g}"
        lines.append(
            f"| [{r['from_px']:g}, {hi}) | {r['pixels']} | {_fmt(r['mae'])} | "
            f"{_fmt(r['median_abs_err'])} |"
        )
    return "\n".join(lines)


def _fmt(v) -> str:
    if isinstance(v, float) and 0 < abs(v) < 1e-3:
        return f"{v:.2e}"
    return "–" if v is None else f"{v:.3f}" if isinstance(v, float) else str(v)


def scale_rows(name: str, m: dict) -> list[tuple[str, dict]]:
    """``[(name, m)]``, or for a scale-free depth's metrics (``gt_`` keys: sfmlearner) one row
    per scale: "P" (``m``) and "GT" (its ``gt_`` metrics)."""
    if "gt_mae" not in m:
        return [(name, m)]
    gt = {k.removeprefix("gt_"): v for k, v in m.items() if k.startswith("gt_")}
    return [(f"{name}, P", m), (f"{name}, GT", gt)]


def markdown_table(rows: list[tuple[str, dict]]) -> str:
    lines = ["| method | " + " | ".join(HEADERS) + " |", "|---" * (len(HEADERS) + 1) + "|"]
    for name, m in rows:
        lines.append(f"| {name} | " + " | ".join(_fmt(m.get(c)) for c in COLUMNS) + " |")
    return "\n".join(lines)


def write_plots(run: Path, model: str, result: EvalResult) -> None:
    """The run's figures (runfolder.PLOTS): error vs depth, vs FOE distance, vs estimate, the
    sample grid, and the learning curve when the run was trained (it has metrics.csv rows)."""
    px = result.pixels
    if px:
        plots.error_vs_depth(px["gt"], px["abs_err"], plot_path(run, "error_vs_depth"))
        curves = {model: (px["foe_distance"], px["abs_err"])}
        plots.error_vs_foe_distance(curves, plot_path(run, "error_vs_foe_distance"))
        plots.error_vs_estimate(px["pred"], px["gt"], plot_path(run, "error_vs_estimate"))
    if result.samples:
        plots.sample_grid(result.samples, plot_path(run, "samples"))
    rows = runfolder.read_rows(run, runfolder.METRICS_CSV)
    if rows:
        plots.learning_curve(rows, _kind(model).name, plot_path(run, "learning_curve"))


def _kind(model: str) -> registry.Kind:
    """The registered method's kind (a depth network for a name the registry does not know)."""
    return registry.MODELS[model].kind if model in registry.MODELS else registry.DEPTH


def summarize(
    model: str, result: EvalResult, info: dict, kind: registry.Kind | None = None
) -> dict:
    """summary.json's content: model, output, ``info`` (dataset, split, timing…), metrics, every
    formula, the averaging and scale rules, the error by FOE distance, the thesis' numbers.
    ``kind``: the method's (default: the registered ``model``'s, else a depth network's); an
    ``info["median_scaling"]`` that is true is added to the scale rule."""
    kind = kind or _kind(model)
    scale = SCALE_RULES[kind.scored_as]
    if info.get("median_scaling"):
        scale += MEDIAN_SCALING_RULE
    px = result.pixels
    formulas = {**metrics.FORMULAS, "depth_error": DEPTH_ERROR_FORMULA}
    if "epe" in result.summary:
        formulas.update(epe=EPE_FORMULA, **flow.FLOW_FORMULAS)
    if result.flow_truth:
        info = {
            **info,
            "flow_ground_truth": "; ".join(FLOW_TRUTH[t] for t in result.flow_truth.split(", ")),
        }
    return {
        "model": model,
        "output": kind.name,
        **info,
        "metrics": result.summary,
        "formulas": formulas,
        "averaging_rule": metrics.AVERAGING_RULE,
        "scale": scale,
        "error_by_foe_distance": foe_bins(px["foe_distance"], px["abs_err"]) if px else [],
        "error_by_depth": depth_bins(px["gt"], px["pred"]) if px else [],
        "thesis_reference_64px": THESIS_64.get(model.removesuffix("-tiny")),
    }


def summary_markdown(summary: dict) -> str:
    """summary.md: the scores beside the thesis' (thesis-style table), the scale rule and the
    error by distance to the focus of expansion, from a :func:`summarize` dict."""
    model, m = summary["model"], summary["metrics"]
    rows = scale_rows(f"{model} (this run)", m)
    ref = summary["thesis_reference_64px"]
    if ref:
        rows.append((f"{model.removesuffix('-tiny')} 64 px, thesis", ref))
    md = [
        f"# {model} on {summary.get('dataset')}",
        "",
        f"Split `{summary.get('split')}`: {m.get('images')} pairs (i, i+"
        f"{summary.get('shift', NOMINAL_SHIFT)}), {summary.get('scenes')} scenes. "
        f"{metrics.AVERAGING_RULE}",
        "",
        markdown_table(rows),
        "",
        f"Depth: {summary['scale']}.",
        "",
        *(
            [f"Flow (EPE, Fl-all) against {summary['flow_ground_truth']}.", ""]
            if summary.get("flow_ground_truth")
            else []
        ),
        "Error by distance to the focus of expansion (pixel subsample of `pixels.npz`; lateral "
        "pairs, FOE at infinity, left out):",
        "",
        foe_table(summary["error_by_foe_distance"]),
        "",
        *(
            [
                "Error by ground-truth depth (the same pixels, per pixel):",
                "",
                depth_table(summary["error_by_depth"]),
                "",
            ]
            if summary.get("error_by_depth")
            else []
        ),
        "Plots: `plots/` (error vs depth, vs distance to the focus of expansion, vs estimate, "
        "samples, learning curve). Per-pair metrics: `per_sample.csv`.",
    ]
    return "\n".join(md) + "\n"


def sensitivity_markdown(noise_px: float, noisy: dict, bins: list[dict]) -> str:
    """The section oracle-flow's summary.md ends with: its scores with ``noise_px`` of Gaussian
    flow noise (``noisy``: metrics) and their error by FOE distance (``bins``)."""
    text = [
        "",
        f"## Sensitivity: exact flow + N(0, {noise_px:g} px) noise per component",
        "",
        f"MAE {noisy['mae']:.3f} m, MRE {noisy['mre']:.3f}, MLE {noisy['mle']:.3f}. Error by "
        "distance to the FOE (the ill-conditioning near the FOE, thesis 3.1.5):",
        "",
        foe_table(bins),
    ]
    return "\n".join(text) + "\n"


def compare_figure(runs: list[Path], path: Path) -> bool:
    """Error vs distance to the FOE with every run that has ``pixels.npz`` on one figure
    (thesis Fig. 3.14); False (nothing written) when none has."""
    curves = {}
    for run in runs:
        px = runfolder.read_pixels(run)
        if px is not None:
            missing = {"foe_distance", "abs_err"} - set(px)
            if missing:
                raise ValueError(f"{run / runfolder.PIXELS_NPZ}: no '{min(missing)}' array")
            model = runfolder.read_summary(run)["model"]
            label = model if model not in curves else f"{model} ({run.name})"
            curves[label] = (px["foe_distance"], px["abs_err"])
    if curves:
        runfolder.make_folder(path.parent)
        plots.error_vs_foe_distance(curves, path)
    return bool(curves)


def compare_runs(runs: list[Path]) -> tuple[str, str]:
    """(markdown, csv) table of the summary.json of several runs."""
    rows = []
    for run in runs:
        s = runfolder.read_summary(run)
        rows += scale_rows(f"{s['model']} ({run.name})", s["metrics"])
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["run", *COLUMNS])
    for name, m in rows:
        w.writerow([name, *(m.get(c) for c in COLUMNS)])
    return markdown_table(rows), buf.getvalue()


def write_comparison(runs: list[Path], out: Path) -> str:
    """OUT.md, OUT.csv and OUT-error_vs_foe_distance.png of several runs; returns the table."""
    md, csv_text = compare_runs(runs)
    figure = runfolder.comparison_paths(out)["figure"]
    text = md
    if compare_figure(runs, figure):
        text += f"\n\nError vs distance to the focus of expansion, every method: `{figure.name}`"
    runfolder.write_comparison(out, text + "\n", csv_text)
    return md
