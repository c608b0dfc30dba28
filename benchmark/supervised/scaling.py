"""Test MAE against training samples: a power-law fit and its extrapolation (docs/results/scaling).

The runs train DepthNet at several budgets with the same schedule shape (the recipe's
learning-rate milestones are fractions of ``--epochs``, so they scale with the budget); each
last checkpoint is scored by ``stillbox-bench eval``. :func:`fit_power_law` fits
``log MAE = a + b log N`` by least squares and gives a Student-t prediction interval for one new
run at any budget N, in metres. The same fit of ``MAE - floor`` (a power law toward an
irreducible error, e.g. the resolution floor of ``reference floor``) is the second model.

``python -m benchmark.supervised.scaling report EVALS... --batch-size 32 --out DIR`` writes
``results.csv``, ``fit.json`` and ``mae_vs_samples.png`` into DIR.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path

from ..core import thesis

THESIS_SAMPLES = thesis.PUBLIC_CODE_SAMPLES  # the budget the fits extrapolate to
THESIS_MAE_64 = thesis.TABLE_3_4_64PX["depthnet"]["mae"]  # DepthNet 64 px, thesis Table 3.4
#: two-sided coverage of the prediction intervals
COVERAGE = 0.95


@lru_cache
def student_t_quantile(p: float, dof: int) -> float:
    """Quantile of Student's t distribution with ``dof`` degrees of freedom (0.5 < p < 1), by
    bisection on its CDF, itself integrated with Simpson's rule on the density."""
    if not 0.5 < p < 1 or dof < 1:
        raise ValueError(f"need 0.5 < p < 1 and dof >= 1, got p={p}, dof={dof}")
    log_norm = math.lgamma((dof + 1) / 2) - math.lgamma(dof / 2) - 0.5 * math.log(dof * math.pi)

    def density(t: float) -> float:
        return math.exp(log_norm - (dof + 1) / 2 * math.log1p(t * t / dof))

    def cdf_above_half(t: float, n: int = 2000) -> float:  # P(0 < T < t), n even
        h = t / n
        inner = sum((4 if i % 2 else 2) * density(i * h) for i in range(1, n))
        return h / 3 * (density(0) + inner + density(t))

    lo, hi = 0.0, 1.0
    while cdf_above_half(hi) < p - 0.5:
        hi *= 2
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if cdf_above_half(mid) < p - 0.5 else (lo, mid)
    return (lo + hi) / 2


@dataclass(frozen=True)
class PowerLaw:
    """``MAE(N) = floor + exp(intercept) * N**slope`` fitted on ``points`` runs, with the residual
    standard deviation ``sigma`` of ``log(MAE - floor)`` (natural log)."""

    intercept: float
    slope: float
    sigma: float
    floor: float
    points: int
    mean_log_n: float
    sxx: float

    def predict(self, samples: float, coverage: float = COVERAGE) -> tuple[float, float, float]:
        """(MAE, low, high) in metres at ``samples``: the fit and the prediction interval of one
        new run (t with points - 2 degrees of freedom), mapped back through the floor."""
        x = math.log(samples)
        y = self.intercept + self.slope * x
        spread = math.sqrt(1 + 1 / self.points + (x - self.mean_log_n) ** 2 / self.sxx)
        half = student_t_quantile((1 + coverage) / 2, self.points - 2) * self.sigma * spread
        return tuple(self.floor + math.exp(v) for v in (y, y - half, y + half))


def fit_power_law(samples: list[float], mae: list[float], floor: float = 0.0) -> PowerLaw:
    """Least squares of ``log(MAE - floor)`` on ``log N`` over at least three runs."""
    if len(samples) != len(mae) or len(samples) < 3:
        raise ValueError("need at least three (samples, MAE) runs to fit and bound a power law")
    if min(mae) <= floor:
        raise ValueError(f"every MAE must exceed the floor {floor} m")
    xs = [math.log(n) for n in samples]
    ys = [math.log(m - floor) for m in mae]
    n = len(xs)
    mx, my = sum(xs) / n, sum(ys) / n
    sxx = sum((x - mx) ** 2 for x in xs)
    slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / sxx
    intercept = my - slope * mx
    rss = sum((y - intercept - slope * x) ** 2 for x, y in zip(xs, ys, strict=True))
    return PowerLaw(intercept, slope, math.sqrt(rss / (n - 2)), floor, n, mx, sxx)


