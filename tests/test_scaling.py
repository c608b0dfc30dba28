"""The scaling study's fit: Student-t quantiles against closed forms, the power law against
numpy's least squares, the prediction interval's coverage by simulation, and the report files."""

import json
import math
from statistics import NormalDist

import numpy as np
import pytest

from benchmark.supervised import scaling


@pytest.mark.parametrize("p", [0.9, 0.975, 0.995])
def test_t_quantile_matches_closed_forms_and_the_normal_limit(p):
    # one degree of freedom is Cauchy; two have F(t) = 1/2 + t / (2 sqrt(2 + t^2))
    assert scaling.student_t_quantile(p, 1) == pytest.approx(math.tan(math.pi * (p - 0.5)), 1e-6)
    a = 2 * p - 1
    assert scaling.student_t_quantile(p, 2) == pytest.approx(a * math.sqrt(2 / (1 - a * a)), 1e-6)
    assert scaling.student_t_quantile(p, 100_000) == pytest.approx(NormalDist().inv_cdf(p), 1e-3)


def test_exact_power_law_is_recovered_with_a_zero_width_interval():
    n = [3e4, 6e4, 1.5e5, 3e5]
    fit = scaling.fit_power_law(n, [2.0 + 80 * x**-0.25 for x in n], floor=2.0)
    assert fit.slope == pytest.approx(-0.25)
    assert math.exp(fit.intercept) == pytest.approx(80)
    mid, low, high = fit.predict(4.4e7)
    assert mid == pytest.approx(2.0 + 80 * 4.4e7**-0.25)
    assert low == pytest.approx(mid) and high == pytest.approx(mid)


def test_fit_matches_numpy_least_squares_on_noisy_points():
    rng = np.random.default_rng(0)
    n = np.array([3e4, 6e4, 1.5e5, 3e5, 6e5])
    mae = 60 * n**-0.12 * np.exp(rng.normal(0, 0.03, n.size))
    fit = scaling.fit_power_law(list(n), list(mae))
    slope, intercept = np.polyfit(np.log(n), np.log(mae), 1)
    assert (fit.slope, fit.intercept) == pytest.approx((slope, intercept))
    resid = np.log(mae) - (intercept + slope * np.log(n))
    assert fit.sigma == pytest.approx(np.sqrt((resid**2).sum() / (n.size - 2)))


def test_prediction_interval_covers_new_runs_at_its_stated_rate():
    rng = np.random.default_rng(1)
    n = [3e4, 6e4, 1.5e5, 3e5]
    target, trials, inside = 4.4e7, 2000, 0
    for _ in range(trials):
        noise = rng.normal(0, 0.05, 5)
        mae = [40 * x**-0.15 * math.exp(e) for x, e in zip(n, noise[:4], strict=True)]
        _, low, high = scaling.fit_power_law(n, mae).predict(target)
        inside += low <= 40 * target**-0.15 * math.exp(noise[4]) <= high
    assert abs(inside / trials - scaling.COVERAGE) < 0.02


def test_fit_refuses_too_few_points_and_errors_below_the_floor():
    with pytest.raises(ValueError, match="three"):
        scaling.fit_power_law([1e4, 1e5], [20.0, 15.0])
    with pytest.raises(ValueError, match="floor"):
        scaling.fit_power_law([1e4, 1e5, 1e6], [20.0, 15.0, 4.0], floor=4.8)


def test_report_writes_rows_by_samples_a_fit_and_a_plot(tmp_path):
    evals = []
    for steps, mae in [(4000, 14.0), (1000, 16.5), (2000, 15.2)]:
        folder = tmp_path / f"ours-e{steps}"
        folder.mkdir()
        metrics = {"mae": mae, "mre": 0.8, "mle": 0.6, "depth_error": mae - 1, "p1.25": 0.25}
        summary = {"training_state": {"global_step": steps}, "metrics": metrics}
        (folder / "summary.json").write_text(json.dumps(summary))
        evals.append(folder / "summary.json")
    out = tmp_path / "out"
    summary = scaling.report(evals, 32, out, floor=4.846)
    rows = (out / "results.csv").read_text().splitlines()
    assert rows[0].startswith("run,samples,mae") and rows[1].startswith("ours-e1000,32000,16.5")
    fits = json.loads((out / "fit.json").read_text())["fits"]
    assert fits == json.loads(json.dumps(summary["fits"])) and len(fits) == 2
    at = fits["power law"]["mae_at_target"]
    assert at["low"] < at["fit"] < at["high"] < 14.0
    assert (out / "mae_vs_samples.png").stat().st_size > 10_000
