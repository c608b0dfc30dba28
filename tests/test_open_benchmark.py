"""Scoring what the registry does not hold: another method's depth files (``eval
--predictions``), a user's own network (``eval --model``), and ``--median-scaling``; each
checked against the registered path or the ground truth."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_bench import bench

from benchmark.core import metrics, runfolder
from benchmark.core.data import load_scenes
from benchmark.engine.predictions import PNG_SCALE
from stillbox_gen.conventions import NOMINAL_SHIFT

pytestmark = pytest.mark.render


def _summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def _write(folder: Path, data: Path, split: str, make, ext: str = "npy", frames=None) -> int:
    """One prediction per frame of the split's scenes (frames ``frames`` or every frame):
    ``make(truth)`` of each frame's true depth; returns the count written."""
    n = 0
    for scene in load_scenes(data, split):
        for f in frames if frames is not None else range(len(scene.depth)):
            path = folder / runfolder.prediction_name(scene.index, f, ext)
            path.parent.mkdir(parents=True, exist_ok=True)
            depth = make(scene.load_depth(f))
            if ext == "npy":
                np.save(path, depth.astype(np.float32))
            else:
                cv2.imwrite(str(path), np.round(depth * PNG_SCALE).astype(np.uint16))
            n += 1
    return n


@pytest.fixture(scope="module")
def tiny_run(tiny_dataset, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("open") / "run"
    bench("run", "depthnet-tiny", "--data", tiny_dataset, "--batch-size", 4, "--max-steps", 2,
          "--quiet", "--out", run)  # fmt: skip
    return run


def test_saved_predictions_score_as_the_network_that_wrote_them(tiny_dataset, tiny_run, tmp_path):
    """eval --save-predictions writes the layout eval --predictions reads: the same maps give
    the same full-resolution metrics, pair for pair."""
    net = tmp_path / "net"
    bench("eval", "--ckpt", tiny_run / "checkpoints" / "best.pt", "--data", tiny_dataset,
          "--out", net, "--save-predictions")  # fmt: skip
    files = tmp_path / "files"
    proc = bench("eval", "--predictions", net / "predictions", "--data", tiny_dataset,
                 "--out", files)  # fmt: skip
    assert "predictions: MAE" in proc.stdout
    a, b = _summary(net), _summary(files)
    assert b["model"] == "predictions" and "as given" in b["scale"]
    for k in metrics.METRICS:
        assert b["metrics"][k] == pytest.approx(a["metrics"][k], rel=1e-6, nan_ok=True), k
    assert b["metrics"]["images"] == a["metrics"]["images"] > 0


def test_true_depth_scores_zero_and_a_constant_scores_the_constant(tiny_dataset, tmp_path):
    """The truth as .npy scores 0; as a 16-bit PNG within its 1/256 m step; a constant map
    scores what the registered constant method scores."""
    split = "test"
    for ext, mae in (("npy", 1e-6), ("png", 0.5 / PNG_SCALE)):
        folder = tmp_path / f"truth-{ext}"
        _write(folder, tiny_dataset, split, lambda d: np.minimum(d, 200.0), ext)
        bench("eval", "--predictions", folder, "--data", tiny_dataset, "--out", tmp_path / ext)
        m = _summary(tmp_path / ext)["metrics"]
        assert m["mae"] <= mae and m["p1.25"] == 1.0 and m["missed_near"] == 0.0, (ext, m)
        assert m["silog"] < 0.1 and m["sqrel"] < 1e-3
    const = tmp_path / "constant"
    bench("run", "constant", "--data", tiny_dataset, "--quiet", "--out", const)
    c = _summary(const)
    folder = tmp_path / "const"
    _write(folder, tiny_dataset, split, lambda d: np.full_like(d, c["constant_depth"]))
    bench("eval", "--predictions", folder, "--data", tiny_dataset, "--out", tmp_path / "c")
    m = _summary(tmp_path / "c")["metrics"]
    for k in metrics.METRICS:
        assert m[k] == pytest.approx(c["metrics"][k], rel=1e-6, nan_ok=True), k


def test_median_scaling_removes_a_global_scale(tiny_dataset, tmp_path):
    folder = tmp_path / "double"
    _write(folder, tiny_dataset, "test", lambda d: 2 * np.minimum(d, 100.0))
    bench("eval", "--predictions", folder, "--data", tiny_dataset, "--out", tmp_path / "raw")
    bench("eval", "--predictions", folder, "--data", tiny_dataset, "--out", tmp_path / "med",
          "--median-scaling")  # fmt: skip
    raw, med = _summary(tmp_path / "raw"), _summary(tmp_path / "med")
    assert raw["metrics"]["mre"] > 0.5  # twice too far, but for the 100 m clamp
    assert med["metrics"]["mae"] < 1e-4 and med["median_scaling"] is True
    assert "median scaling" in med["scale"] and "median" not in raw["scale"]


def _net_file(tmp_path: Path, ckpt: Path, body: str = "") -> Path:
    """A user's file defining build(): the checkpoint's network, loaded without the project's
    checkpoint code (plain torch.load of tensors), or ``body`` instead."""
    path = tmp_path / "user_net.py"
    path.write_text(
        body
        or "import torch\n"
        "from benchmark.core.models import DepthNet\n"
        "def build():\n"
        "    net = DepthNet(width=0.125)\n"
        f"    state = torch.load({str(ckpt)!r}, weights_only=True)['model']\n"
        "    net.load_state_dict(state)\n"
        "    return net\n"
    )
    return path


def test_a_users_network_scores_as_the_registered_one(tiny_dataset, tiny_run, tmp_path):
    ckpt = tiny_run / "checkpoints" / "best.pt"
    reg = tmp_path / "reg"
    bench("eval", "--ckpt", ckpt, "--data", tiny_dataset, "--out", reg)
    s = _summary(reg)
    user = tmp_path / "user"
    spec = f"{_net_file(tmp_path, ckpt)}:build"
    bench("eval", "--model", spec, "--data", tiny_dataset, "--out", user,
          "--displacement", s["nominal_displacement"])  # fmt: skip
    u = _summary(user)
    assert u["model"] == spec and u["shift"] == NOMINAL_SHIFT
    for k in (*metrics.METRICS, "depth_error"):
        assert u["metrics"][k] == pytest.approx(s["metrics"][k], rel=1e-6, nan_ok=True), k


@pytest.mark.parametrize(
    ("body", "words"),
    [
        ("def build():\n    return 3\n", ["--model", "int, not a Module"]),
        ("import torch\ndef build():\n    return torch.nn.Conv2d(6, 2, 1)\n",
         ["--model", "(1, 2, 64, 64)", "(1, 1, h, w)"]),
        ("import torch\ndef build():\n    return torch.nn.Conv2d(3, 1, 1)\n",
         ["--model", "failed on a (1, 6, 64, 64) input"]),
        ("raise ImportError('no such thing')\n", ["--model", "importing", "no such thing"]),
        ("x = 1\n", ["--model", "has no 'build'"]),
    ],
)  # fmt: skip
def test_a_network_that_breaks_the_contract_is_one_line(tiny_dataset, tmp_path, body, words):
    out = tmp_path / "out"
    spec = f"{_net_file(tmp_path, Path(), body)}:build"
    proc = bench("eval", "--model", spec, "--data", tiny_dataset, "--out", out, check=False)
    _assert_one_line(proc, *words)
    assert not out.exists()


def _assert_one_line(proc, *words: str) -> None:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0].startswith("stillbox-bench: error: "), lines[0]
    for w in words:
        assert w in lines[0], (w, lines[0])


