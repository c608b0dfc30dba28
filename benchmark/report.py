"""Run reports: summary.json / summary.md, plots, and comparison tables across runs."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from stillbox_gen.dataset import MAX_DEPTH, NOMINAL_SHIFT  # noqa: E402

from . import metrics, plots, registry  # noqa: E402
from .evaluate import EvalResult  # noqa: E402

COLUMNS = ("mae", "mre", "mle", "sae", "sle", "p1.25", "p1.25^2", "p1.25^3", "depth_error", "epe")
HEADERS = (
    "MAE (m)",
    "MRE",
    "MLE",
    "SAE (m)",
    "SLE",
    "P1.25",
    "P1.25²",
    "P1.25³",
    "depth error (m)",
    "EPE (px)",
)
# Thesis Tables 3.4 / 3.5 (StillBox validation set, 64 px) and the public code's depth error.
THESIS_64 = {
    "depthnet": {"mae": 4.72, "mre": 0.26, "mle": 0.32, "depth_error": 4.65},
    "flownets-depth": {"mae": 5.72, "mre": 0.363, "mle": 0.276},
    "flownets-flow": {"mae": 6.462, "mre": 0.203, "mle": 0.172},  # FlowNetS -> depth
}
DEPTH_ERROR_FORMULA = (
    "original DepthNet 'depth error': mean |θ̃_1/4 − area_downsample(min(θ, "
    f"{MAX_DEPTH:g}))| at 1/4 resolution, per image, then averaged like the other metrics "
    "(methods without a 1/4 depth output: their full-resolution depth area-downsampled by 4)"
)
EPE_FORMULA = (
    "EPE = E‖F̃ − F‖₂ (pixels) at full resolution (the 1/4 flow upsampled bilinearly) against the "
    "exact flow of the second frame's pixels towards the first frame, over pixels whose point is "
    "in front of both cameras; per image, then averaged like the other metrics"
)
_CLAMP = f"[{metrics.MIN_DEPTH:g}, {MAX_DEPTH:g}]"
SCALE_RULES = {
    "depth": "prediction × |pair translation| / nominal displacement (known displacement; never "
    "the ground-truth median)",
    "flow": "depth from the predicted flow and the pair's known translation (FOE geometry, "
    f"benchmark.flow), clamped to {_CLAMP} m; every pixel scored, the FOE's included",
    "oracle-flow": "depth from the exact flow and the pair's known translation (FOE geometry), "
    f"clamped to {_CLAMP} m; every pixel scored",
    "constant": "one depth everywhere: the training split's median depth (no scale needed)",
}
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


def markdown_table(rows: list[tuple[str, dict]]) -> str:
    lines = ["| method | " + " | ".join(HEADERS) + " |", "|---" * (len(HEADERS) + 1) + "|"]
    for name, m in rows:
        lines.append(f"| {name} | " + " | ".join(_fmt(m.get(c)) for c in COLUMNS) + " |")
    return "\n".join(lines)


def learning_curve(metrics_csv: Path, path: Path) -> None:
    with open(metrics_csv, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return
    step = [float(r["step"]) for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(step, [float(r["train_loss"]) for r in rows], "o-", label="train loss (multi-scale L1)")
    ax.plot(step, [float(r["val_mae"]) for r in rows], "s-", label="validation MAE (m)")
    ax.set_xlabel("optimiser step")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_run_report(run: Path, model: str, result: EvalResult, info: dict) -> dict:
    """summary.json, summary.md, per_sample.csv and plots/ for one evaluated model."""
    plot_dir = run / "plots"
    plot_dir.mkdir(parents=True, exist_ok=True)
    with open(run / "per_sample.csv", "w", newline="") as f:
        if result.per_sample:
            w = csv.DictWriter(f, fieldnames=list(result.per_sample[0]))
            w.writeheader()
            w.writerows(result.per_sample)
    px = result.pixels
    if px:
        np.savez_compressed(run / "pixels.npz", **px)
        plots.error_vs_depth(px["gt"], px["abs_err"], plot_dir / "error_vs_depth.png")
        plots.error_vs_foe_distance(
            {model: (px["foe_distance"], px["abs_err"])}, plot_dir / "error_vs_foe_distance.png"
        )
        plots.error_vs_estimate(px["pred"], px["gt"], plot_dir / "error_vs_estimate.png")
    if result.samples:
        plots.sample_grid(result.samples, plot_dir / "samples.png")
    if (run / "metrics.csv").exists():
        learning_curve(run / "metrics.csv", plot_dir / "learning_curve.png")
    output = registry.MODELS[model].output if model in registry.MODELS else "depth"
    bins = foe_bins(px["foe_distance"], px["abs_err"]) if px else []
    formulas = {**metrics.FORMULAS, "depth_error": DEPTH_ERROR_FORMULA}
    if "epe" in result.summary:
        formulas["epe"] = EPE_FORMULA
    summary = {
        "model": model,
        "output": output,
        **info,
        "metrics": result.summary,
        "formulas": formulas,
        "averaging_rule": metrics.AVERAGING_RULE,
        "scale": SCALE_RULES[output],
        "error_by_foe_distance": bins,
        "thesis_reference_64px": THESIS_64.get(model.removesuffix("-tiny")),
    }
    (run / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    rows = [(f"{model} (this run)", result.summary)]
    ref = THESIS_64.get(model.removesuffix("-tiny"))
    if ref:
        rows.append((f"{model.removesuffix('-tiny')} 64 px, thesis", ref))
    md = [
        f"# {model} on {info.get('dataset')}",
        "",
        f"Split `{info.get('split')}`: {result.summary.get('images')} pairs (i, i+"
        f"{info.get('shift', NOMINAL_SHIFT)}), {info.get('scenes')} scenes. "
        f"{metrics.AVERAGING_RULE}",
        "",
        markdown_table(rows),
        "",
        f"Depth: {SCALE_RULES[output]}.",
        "",
        "Error by distance to the focus of expansion (pixel subsample of `pixels.npz`; lateral "
        "pairs, FOE at infinity, left out):",
        "",
        foe_table(bins),
        "",
        "Plots: `plots/` (error vs depth, vs distance to the focus of expansion, vs estimate, "
        "samples, learning curve). Per-pair metrics: `per_sample.csv`.",
    ]
    (run / "summary.md").write_text("\n".join(md) + "\n")
    return summary


def compare_figure(runs: list[Path], path: Path) -> bool:
    """Error vs distance to the FOE with every run that has ``pixels.npz`` on one figure
    (thesis Fig. 3.14); False (nothing written) when none has."""
    curves = {}
    for run in runs:
        if (run / "pixels.npz").is_file():
            s = json.loads((run / "summary.json").read_text())
            with np.load(run / "pixels.npz") as px:
                label = s["model"] if s["model"] not in curves else f"{s['model']} ({run.name})"
                curves[label] = (px["foe_distance"], px["abs_err"])
    if curves:
        plots.error_vs_foe_distance(curves, path)
    return bool(curves)


def compare_runs(runs: list[Path]) -> tuple[str, str]:
    """(markdown, csv) table of the summary.json of several runs."""
    rows = []
    for run in runs:
        s = json.loads((run / "summary.json").read_text())
        rows.append((f"{s['model']} ({run.name})", s["metrics"]))
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["run", *COLUMNS])
    for name, m in rows:
        w.writerow([name, *(m.get(c) for c in COLUMNS)])
    return markdown_table(rows), buf.getvalue()
