"""``stillbox-bench`` on a packed dataset (``stillbox-gen pack``): every command's --data takes
the pack as it takes the folder (benchmark.core.data.read_dataset decides which, from
index.json), with the same training, checkpoints and scores, byte for byte; a corrupted or
unfinished pack is refused in one line naming --data before anything is written."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest
import torch
from conftest import invoke_cli, invoke_main
from test_bench_hardening import assert_bench_error

from benchmark import cli
from benchmark.core import runfolder
from benchmark.core.data import load_scenes, read_dataset, read_scenes
from stillbox_gen.dataset import Dataset
from stillbox_gen.errors import DatasetError
from stillbox_gen.packed import INDEX_JSON, PackedDataset

pytestmark = pytest.mark.render

#: metrics.csv's columns that time the run (docs/RUNS.md; the others must match)
TIMING = ("samples_per_s", "data_wait_share", "seconds")


def bench(*args: object):
    return invoke_main(cli.main, *args)


@pytest.fixture(scope="module")
def packed(tiny_dataset, tmp_path_factory) -> Path:
    """tiny_dataset packed two scenes per shard."""
    out = tmp_path_factory.mktemp("packed-bench") / "tiny-wds"
    proc = invoke_cli("pack", tiny_dataset, "--format", "webdataset", "--out", out,
                      "--scenes-per-shard", 2)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return out


@pytest.fixture(scope="module")
def runs(tiny_dataset, packed, tmp_path_factory) -> dict[str, Path]:
    """``run depthnet`` a few steps on the folder and on its pack: {"folder"|"pack": run}."""
    root = tmp_path_factory.mktemp("packed-runs")
    out = {}
    for name, data in (("folder", tiny_dataset), ("pack", packed)):
        out[name] = root / name
        proc = bench("run", "depthnet", "--data", data, "--out", out[name], "--max-steps", 4,
                     "--batch-size", 4, "--threads", 1, "--quiet")  # fmt: skip
        assert proc.returncode == 0, proc.stderr
    return out


def test_one_place_decides_folder_or_pack(tiny_dataset, packed, tmp_path):
    assert isinstance(read_dataset(tiny_dataset), Dataset)
    assert isinstance(read_dataset(packed), PackedDataset)
    for split in ("train", "val", "test"):
        a, b = read_scenes(tiny_dataset, split), read_scenes(packed, split)
        assert [s.index for s in a] == [s.index for s in b]
        assert [s.record for s in a] == [s.record for s in b]
    assert [s.index for s in read_scenes(packed, "train", 1)] == [
        s.index for s in read_scenes(tiny_dataset, "train", 1)
    ]
    unfinished = tmp_path / "unfinished"
    shutil.copytree(packed, unfinished)
    (unfinished / INDEX_JSON).unlink()
    with pytest.raises(DatasetError, match="interrupted pack"):
        read_dataset(unfinished)
    with pytest.raises(DatasetError, match="no manifest.parquet"):
        read_dataset(tmp_path)


def _state(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


def _same_tensors(a, b, where: str = "") -> None:
    """``a`` and ``b`` equal exactly: tensors bit for bit, containers item by item."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype and a.shape == b.shape, where
        assert torch.equal(a.view(torch.uint8) if a.is_floating_point() else a,
                           b.view(torch.uint8) if b.is_floating_point() else b), where  # fmt: skip
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _same_tensors(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _same_tensors(x, y, f"{where}/{i}")
    else:
        assert a == b, (where, a, b)


def _rows(path: Path) -> list[dict]:
    """metrics.csv without its timing columns."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows and set(TIMING) <= set(rows[0])
    return [{k: v for k, v in r.items() if k not in TIMING} for r in rows]


def test_run_on_a_pack_trains_and_scores_as_on_the_folder(runs):
    folder, pack = runs["folder"], runs["pack"]
    for name in ("last", "best"):
        a = _state(runfolder.checkpoint_path(folder, name))
        b = _state(runfolder.checkpoint_path(pack, name))
        for key in ("config", "environment"):  # the paths given and the machine
            a.pop(key, None), b.pop(key, None)
        _same_tensors(a, b, name)  # weights, optimiser, state, displacement, camera
    rows = _rows(folder / "metrics.csv")
    assert rows == _rows(pack / "metrics.csv") and "val_mae" in rows[0]
    sa, sb = (json.loads((r / "summary.json").read_text()) for r in (folder, pack))
    assert sa["metrics"] == sb["metrics"] and sa["split"] == sb["split"] == "test"
    assert (folder / "per_sample.csv").read_bytes() == (pack / "per_sample.csv").read_bytes()


def test_eval_of_a_checkpoint_scores_the_same_on_the_pack(tiny_dataset, packed, runs, tmp_path):
    ckpt = runfolder.checkpoint_path(runs["folder"], "best")
    summaries = []
    for name, data in (("folder", tiny_dataset), ("pack", packed)):
        out = tmp_path / name
        proc = bench("eval", "--ckpt", ckpt, "--data", data, "--out", out, "--batch-size", 3)
        assert proc.returncode == 0, proc.stderr
        summaries.append(json.loads((out / "summary.json").read_text()))
    assert summaries[0]["metrics"] == summaries[1]["metrics"]
    assert summaries[0]["scenes"] == summaries[1]["scenes"] > 0


def test_eval_sequences_scores_the_same_on_the_pack(tiny_dataset, packed, runs, tmp_path):
    ckpt = runfolder.checkpoint_path(runs["folder"], "best")
    rows = []
    for name, data in (("folder", tiny_dataset), ("pack", packed)):
        out = tmp_path / name
        proc = bench("eval-sequences", "--ckpt", ckpt, "--data", data, "--out", out, "--quiet")
        assert proc.returncode == 0, proc.stderr
        rows.append(json.loads((out / runfolder.RESULTS_JSON).read_text())["rows"])
    assert rows[0] == rows[1]  # every method, scale and metric
    assert {r["model"] for r in rows[0]} >= {"depthnet", "constant"}
    assert all(r["images"] > 0 for r in rows[0])


def _corrupted(packed: Path, tmp_path: Path) -> tuple[Path, str]:
    """A copy of ``packed`` whose last shard (a test split's) has one byte changed."""
    bad = tmp_path / "bad-pack"
    shutil.copytree(packed, bad)
    shard = sorted(bad.glob("shard-*.tar"))[-1]
    data = bytearray(shard.read_bytes())
    data[1000] ^= 0xFF
    shard.write_bytes(bytes(data))
    return bad, shard.name


@pytest.mark.parametrize("command", ["run", "eval", "compare", "eval-sequences"])
def test_a_corrupted_shard_is_refused_before_anything_is_written(packed, runs, tmp_path, command):
    bad, shard = _corrupted(packed, tmp_path)
    out = tmp_path / "out"
    ckpt = runfolder.checkpoint_path(runs["folder"], "best")
    args = {
        "run": ["run", "depthnet", "--max-steps", 1, "--batch-size", 4, "--quiet"],
        "eval": ["eval", "--ckpt", ckpt],
        "compare": ["compare", "--models", "constant"],
        "eval-sequences": ["eval-sequences", "--ckpt", ckpt, "--quiet"],
    }[command]
    proc = bench(*args, "--data", bad, "--out", out)
    assert_bench_error(proc, "--data", shard, "SHA-256")
    assert not out.exists()
    with pytest.raises(DatasetError, match=shard):  # the reader refuses it too
        load_scenes(bad, "test")


def test_an_unfinished_pack_is_refused_in_one_line(packed, tmp_path):
    unfinished = tmp_path / "unfinished"
    shutil.copytree(packed, unfinished)
    (unfinished / INDEX_JSON).unlink()
    out = tmp_path / "out"
    proc = bench("run", "constant", "--data", unfinished, "--out", out)
    assert_bench_error(proc, "--data", str(unfinished), INDEX_JSON)
    assert not out.exists()


def test_the_reference_runs_need_the_folder_and_say_so(packed):
    """The original DepthNet code reads the --legacy copies, which a pack does not hold."""
    from benchmark.supervised import reference

    with pytest.raises(ValueError, match="--legacy copies") as e:
        reference.author_split(packed)
    assert str(e.value).startswith(f"data {packed}: ")


def test_eval_multishift_scores_the_same_on_the_pack(tiny_dataset, packed, runs, tmp_path):
    ckpt = runfolder.checkpoint_path(runs["folder"], "best")
    rows = []
    for name, data in (("folder", tiny_dataset), ("pack", packed)):
        out = tmp_path / name
        proc = bench("eval-multishift", "--ckpt", ckpt, "--data", data, "--out", out,
                     "--max-shift", 3, "--shifts", 1, "--scenes", 1, "--quiet")  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        result = json.loads((out / runfolder.RESULTS_JSON).read_text())
        timing = ("network_ms_per_frame", "fps")
        rows.append([{k: v for k, v in r.items() if k not in timing} for r in result["rows"]])
    assert rows[0] == rows[1] and rows[0]


def test_a_rotating_scene_in_a_pack_is_named_by_its_record(rotating_dataset, tmp_path):
    out = tmp_path / "rotating-wds"
    proc = invoke_cli("pack", rotating_dataset, "--format", "webdataset", "--out", out)
    assert proc.returncode == 0, proc.stderr
    with pytest.raises(DatasetError, match=r"shard-000000\.tar/\d{7}\.json: scene \d+ has camera"):
        load_scenes(out, "train")
    assert [s.index for s in load_scenes(out, "train", rotations=True)] == [
        s.index for s in load_scenes(rotating_dataset, "train", rotations=True)
    ]
