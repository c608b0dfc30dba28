"""Scores of a set of episodes flown with one depth source: what ``fly`` will write."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .obstacles import SensingConfig
from .simulate import EpisodeResult

#: Per-episode error keys of :meth:`sources.Scored.errors` (besides ``depth_frames``), each a
#: mean over the frames the source answered: MAE (m) and MRE over every pixel; MAE over the
#: pixels truly within the sensing range (what becomes obstacle points); ``missed_near``: the
#: fraction of those pixels estimated beyond the range (an obstacle not seen: crashes);
#: ``phantom_near``: the fraction of the pixels truly beyond the range estimated within it (an
#: obstacle that is not there: detours and timeouts).
ERROR_KEYS = ("depth_mae_m", "depth_mre", "near_mae_m", "missed_near", "phantom_near")
NEAR = f"< {SensingConfig.max_range:g} m"  # fly-compare's header of the near-range columns

OUTCOMES = ("reached", "collided", "timeout")
Z_95 = 1.959963984540054  # two-sided 95 % normal quantile


def wilson_interval(successes: int, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % by default); (0, 1) for n = 0."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z / denom * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return max(0.0, centre - half), min(1.0, centre + half)


def episode_row(index: int, r: EpisodeResult) -> dict:
    """One episode as plain JSON values (metres, seconds per step)."""
    return {
        "episode": index,
        "outcome": r.outcome,
        "steps": r.steps,
        "min_clearance_m": r.min_clearance,
        "path_length_m": r.path_length,
        "path_ratio": r.path_ratio,
        "render_s_per_step": r.render_s,
        "depth_s_per_step": r.depth_s,
        "control_s_per_step": r.control_s,
    }


def summarise(results: Sequence[EpisodeResult]) -> dict:
    """Success rate with its 95 % Wilson interval, outcome counts, mean least clearance (m)
    and mean path ratio of the episodes that reached the goal (None without any)."""
    n = len(results)
    counts = {o: sum(r.outcome == o for r in results) for o in OUTCOMES}
    reached = [r for r in results if r.outcome == "reached"]
    low, high = wilson_interval(counts["reached"], n)
    return {
        "episodes": n,
        **counts,
        "success_rate": counts["reached"] / n if n else None,
        "success_rate_ci95": [low, high],
        "mean_min_clearance_m": float(np.mean([r.min_clearance for r in results])) if n else None,
        "mean_path_ratio_reached": (
            float(np.mean([r.path_ratio for r in reached])) if reached else None
        ),
    }


def source_summary(results: Sequence[EpisodeResult], errors: Sequence[dict]) -> dict:
    """What ``fly`` writes in summary.json for one depth source: :func:`summarise`, the least
    clearance of all episodes (m), seconds per control step over every step (render, depth,
    control) and the depth error of the source over every frame it answered (``errors``: one
    sources.Scored.errors() per episode; frames weigh equally)."""
    out = summarise(results)
    steps = sum(r.steps for r in results)
    out["min_min_clearance_m"] = min((r.min_clearance for r in results), default=None)
    for name in ("render_s", "depth_s", "control_s"):
        total = sum(getattr(r, name) * r.steps for r in results)
        out[f"{name}_per_step"] = total / steps if steps else None
    out["depth_frames"] = sum(e["depth_frames"] for e in errors)
    for key in ERROR_KEYS:
        scored = [(e[key], e["depth_frames"]) for e in errors if e.get(key) is not None]
        frames = sum(n for _, n in scored)
        out[key] = sum(v * n for v, n in scored) / frames if frames else None
    return out


#: fly-compare's columns: (CSV name, markdown header, summary.json key, format)
COMPARISON_COLUMNS = (
    ("episodes", "episodes", "episodes", "{:d}"),
    ("success_rate", "success", "success_rate", "{:.0%}"),
    ("success_ci95_low", "95 % CI", None, None),
    ("success_ci95_high", None, None, None),
    ("collided", "collided", "collided", "{:d}"),
    ("timeout", "timeout", "timeout", "{:d}"),
    ("mean_min_clearance_m", "mean clearance (m)", "mean_min_clearance_m", "{:.2f}"),
    ("min_min_clearance_m", "least clearance (m)", "min_min_clearance_m", "{:.2f}"),
    ("mean_path_ratio_reached", "path ratio", "mean_path_ratio_reached", "{:.3f}"),
    ("depth_mae_m", "depth MAE (m)", "depth_mae_m", "{:.3f}"),
    ("depth_mre", "depth MRE", "depth_mre", "{:.3f}"),
    ("near_mae_m", f"MAE {NEAR} (m)", "near_mae_m", "{:.2f}"),
    ("missed_near", f"missed {NEAR}", "missed_near", "{:.0%}"),
    ("phantom_near", f"phantom {NEAR}", "phantom_near", "{:.0%}"),
    ("render_ms_per_step", "render (ms/step)", "render_s_per_step", "{:.1f}"),
    ("depth_ms_per_step", "depth (ms/step)", "depth_s_per_step", "{:.1f}"),
    ("control_ms_per_step", "control (ms/step)", "control_s_per_step", "{:.1f}"),
)


def comparison_row(run: str, s: dict) -> dict:
    """One fly-compare CSV row of a run's summary.json (times in ms per step)."""
    row = {"run": run, "depth": s["depth"]}
    for name, _, key, _ in COMPARISON_COLUMNS:
        if key is not None:
            value = s.get(key)
            ms = value is not None and name.endswith("_ms_per_step")
            row[name] = value * 1000 if ms else value
    row["success_ci95_low"], row["success_ci95_high"] = s["success_rate_ci95"]
    order = ["run", "depth", *(c[0] for c in COMPARISON_COLUMNS)]
    return {k: row[k] for k in order}


def comparison_markdown(rows: list[dict]) -> str:
    """fly-compare's table: one row per run (:func:`comparison_row`)."""
    heads = ["run", "depth", *(c[1] for c in COMPARISON_COLUMNS if c[1])]
    lines = ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for row in rows:
        cells = [row["run"], row["depth"]]
        for name, head, _, fmt in COMPARISON_COLUMNS:
            if name == "success_ci95_low":
                cells.append(f"{row['success_ci95_low']:.0%}-{row['success_ci95_high']:.0%}")
            elif head:
                value = row[name]
                cells.append("-" if value is None else fmt.format(value))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
