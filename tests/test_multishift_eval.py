"""eval-multishift on the tiny rendered dataset, cross-checked against `stillbox-bench eval`."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from test_bench import bench

from benchmark.cli.options import user_error
from benchmark.core.multishift import displacements
from benchmark.video.multishift_eval import BANDS, band_key, strategies
from stillbox_gen.dataset import Dataset


@pytest.fixture(scope="module")
def trained(tiny_dataset, tmp_path_factory):
    """A DepthNet-tiny trained for 3 steps on the tiny dataset (its best.pt)."""
    out = tmp_path_factory.mktemp("ms") / "run"
    bench("run", "depthnet-tiny", "--data", tiny_dataset, "--out", out, "--batch-size", 4,
          "--max-steps", 3, "--quiet")  # fmt: skip
    return out


def test_displacements_are_the_camera_path(tiny_dataset):
    scene = Dataset(tiny_dataset).scenes("test")[0]
    d = displacements(scene.cam2world[:, :3, 3], 7, 5)
    np.testing.assert_allclose(d, 0.1 * np.arange(1, 6), rtol=1e-9)  # 0.1 m per frame
    assert len(displacements(scene.cam2world[:, :3, 3], 2, 5)) == 2  # only the frames before t


def test_strategies():
    assert [s.label for s in strategies((3, 1, 1))] == ["nominal", "n=1", "n=3"]
    with pytest.raises(ValueError, match=r"^counts: each n must be in 1\.\.4") as e:
        strategies((5,))  # the library names its argument, eval-multishift its flag:
    assert user_error(e.value, counts="--shifts").message.startswith("--shifts: each n")


def test_nominal_strategy_scores_what_eval_scores(tiny_dataset, trained, tmp_path):
    """With --max-shift 3 on 10-frame scenes, the nominal strategy scores the pairs (t - 3, t) for
    t = 3..9: exactly eval's fixed forward pairs, so the two commands must agree."""
    ckpt = trained / "checkpoints" / "best.pt"
    out = tmp_path / "ms"
    proc = bench("eval-multishift", "--ckpt", ckpt, "--ckpt", ckpt, "--data", tiny_dataset,
                 "--max-shift", 3, "--shifts", "1,2", "--out", out, "--quiet")  # fmt: skip
    assert "| depthnet-tiny | nominal |" in proc.stdout
    rows = list(csv.DictReader((out / "results.csv").read_text().splitlines()))
    assert [r["strategy"] for r in rows] == ["nominal", "n=1", "n=2"] * 2
    scenes = Dataset(tiny_dataset).scenes("test")
    assert all(int(r["frames"]) == 7 * len(scenes) for r in rows)
    nominal = rows[0]
    assert nominal["shifts_used"] == f"3:{7 * len(scenes)}"
    assert float(nominal["pairs_per_frame"]) == 1.0
    assert all(1.0 <= float(r["pairs_per_frame"]) <= 2.0 for r in rows if r["strategy"] == "n=2")
    bench("eval", "--ckpt", ckpt, "--data", tiny_dataset, "--out", tmp_path / "ev")
    ev = json.loads((tmp_path / "ev" / "summary.json").read_text())["metrics"]
    assert ev["images"] == 7 * len(scenes)
    for name in ("mae", "mre", "mle"):
        assert float(nominal[f"all/{name}"]) == pytest.approx(ev[name], rel=1e-5), name
    for band in BANDS:  # every band column exists (NaN when no pixel falls in it)
        assert f"{band_key(band)}/mre" in nominal
    info = json.loads((out / "results.json").read_text())
    assert info["max_shift"] == 3 and len(info["rows"]) == 6
    assert (out / "results.md").is_file() and (out / "mre_vs_time.png").stat().st_size > 1000


@pytest.mark.parametrize(
    ("flags", "words"),
    [
        (["--shifts", "1,5"], ["--shifts", "at most 4 pairs per frame, got 5"]),
        (["--shifts", "one"], ["--shifts", "integers"]),
        (["--max-shift", "10"], ["--max-shift 10", "--frames"]),
        (["--max-shift", "0"], ["--max-shift", "at least 1"]),
        (["--beta-mean", "0.95"], ["--beta-mean", "(0.1, 0.9)"]),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tiny_dataset, trained, tmp_path, flags, words):
    ckpt = trained / "checkpoints" / "best.pt"
    out = tmp_path / "ms"
    proc = bench("eval-multishift", "--ckpt", ckpt, "--data", tiny_dataset, "--out", out, *flags,
                 "--quiet", check=False)  # fmt: skip
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert all(w in lines[0] for w in words), lines[0]
    assert not out.exists()


def test_a_flow_checkpoint_is_refused(tiny_dataset, tmp_path):
    run = tmp_path / "flow"
    bench("run", "flownets-flow-tiny", "--data", tiny_dataset, "--out", run, "--batch-size", 4,
          "--max-steps", 1, "--quiet")  # fmt: skip
    proc = bench("eval-multishift", "--ckpt", run / "checkpoints" / "best.pt", "--data",
                 tiny_dataset, "--max-shift", 3, "--out", tmp_path / "ms", check=False)  # fmt: skip
    assert proc.returncode == 2 and "--ckpt" in proc.stderr and "not depth" in proc.stderr
    assert not (tmp_path / "ms").exists()
