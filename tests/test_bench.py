"""Benchmark on a tiny real dataset: pair sampling, smoke `run`, exact resume, eval, report.

``stillbox-bench`` runs in this process (conftest.invoke_main) but for two end-to-end runs in a
subprocess (the smoke run and the speed table, which sets torch's thread count).
"""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import CliResult, invoke_main

from benchmark import cli
from benchmark.core import runfolder
from benchmark.core.data import FrameStore, PairDataset, load_scenes

BENCH = [sys.executable, "-m", "benchmark.cli"]


def bench(*args, check: bool = True) -> CliResult:
    """``stillbox-bench ARGS`` in this process; AssertionError on a non-zero exit if ``check``."""
    proc = invoke_main(cli.main, *args)
    if check and proc.returncode != 0:
        raise AssertionError(f"stillbox-bench {' '.join(map(str, args))} failed:\n{proc.stderr}")
    return proc


def bench_e2e(*args, check: bool = True) -> subprocess.CompletedProcess:
    """``stillbox-bench ARGS`` end to end, in a subprocess."""
    proc = subprocess.run([*BENCH, *map(str, args)], capture_output=True, text=True, timeout=900)
    if check and proc.returncode != 0:
        raise AssertionError(f"stillbox-bench {' '.join(map(str, args))} failed:\n{proc.stderr}")
    return proc


@pytest.fixture(scope="session")
def store(tiny_dataset) -> FrameStore:
    return FrameStore(load_scenes(tiny_dataset, "train"), progress=False)


@pytest.mark.render
def test_training_pairs_follow_the_original_sampling(store):
    """Shifts 0..6, about half reversed, depth rescaled to the nominal shift, flips applied."""
    ds = PairDataset(store, "train", shift=3, seed=0)
    shifts, reversed_ = [], 0
    for epoch in range(4):
        ds.set_epoch(epoch)
        for i in range(len(ds)):
            item = ds[i]
            k, _ = ds.items[i]
            i1, i2 = item["frames"].tolist()
            fh, fv = item["flips"].tolist()
            shifts.append(abs(i2 - i1))
            reversed_ += i2 < i1
            depth = store.depth(k, i2).copy()
            expected = np.full_like(depth, 100.0) if i1 == i2 else depth * 3 / abs(i2 - i1)
            expected = np.clip(expected, 0, 100)
            img2 = store.rgb(k, i2)
            if fh:
                expected, img2 = expected[:, ::-1], img2[:, ::-1]
            if fv:
                expected, img2 = expected[::-1], img2[::-1]
            np.testing.assert_allclose(item["target"].numpy(), expected, rtol=1e-6)
            x2 = item["input"][3:].numpy().transpose(1, 2, 0)
            np.testing.assert_allclose((x2 * 0.2 + 0.5) * 255, img2, atol=1e-3)
            scene = store.scenes[k]
            t = (i2 - i1) * scene.speed * scene.time_step * [(-1) ** fh, (-1) ** fv, 1]
            np.testing.assert_allclose(item["translation"].numpy(), t, rtol=1e-5, atol=1e-7)
    assert set(shifts) <= set(range(7)) and max(shifts) >= 5 and 0 in shifts
    assert 0.3 < reversed_ / len(shifts) < 0.6


@pytest.mark.render
def test_pair_sampling_is_deterministic_per_seed_and_epoch(store):
    a, b = PairDataset(store, "train", seed=1), PairDataset(store, "train", seed=1)
    assert all(np.array_equal(a[i]["target"], b[i]["target"]) for i in range(len(a)))
    b.set_epoch(1)
    assert any(not np.array_equal(a[i]["target"], b[i]["target"]) for i in range(len(a)))


@pytest.mark.render
def test_eval_pairs_are_fixed_forward_pairs(tiny_dataset):
    scenes = load_scenes(tiny_dataset, "val")
    ds = PairDataset(FrameStore(scenes, progress=False), "eval", shift=3)
    assert len(ds) == 7 * len(scenes)
    item = ds[2]
    assert item["frames"].tolist() == [2, 5] and item["flips"].tolist() == [False, False]
    np.testing.assert_array_equal(item["target"].numpy(), ds.store.depth(0, 5))


