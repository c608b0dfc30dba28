"""Scores of a set of episodes flown with one depth source: what ``fly`` will write."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .simulate import EpisodeResult

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