def _good(tiny_dataset: Path, folder: Path) -> None:
    _write(folder, tiny_dataset, "test", lambda d: np.minimum(d, 100.0))


def _first(folder: Path) -> Path:
    return sorted(folder.rglob("depth_*"))[-1]


def test_bad_prediction_files_are_named_and_nothing_is_written(tiny_dataset, tmp_path):
    val_scene = load_scenes(tiny_dataset, "val")[0].index
    cases = {
        "missing": (lambda f: _first(f).unlink(), ["missing", "depth_"]),
        "mis-sized": (lambda f: np.save(_first(f), np.ones((32, 64), np.float32)), ["32×64"]),
        "non-finite": (
            lambda f: np.save(_first(f), np.full((64, 64), math.inf, np.float32)),
            ["non-finite"],
        ),
        "integers": (lambda f: np.save(_first(f), np.ones((64, 64), np.int32)), ["int32"]),
        "other split": (
            lambda f: np.save(f / runfolder.prediction_name(val_scene, 0), np.ones((64, 64))),
            ["names no frame of a scene of the scored split"],
        ),
        "stray file": (lambda f: (f / "notes.txt").write_text("x"), ["notes.txt", "not a"]),
        "mixed": (
            lambda f: cv2.imwrite(str(_first(f).with_suffix(".png")), np.ones((64, 64), np.uint16)),
            ["mixes npy and png"],
        ),
        "symlink": (lambda f: (f / "0" / "link").symlink_to("/etc"), ["symlink"]),
    }
    for name, (spoil, words) in cases.items():
        folder = tmp_path / name.replace(" ", "-")
        _good(tiny_dataset, folder)
        spoil(folder)
        out = tmp_path / f"out-{folder.name}"
        proc = bench("eval", "--predictions", folder, "--data", tiny_dataset, "--out", out,
                     check=False)  # fmt: skip
        _assert_one_line(proc, "--predictions", *words)
        assert not out.exists(), name


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        ([], ["one of --ckpt, --predictions, --model"]),
        (["--ckpt", "a.pt", "--model", "m:f"], ["--ckpt and --model"]),
        (["--predictions", "p", "--save-predictions"], ["--save-predictions"]),
        (["--predictions", "p", "--displacement", "1"], ["--displacement", "only with --model"]),
    ],
)
def test_eval_wants_one_method(tiny_dataset, extra, words):
    _assert_one_line(bench("eval", "--data", tiny_dataset, *extra, check=False), *words)


def test_a_report_inside_the_data_or_the_predictions_is_refused(tiny_dataset, tmp_path):
    folder = tmp_path / "p"
    _good(tiny_dataset, folder)
    cases = ((tiny_dataset / "report", "inside the dataset"), (folder / "report", "--predictions"))
    for out, words in cases:
        proc = bench("eval", "--predictions", folder, "--data", tiny_dataset, "--out", out,
                     check=False)  # fmt: skip
        _assert_one_line(proc, "--out", words)
        assert not out.exists()


def test_the_documented_example_writes_predictions_eval_reads(tiny_dataset, tmp_path, monkeypatch):
    """docs/RUNS.md's example, run as written (its model: a constant 20 m), then scored."""
    import torch

    text = (Path(__file__).parents[1] / "docs" / "RUNS.md").read_text()
    code = text.split("Writing predictions from any PyTorch model")[1].split("```python\n")[1]
    code = code.split("```")[0].replace('"data/stillbox-64"', repr(str(tiny_dataset)))
    monkeypatch.chdir(tmp_path)
    exec(code, {"my_model": lambda x: torch.full((1, 1, *x.shape[-2:]), 20.0)})
    bench("eval", "--predictions", "my-predictions", "--data", tiny_dataset, "--out", "r")
    m = _summary(tmp_path / "r")["metrics"]
    assert m["images"] > 0 and m["p1.25^3"] < 1