@pytest.mark.render
def test_bad_file_is_named(tiny_dataset, tmp_path):
    import shutil

    from benchmark.core.data import DataError

    broken = tmp_path / "broken"
    shutil.copytree(tiny_dataset, broken)
    victim = load_scenes(broken, "train")[0].rgb[4]
    victim.write_bytes(b"not a png")
    with pytest.raises(DataError, match=victim.name):
        FrameStore(load_scenes(broken, "train"), progress=False)


def _losses(run: Path) -> dict[int, float]:
    return {int(r["step"]): float(r["loss"]) for r in csv.DictReader(open(run / "steps.csv"))}


@pytest.mark.render
def test_smoke_run_writes_the_run_folder_and_resume_is_exact(tiny_dataset, tmp_path):
    """`run` a few steps: every report file; an interrupted-then-resumed run matches exactly."""
    common = [
        "run",
        "depthnet-tiny",
        "--data",
        tiny_dataset,
        "--batch-size",
        4,
        "--quiet",
        "--log-every",
        1,
        "--ckpt-every",
        2,
    ]
    full = tmp_path / "full"
    proc = bench_e2e(*common, "--max-steps", 6, "--out", full)
    assert "MAE" in proc.stdout
    for name in (
        "config.json",
        "environment.json",
        "metrics.csv",
        "steps.csv",
        "summary.json",
        "summary.md",
        "per_sample.csv",
        "checkpoints/last.pt",
        "checkpoints/best.pt",
        "plots/error_vs_depth.png",
        "plots/error_vs_foe_distance.png",
        "plots/error_vs_estimate.png",
        "plots/samples.png",
        "plots/learning_curve.png",
    ):
        assert (full / name).is_file(), name
    assert list((full / "tb").glob("events.out.tfevents.*")) or not runfolder.has_tensorboard()
    layout = {v for k, v in vars(runfolder).items() if k.isupper() and isinstance(v, str)}
    assert {p.name for p in full.iterdir()} <= layout  # every file is one docs/RUNS.md names
    losses = _losses(full)
    assert sorted(losses) == [1, 2, 3, 4, 5, 6] and all(math.isfinite(v) for v in losses.values())
    summary = json.loads((full / "summary.json").read_text())
    assert summary["split"] == "test" and summary["metrics"]["images"] > 0
    assert "per image" in summary["averaging_rule"] and "mae" in summary["formulas"]

    part = tmp_path / "part"
    bench(*common, "--max-steps", 3, "--out", part)
    bench(*common, "--max-steps", 6, "--out", part, "--resume")
    resumed = _losses(part)
    for step in (4, 5, 6):
        assert resumed[step] == losses[step], (step, resumed[step], losses[step])


