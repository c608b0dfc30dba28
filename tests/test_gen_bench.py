"""``stillbox-gen bench``'s reference loop (stillbox_gen.bench.reference_loop): the fixed CPU
workload timed before and after the benchmark. Its work is checked against the same arithmetic
in plain Python integers, its full size is pinned (a changed workload would make the times of
old and new tables incomparable), and a tiny real bench prints and records its times. No timing
is asserted (only that times were taken)."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
from conftest import invoke_cli

from stillbox_gen import bench

#: reference_loop() at its default size: the same on every machine (exact integer arithmetic)
REFERENCE_CHECKSUM = 1124627775331324


def test_reference_loop_is_the_documented_integer_work():
    """LCG steps in Python and sorted LCG steps of numpy's seed-0 integers, redone here with
    Python's unbounded integers, % and // (no masks, no int64)."""
    a, c, m = 1103515245, 12345, 2**31
    x, total = 1, 0
    for _ in range(1000):
        x = (a * x + c) % m
        total += x // 2**16
    values = [int(v) for v in np.random.default_rng(0).integers(0, m, 64, dtype=np.int64)]
    for _ in range(3):
        values = sorted((a * v + c) % m for v in values)
    assert bench.reference_loop(1000, 64, 3) == total + sum(values)
    assert bench.reference_loop(1000, 64, 2) != total + sum(values)


def test_reference_loop_at_full_size_is_pinned():
    assert bench.reference_loop() == REFERENCE_CHECKSUM


def test_reference_line_and_csv_carry_the_times(tmp_path):
    row = bench.BenchRow(64, "fast", "CPU", "direct", 1, False, 2, 1.0, 20.0, 30.0)
    row.reference_before_s, row.reference_after_s = 1.234, 1.251
    assert bench.reference_line([row]).startswith("reference loop: 1.23 s before, 1.25 s after")
    bench.write_csv([row], tmp_path / "b.csv")
    (got,) = csv.DictReader((tmp_path / "b.csv").open())
    assert (got["reference_before_s"], got["reference_after_s"]) == ("1.234", "1.251")


@pytest.mark.render
def test_a_bench_prints_and_records_the_reference_times(tmp_path):
    """One 16 px scene, one configuration: the line below the table and the CSV's columns."""
    out = tmp_path / "bench.csv"
    result = invoke_cli("bench", "--res", "16:1", "--configs", "fast", "--workers", 1,
                        "--psnr-scenes", 1, "--csv", out)  # fmt: skip
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    table_end = max(i for i, line in enumerate(lines) if line.startswith("| 16 | fast |"))
    assert lines[table_end + 1].startswith("reference loop: ")
    (row,) = csv.DictReader(out.open())
    times = [float(row["reference_before_s"]), float(row["reference_after_s"])]
    assert all(t > 0 and math.isfinite(t) for t in times)
    assert lines[table_end + 1].startswith(f"reference loop: {times[0]:.2f} s before, ")
