"""Run reports: summary.json / summary.md, plots, and comparison tables across runs."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from . import metrics, plots  # noqa: E402
from .evaluate import EvalResult  # noqa: E402

COLUMNS = ("mae", "mre", "mle", "sae", "sle", "p1.25", "p1.25^2", "p1.25^3", "depth_error")
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
)
# Thesis Tables 3.4 / 3.5 (StillBox validation set, 64 px) and the public code's depth error.
THESIS_64 = {
    "depthnet": {"mae": 4.72, "mre": 0.26, "mle": 0.32, "depth_error": 4.65},
    "flownets-depth": {"mae": 5.72, "mre": 0.363, "mle": 0.276},
}
DEPTH_ERROR_FORMULA = (
    "original DepthNet 'depth error': mean |θ̃_1/4 − area_downsample(min(θ, 100))| at 1/4 "
    "resolution, per image, then averaged like the other metrics"
)


def _fmt(v) -> str:
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
        plots.error_vs_depth(px["gt"], px["abs_err"], plot_dir / "error_vs_depth.png")
        plots.error_vs_foe_distance(
            {model: (px["foe_distance"], px["abs_err"])}, plot_dir / "error_vs_foe_distance.png"
        )
        plots.error_vs_estimate(px["pred"], px["gt"], plot_dir / "error_vs_estimate.png")
    if result.samples:
        plots.sample_grid(result.samples, plot_dir / "samples.png")
    if (run / "metrics.csv").exists():
        learning_curve(run / "metrics.csv", plot_dir / "learning_curve.png")
    summary = {
        "model": model,
        **info,
        "metrics": result.summary,
        "formulas": {**metrics.FORMULAS, "depth_error": DEPTH_ERROR_FORMULA},
        "averaging_rule": metrics.AVERAGING_RULE,
        "scale": "prediction × |pair translation| / nominal displacement (known displacement; "
        "never the ground-truth median)",
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
        f"{info.get('shift', 3)}), {info.get('scenes')} scenes. {metrics.AVERAGING_RULE}",
        "",
        markdown_table(rows),
        "",
        "Plots: `plots/` (error vs depth, vs distance to the focus of expansion, vs estimate, "
        "samples, learning curve). Per-pair metrics: `per_sample.csv`.",
    ]
    (run / "summary.md").write_text("\n".join(md) + "\n")
    return summary


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