def collect(summaries: list[Path], batch_size: int) -> list[dict]:
    """One row per ``stillbox-bench eval`` summary: its folder's name, the checkpoint's training
    samples (optimiser steps x ``batch_size``) and the test metrics."""
    rows = []
    for path in summaries:
        s = json.loads(Path(path).read_text())
        state = s.get("training_state") or {}
        if "global_step" not in state:
            raise ValueError(f"{path}: no training_state.global_step (not a trained checkpoint)")
        row = {"run": Path(path).parent.name, "samples": state["global_step"] * batch_size}
        row.update({k: s["metrics"][k] for k in ("mae", "mre", "mle", "depth_error", "p1.25")})
        rows.append(row)
    return sorted(rows, key=lambda r: (r["samples"], r["run"]))


def plot(rows: list[dict], fits: dict[str, PowerLaw], path: Path) -> None:
    """Test MAE against samples (log axes) with each fit extrapolated to 44 M samples, its
    prediction band, and the thesis' 4.72 m (placed at 44 M samples)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ax.plot([r["samples"] for r in rows], [r["mae"] for r in rows], "ko", label="runs (ours)")
    lo_n = min(r["samples"] for r in rows)
    grid = [lo_n * (THESIS_SAMPLES / lo_n) ** (i / 60) for i in range(61)]
    for (name, fit), colour in zip(fits.items(), ("C0", "C1"), strict=False):
        mid, low, high = zip(*(fit.predict(n) for n in grid), strict=True)
        ax.plot(grid, mid, color=colour, label=f"{name}: {mid[-1]:.1f} m at 44 M")
        ax.fill_between(grid, low, high, color=colour, alpha=0.15)
    ax.plot([THESIS_SAMPLES], [THESIS_MAE_64], "r*", ms=12, label="thesis (Table 3.4): 4.72 m")
    ax.set(xscale="log", yscale="log", xlabel="training samples", ylabel="test MAE (m)")
    ax.set_title(f"DepthNet 64 px: MAE against budget ({COVERAGE:.0%} prediction bands)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def report(summaries: list[Path], batch_size: int, out: Path, floor: float | None) -> dict:
    """Write ``results.csv``, ``fit.json`` and ``mae_vs_samples.png`` into ``out``; return the
    fit summary (each model's parameters and its prediction at THESIS_SAMPLES)."""
    rows = collect(summaries, batch_size)
    samples, mae = [r["samples"] for r in rows], [r["mae"] for r in rows]
    fits = {"power law": fit_power_law(samples, mae)}
    if floor is not None:
        fits[f"power law to the {floor:.2f} m floor"] = fit_power_law(samples, mae, floor)
    summary = {
        "target_samples": THESIS_SAMPLES,
        "thesis_mae": THESIS_MAE_64,
        "coverage": COVERAGE,
        "fits": {
            name: {
                **asdict(fit),
                "mae_at_target": dict(
                    zip(("fit", "low", "high"), fit.predict(THESIS_SAMPLES), strict=True)
                ),
            }
            for name, fit in fits.items()
        },
    }
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "results.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (out / "fit.json").write_text(json.dumps(summary, indent=1) + "\n")
    plot(rows, fits, out / "mae_vs_samples.png")
    return summary


def main(argv: list[str] | None = None) -> None:
    """``python -m benchmark.supervised.scaling report EVALS... --batch-size B --out DIR``."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m benchmark.supervised.scaling")
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("report", help="results.csv, fit.json and mae_vs_samples.png")
    r.add_argument("evals", type=Path, nargs="+", help="eval folders (each with summary.json)")
    r.add_argument("--batch-size", type=int, required=True)
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--floor", type=float, default=None, help="irreducible MAE (m), second fit")
    args = p.parse_args(argv)
    for e in args.evals:
        if not (e / "summary.json").is_file():
            p.error(f"{e}: no summary.json (an eval folder of stillbox-bench eval)")
    summary = report(
        [e / "summary.json" for e in args.evals], args.batch_size, args.out, args.floor
    )
    for name, fit in summary["fits"].items():
        at = fit["mae_at_target"]
        print(
            f"{name}: slope {fit['slope']:+.3f}; at {THESIS_SAMPLES:,} samples "
            f"{at['fit']:.2f} m ({COVERAGE:.0%} interval {at['low']:.2f}-{at['high']:.2f} m)"
        )


if __name__ == "__main__":
    main()
