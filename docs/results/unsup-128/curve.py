"""Usage: python docs/results/unsup-128/curve.py OUT

The learning curves of depthnet-unsup at 128 px, from the committed eval-sequences outputs
(results.csv) of this folder and of ../reference/unsupervised/128px: each checkpoint's test MAE
relative to the constant plane of its own test split (−0.25: the issue's goal, 25 % better), under
the thesis' pair rule "P" and with the fixed pair, against its training steps (the checkpoint's
epoch × the series' steps per epoch, plus the series' offset for a continued run). Writes
OUT/learning_curve.png (Y_LIMITS: checkpoints beyond them are in the table only) and
OUT/learning_curve.md: one row per checkpoint, then each series' trend (:func:`trend`: its last
checkpoints' improvements extrapolated as a geometric series: where it levels off and how many
steps it would need to reach the constant and the goal). Reads only the CSV files; nothing is
trained or scored.
"""

import csv
import math
import re
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HERE = Path(__file__).resolve().parent
GOAL = -0.25
TREND_POINTS = 4  # checkpoints a trend is fitted on
Y_LIMITS = (-40, 100)  # % of the constant's MAE shown; the 1,519-scene run starts far above
RULES = {"P": "thesis rule P", "P (fixed pair)": "fixed pair"}
#: (label, results.csv files, steps per epoch of its checkpoints, steps before its epoch 0)
SERIES = (
    ("ours, recipe (--pose orientation), first run", ["orientation/results.csv"], 100, 0),
    ("ours, recipe, run again", ["orientation-recipe/results.csv"], 100, 0),
    ("ours, --pose-lr 1e-3", ["orientation-pose-lr/results.csv"], 100, 0),
    ("ours, recipe on 1,519 training scenes", ["orientation-1900/results.csv"], 100, 0),
    ("ours, 1,519 scenes, lr 6e-5 from 5,800", ["orientation-1900-lr/results.csv"], 100, 5800),
    ("ours, D + O → O, 1,000-step PoseNet warm-up", ["finetune-warmup-1000/results.csv"], 100, 0),
    ("author's code (--supervise-pose)", ["../reference/unsupervised/128px/results.csv"], 200, 0),
    ("ours, true motion (--known-motion, stabilised data)", ["known-motion/results.csv"], 100, 0),
    ("ours, true motion, continued", ["known-motion-continued/results.csv"], 100, 1200),
)


def epoch_of(checkpoint: str) -> int:
    """The epoch in a kept checkpoint's name (``epoch_4.pt``, ``epoch4.pt``)."""
    return int(re.search(r"epoch_?(\d+)", Path(checkpoint).name).group(1))


def rows_of(files: list[str], per_epoch: int, offset: int) -> list[dict]:
    """One row per (checkpoint, rule): steps, MAE, the constant's MAE and the ratio."""
    out = []
    for name in files:
        rows = [r for r in csv.DictReader((HERE / name).open()) if r["orientation"] == "upright"]
        constant = next(float(r["mae"]) for r in rows if r["model"] == "constant")
        for r in rows:
            if r["scale"] in RULES and r["checkpoint"]:
                steps = offset + per_epoch * epoch_of(r["checkpoint"])
                mae = float(r["mae"])
                cosine = float(r["pose_cosine"]) if r.get("pose_cosine") else float("nan")
                out.append({"steps": steps, "rule": r["scale"], "mae": mae,
                            "constant": constant, "relative": mae / constant - 1,
                            "cosine": cosine})  # fmt: skip
    return sorted(out, key=lambda r: (r["rule"], r["steps"]))