@pytest.mark.render
def test_eval_does_not_depend_on_batch_size_and_report_merges_runs(tiny_dataset, tmp_path):
    run = tmp_path / "r"
    bench(
        "run",
        "depthnet-tiny",
        "--data",
        tiny_dataset,
        "--batch-size",
        4,
        "--max-steps",
        2,
        "--quiet",
        "--out",
        run,
    )
    ckpt = run / "checkpoints" / "best.pt"
    for bs in (1, 5):
        bench(
            "eval",
            "--ckpt",
            ckpt,
            "--data",
            tiny_dataset,
            "--split",
            "val",
            "--batch-size",
            bs,
            "--out",
            tmp_path / f"e{bs}",
            "--save-predictions",
        )
    m1, m5 = (
        json.loads((tmp_path / f"e{bs}" / "summary.json").read_text())["metrics"] for bs in (1, 5)
    )
    for k in m1:  # the network's float32 convolutions differ in the last bits across batch sizes
        assert m1[k] == pytest.approx(m5[k], rel=1e-6, abs=1e-9), k
    preds = sorted((tmp_path / "e1" / "predictions").rglob("depth_*.npy"))
    assert len(preds) == m1["images"] and np.load(preds[0]).shape == (64, 64)
    proc = bench("report", run, tmp_path / "e1", "--out", tmp_path / "cmp")
    assert proc.stdout.count("depthnet-tiny") == 2
    assert (tmp_path / "cmp.csv").read_text().count("\n") == 3


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["run", "nope", "--data", "."], ["MODEL", "depthnet"]),
        (["run", "depthnet", "--data", "/no/such"], ["--data"]),
        (["eval", "--ckpt", "/no/such.pt", "--data", "."], ["--ckpt"]),
        (["report", "/no/such/run"], ["summary.json"]),
    ],
)
def test_bad_input_is_a_one_line_error(args, words):
    proc = bench(*args, check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert all(w in lines[0] for w in words), lines[0]


def test_run_depthnet_typed_alone_reads_the_default_dataset(tmp_path, monkeypatch):
    """`stillbox-bench run depthnet` (in-process, from an empty folder): a one-line error naming
    the stillbox-gen command that makes data/stillbox-64; once that dataset is there, the run
    starts on it with the registry's recipe (the training itself is replaced by a stub)."""
    from click.testing import CliRunner

    from benchmark import cli
    from benchmark.engine import runner

    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(cli.cli, ["run", "depthnet"])
    assert result.exit_code == 2, result.output
    (line,) = result.stderr.strip().splitlines()
    assert "--data" in line and "data/stillbox-64" in line
    assert "'stillbox-gen --res 64 --scenes 3000'" in line

    (tmp_path / "data" / "stillbox-64").mkdir(parents=True)
    (tmp_path / "data" / "stillbox-64" / "manifest.parquet").touch()
    calls = []
    metrics = {"mae": 1.0, "mre": 0.1, "mle": 0.1, "depth_error": 1.0, "images": 7}

    def run_method(model, data, out, **overrides):
        calls.append((model, data, out, overrides))
        return {"metrics": metrics, "split": "test"}

    monkeypatch.setattr(runner, "run_method", run_method)
    result = CliRunner().invoke(cli.cli, ["run", "depthnet"])
    assert result.exit_code == 0, result.output
    ((model, data, out, overrides),) = calls
    assert (model, data) == ("depthnet", Path("data/stillbox-64"))
    assert out.parent == Path("runs") and out.name.startswith("depthnet-stillbox-64-")
    cfg = runner.train_config(model, data, out, **overrides)
    assert (cfg.epochs, cfg.batch_size, cfg.lr, cfg.seed) == (55, 256, 0.01, 0)
    assert "MAE 1.000 m" in result.output


def test_list_shows_registered_models():
    out = bench("list").stdout
    assert "depthnet " in out and "depthnet-tiny" in out
    assert "flownets-flow " in out and "38.68 M" in out and "oracle-flow" in out


# --------------------------------------------------------------------------- flow baselines


@pytest.mark.render
def test_flow_targets_follow_depth_translation_and_flips(store):
    """Training flow targets = exact flow of frame i2 towards frame i1, flipped consistently."""
    import torch

    from benchmark.core.flow import flow_from_depth

    ds = PairDataset(store, "train", shift=3, seed=0, target="flow")
    seen = set()
    for i in range(len(ds)):
        item = ds[i]
        k, _ = ds.items[i]
        i1, i2 = item["frames"].tolist()
        fh, fv = item["flips"].tolist()
        scene = store.scenes[k]
        depth = torch.from_numpy(store.depth(k, i2).astype(np.float64))
        t = torch.from_numpy(scene.translation(i2, i1))  # second frame -> first frame
        flow = flow_from_depth(depth, torch.from_numpy(scene.K), t).numpy()
        if fh:
            flow = flow[:, :, ::-1] * np.array([-1.0, 1.0])[:, None, None]
        if fv:
            flow = flow[:, ::-1] * np.array([1.0, -1.0])[:, None, None]
        got = item["target"].numpy()
        assert got.shape == (2, 64, 64)
        np.testing.assert_allclose(got, flow, atol=2e-4, equal_nan=True)
        if i1 == i2:
            assert np.all(got == 0)
        seen.add((fh, fv))
    assert len(seen) == 4


def _summary(run: Path) -> dict:
    return json.loads((run / "summary.json").read_text())


@pytest.mark.render
@pytest.mark.parametrize("model", ["flownets-depth-tiny", "flownets-flow-tiny"])
def test_flownets_smoke_runs(tiny_dataset, tmp_path, model):
    out = tmp_path / model
    proc = bench(
        "run", model, "--data", tiny_dataset, "--batch-size", 4, "--max-steps", 3, "--quiet",
        "--log-every", 1, "--out", out,
    )  # fmt: skip
    assert "MAE" in proc.stdout
    for name in ("summary.md", "per_sample.csv", "pixels.npz", "checkpoints/best.pt"):
        assert (out / name).is_file(), name
    assert (out / "plots" / "error_vs_foe_distance.png").is_file()
    s = _summary(out)
    assert s["metrics"]["images"] > 0 and math.isfinite(s["metrics"]["mae"])
    assert all(math.isfinite(v) for v in _losses(out).values())
    metrics_csv = (out / "metrics.csv").read_text()
    if model == "flownets-flow-tiny":
        assert "EPE" in proc.stdout and math.isfinite(s["metrics"]["epe"])
        assert "val_epe" in metrics_csv and "epe" in s["formulas"]
        assert s["output"] == "flow" and "known translation" in s["scale"]
        # ill-posed near the FOE, but every pixel stays in the score: all pixels counted
        assert sum(b["pixels"] for b in s["error_by_foe_distance"]) > 0
    else:
        assert "epe" not in s["metrics"] and s["thesis_reference_64px"]["mae"] == 5.72


@pytest.mark.render
def test_oracle_flow_returns_ground_truth_and_constant_is_the_median(tiny_dataset, tmp_path):
    """oracle-flow: the geometry and the dataset's motion metadata agree (exact depth back from
    the exact flow, every pixel scored); constant: the training split's median depth."""
    oracle = tmp_path / "oracle"
    proc = bench("run", "oracle-flow", "--data", tiny_dataset, "--quiet", "--out", oracle)
    assert "EPE 0.000 px" in proc.stdout
    s = _summary(oracle)
    m = s["metrics"]
    assert m["mae"] < 1e-4 and m["mre"] < 1e-5 and m["p1.25"] > 0.9999 and m["epe"] == 0
    assert not (oracle / "checkpoints").exists() and (oracle / "plots" / "samples.png").is_file()
    assert s["metrics_with_flow_noise"]["mae"] > 10 * m["mae"]
    bands = [b for b in s["error_by_depth"] if b["pixels"]]  # exact depth in every band
    assert len(bands) >= 2 and all(b["mae"] < 1e-3 for b in bands)
    assert "Error by ground-truth depth" in (oracle / "summary.md").read_text()
    near = [b for b in s["error_by_foe_distance_with_flow_noise"] if b["pixels"] >= 10]
    assert near[0]["median_abs_err"] > near[-1]["median_abs_err"]  # worse near the FOE
    assert "Sensitivity" in (oracle / "summary.md").read_text()

    const = tmp_path / "constant"
    bench("run", "constant", "--data", tiny_dataset, "--quiet", "--out", const)
    s = _summary(const)
    scenes = load_scenes(tiny_dataset, "train")
    depths = FrameStore(scenes, progress=False)._depth
    assert s["constant_depth"] == pytest.approx(float(np.median(np.clip(depths, 0, 100))))
    assert s["metrics"]["mae"] > 1.0 and "median" in s["constant_rule"]


@pytest.mark.render
@pytest.mark.parametrize("model", ["oracle-flow", "constant"])
def test_every_file_of_a_scored_run_is_written_once(tiny_dataset, tmp_path, monkeypatch, model):
    """One writer of the run folder: each report file is written once, atomically, by
    benchmark.core.runfolder (summary.json used to be written again to add entries)."""
    from benchmark.engine import runner

    written = []

    def spy(write):
        return lambda path, *args, **kw: [written.append(path), write(path, *args, **kw)]

    for name in ("atomic_write_text", "atomic_write_binary"):
        monkeypatch.setattr(runfolder, name, spy(getattr(runfolder, name)))
    out = tmp_path / "run"
    summary = runner.run_method(model, tiny_dataset, out, progress=False)
    names = [str(p.relative_to(out)) for p in written]
    assert sorted(names) == sorted(set(names)), names
    assert {"config.json", "summary.json", "summary.md", "per_sample.csv"} <= set(names)
    assert json.loads((out / "summary.json").read_text()) == json.loads(json.dumps(summary))
    on_disk = {str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()}
    assert on_disk == set(names)


@pytest.mark.render
def test_compare_makes_one_table_and_one_figure(tiny_dataset, tmp_path):
    out = tmp_path / "cmp"
    models = "depthnet-tiny,flownets-flow-tiny,oracle-flow,constant"
    args = ["compare", "--data", tiny_dataset, "--models", models, "--batch-size", 4]
    proc = bench(*args, "--max-steps", 1, "--quiet", "--out", out)
    table = (out / "comparison.md").read_text()
    for name in models.split(","):
        assert f"| {name} ({name})" in table
        assert (out / name / "summary.json").is_file()
    assert "EPE (px)" in table and (out / "comparison-error_vs_foe_distance.png").is_file()
    assert (out / "comparison.csv").read_text().count("\n") == 5
    assert proc.stdout.count("running into") == 4
    again = bench(*args, "--max-steps", 1, "--quiet", "--out", out)  # finished runs are reused
    assert again.stdout.count("reusing") == 4
    proc = bench("report", out / "oracle-flow", out / "constant", "--out", tmp_path / "r")
    assert (tmp_path / "r-error_vs_foe_distance.png").is_file()


def test_speed_table(tmp_path):
    import torch

    proc = bench_e2e(
        "speed", "--models", "depthnet-tiny,flownets-flow-tiny", "--resolutions", "64,128",
        "--time-res", 64, "--warmup", 1, "--repeats", 2, "--threads", 1, "--out", tmp_path,
    )  # fmt: skip
    (path,) = tmp_path.glob("speed-*.csv")
    version = torch.__version__.replace("+", "-")
    assert f"-1t-torch{version}.csv" in path.name and path.name.startswith("speed-cpu")
    rows = list(csv.DictReader(path.read_text().splitlines()))
    assert [r["model"] for r in rows] == ["depthnet-tiny", "flownets-flow-tiny"]
    for r in rows:
        assert float(r["params_m"]) > 0 and float(r["latency_ms_b1"]) > 0
        assert float(r["fps_b8"]) > 0 and r["repeats"] == "2"
        assert float(r["gmac_128"]) == pytest.approx(4 * float(r["gmac_64"]), abs=3e-6)
    assert "depthnet-tiny" in proc.stdout and str(path) in proc.stdout


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["compare", "--data", ".", "--models", "depthnet,nope"], ["--models", "nope"]),
        (["speed", "--models", "oracle-flow"], ["--models", "no network"]),
        (["speed", "--resolutions", "64,100"], ["--resolutions"]),
        (["compare", "--data", ".", "--models", ","], ["--models", "empty"]),
    ],
)
def test_bad_flow_benchmark_input_is_a_one_line_error(args, words):
    proc = bench(*args, check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert all(w in lines[0] for w in words), lines[0]


def test_every_flagged_setting_is_an_option_of_its_commands():
    """TrainConfig's fields carry their flags: 'run' and 'compare' offer exactly the fields whose
    Flag has a help text for them, each under its field's name, so that a new knob is one field
    of TrainConfig; the training config copies what they give."""
    from benchmark.cli import supervised
    from benchmark.cli.options import training_settings
    from benchmark.core.config import FLAGGED

    for command in ("run", "compare"):
        params = {p.name: p for p in getattr(supervised, command).params}
        for f in FLAGGED:
            flag = f.metadata["flag"]
            offered = command in flag.help
            assert (f.name in params) == offered, (command, f.name)
            if offered:
                assert flag.name in params[f.name].opts, (command, f.name)
    given = {f.name: None for f in FLAGGED} | {"device": "cpu", "depth_range": "10,60"}
    settings = training_settings(given | {"progress": True, "pretrained": Path("p.pt")})
    assert settings["depth_range"] == (10.0, 60.0) and settings["progress"] is False
    assert settings["pretrained"] == "p.pt" and settings["epochs"] is None


def test_settings_are_checked_by_field_and_named_by_flag():
    """One rule per TrainConfig field: the library names the field, the command line the flag."""
    from benchmark.cli.options import UserError, training_settings
    from benchmark.core.config import check_settings
    from benchmark.core.errors import FieldError

    with pytest.raises(FieldError, match=r"^log_every: must be at least 1, got 0$") as e:
        check_settings({"epochs": 3, "log_every": 0})
    assert e.value.field == "log_every"
    check_settings({"epochs": None, "seed": 2**64 - 1})  # None: the default applies
    with pytest.raises(UserError, match=r"^--log-every: must be at least 1, got 0$"):
        training_settings({"log_every": 0, "device": "cpu"})
    with pytest.raises(UserError, match=r"^--clamp: expected LO,HI in metres"):
        training_settings({"depth_range": "10", "device": "cpu"})
