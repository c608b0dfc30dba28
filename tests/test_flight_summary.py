"""benchmark/flight/summary.py: Wilson intervals computed by hand, counts and means."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmark.flight.simulate import EpisodeResult
from benchmark.flight.summary import episode_row, summarise, wilson_interval


def result(outcome: str, clearance: float, length: float) -> EpisodeResult:
    return EpisodeResult(outcome, 10, clearance, length, 10.0, 0.01, 0.0, 0.002, np.zeros((11, 3)))


def test_wilson_interval_by_hand():
    z2 = 1.959963984540054**2
    assert wilson_interval(20, 20) == pytest.approx((20 / (20 + z2), 1.0))
    assert wilson_interval(0, 20) == pytest.approx((0.0, z2 / (20 + z2)))
    # 10 of 20: centre 0.5, half-width z / (1 + z^2/n) * sqrt(1/80 + z^2/1600)
    half = 1.959963984540054 / (1 + z2 / 20) * (1 / 80 + z2 / 1600) ** 0.5
    assert wilson_interval(10, 20) == pytest.approx((0.5 - half, 0.5 + half))
    assert wilson_interval(0, 0) == (0.0, 1.0)


def test_summary_counts_and_means():
    rs = [result("reached", 1.0, 11.0), result("reached", 0.5, 13.0), result("collided", -0.1, 4.0)]
    s = summarise(rs)
    assert (s["episodes"], s["reached"], s["collided"], s["timeout"]) == (3, 2, 1, 0)
    assert s["success_rate"] == pytest.approx(2 / 3)
    assert s["success_rate_ci95"] == pytest.approx(list(wilson_interval(2, 3)))
    assert s["mean_min_clearance_m"] == pytest.approx(1.4 / 3)
    assert s["mean_path_ratio_reached"] == pytest.approx(1.2)  # (1.1 + 1.3) / 2
    row = episode_row(2, rs[2])
    assert row["outcome"] == "collided" and row["path_ratio"] == pytest.approx(0.4)
    json.dumps([s, row])  # plain JSON values