def trend(rows: list[dict], points: int = TREND_POINTS) -> dict | None:
    """The extrapolated trend of one series and rule from its last ``points`` checkpoints (equally
    spaced in steps): their MAE decrements d_1..d_n fitted as d_i = d·r^i (least squares on
    log d), continued: the MAE levels off at ``asymptote`` = last − d_n·r/(1 − r), and reaches a
    target T after ``steps_to(T)`` more steps (None: never). None when the series has fewer
    points or stopped improving (a decrement ≤ 0); ``ratio`` ≥ 1 (not slowing) gives no
    asymptote (−inf). A four-point extrapolation: a trend, not a forecast."""
    last = rows[-points:]
    if len(last) < points:
        return None
    steps = [r["steps"] for r in last]
    spacing = steps[1] - steps[0]
    decrements = [a["mae"] - b["mae"] for a, b in zip(last, last[1:], strict=False)]
    gaps = {b - a for a, b in zip(steps, steps[1:], strict=False)}
    if any(d <= 0 for d in decrements) or len(gaps) > 1:
        return None
    n = len(decrements)
    xs, ys = range(n), [math.log(d) for d in decrements]
    mean_x, mean_y = (n - 1) / 2, sum(ys) / n
    slope = sum((x - mean_x) * (y - mean_y) for x, y in zip(xs, ys, strict=True)) / sum(
        (x - mean_x) ** 2 for x in xs
    )
    ratio = math.exp(slope)
    d_last = math.exp(mean_y + slope * (n - 1 - mean_x))  # the fit's last decrement
    mae = last[-1]["mae"]
    asymptote = mae - d_last * ratio / (1 - ratio) if ratio < 1 else -math.inf

    def steps_to(target: float) -> int | None:
        if mae <= target:
            return 0
        if target <= asymptote:
            return None
        if ratio >= 1:
            return spacing * math.ceil((mae - target) / d_last)
        k = math.log(1 - (mae - target) * (1 - ratio) / (d_last * ratio)) / math.log(ratio)
        return spacing * math.ceil(k)

    return {"steps": steps[-1], "mae": mae, "ratio": ratio, "asymptote": asymptote,
            "to_constant": steps_to(last[-1]["constant"]),
            "to_goal": steps_to(last[-1]["constant"] * (1 + GOAL))}  # fmt: skip


def _level_text(asymptote: float) -> str:
    return "none (not slowing)" if math.isinf(asymptote) else f"{asymptote:.2f}"


def _steps_text(more: int | None, now: int) -> str:
    return "never (levels off above)" if more is None else f"{now + more:,} ({more:,} more)"


def main(out: str) -> None:
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    lines = ["| series | steps | rule | MAE (m) | constant (m) | vs constant | PoseNet cosine |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    trends = ["| series | rule | last checkpoint (steps) | MAE (m) | decrement ratio per "
              "checkpoint | levels off at (m) | steps to the constant | steps to −25 % |",
              "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for label, files, per_epoch, offset in SERIES:
        rows = rows_of(files, per_epoch, offset)
        for rule in RULES:
            t = trend([r for r in rows if r["rule"] == rule])
            if t is None:
                continue
            trends.append(
                f"| {label} | {RULES[rule]} | {t['steps']:,} | {t['mae']:.2f} | {t['ratio']:.2f} | "
                f"{_level_text(t['asymptote'])} | {_steps_text(t['to_constant'], t['steps'])} | "
                f"{_steps_text(t['to_goal'], t['steps'])} |"
            )
        for ax, rule in zip(axes, RULES, strict=True):
            mine = [r for r in rows if r["rule"] == rule]
            ax.plot([r["steps"] for r in mine], [100 * r["relative"] for r in mine], "o-",
                    label=label, ms=3)  # fmt: skip
        for r in rows:
            lines.append(
                f"| {label} | {r['steps']} | {RULES[r['rule']]} | {r['mae']:.2f} | "
                f"{r['constant']:.2f} | {100 * r['relative']:+.1f} % | {r['cosine']:.3f} |"
            )
    for ax, rule in zip(axes, RULES.values(), strict=True):
        ax.axhline(0, color="grey", lw=0.8)
        ax.axhline(100 * GOAL, color="grey", lw=0.8, ls="--")
        ax.set_ylim(*Y_LIMITS)
        ax.set_title(f"test MAE vs the constant plane, {rule}")
        ax.set_xlabel("training steps (batches of 16 sequences)")
    axes[0].set_ylabel("% of the constant plane's MAE (−25 %: the goal)")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(folder / "learning_curve.png", dpi=110)
    trends = trends if len(trends) > 2 else [*trends, "| (no series with a falling trend) |"]
    text = "\n".join(lines) + "\n\nTrends (curve.py's `trend`: the last "
    text += f"{TREND_POINTS} checkpoints' decrements as a geometric series):\n\n"
    (folder / "learning_curve.md").write_text(text + "\n".join(trends) + "\n")
    print(f"wrote {folder / 'learning_curve.png'} and {folder / 'learning_curve.md'}")


if __name__ == "__main__":
    main(sys.argv[1])
