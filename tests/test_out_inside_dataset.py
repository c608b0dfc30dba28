"""No command writes inside a dataset (`validate` would then report stray files): every
`stillbox-bench` command with an --out, and `stillbox-gen preview`, given valid inputs, refuse an
--out inside any dataset folder in one line naming --out, with nothing written."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from conftest import assert_user_error, invoke_cli, invoke_main
from test_bench_hardening import assert_bench_error, write_checkpoint
from test_infer import _frames, _write_folder

from benchmark import cli
from stillbox_gen.layout import chunk_name

#: each command's arguments but --out: {d} a dataset, {c} a depth checkpoint, {v} a video
ARGS = {
    "run": ["depthnet-tiny", "--data", "{d}"],
    "eval": ["--ckpt", "{c}", "--data", "{d}"],
    "compare": ["--data", "{d}", "--models", "constant"],
    "speed": [],
    "infer": ["--ckpt", "{c}", "--input", "{v}", "--speed", "3", "--fps", "10"],
    "eval-multishift": ["--ckpt", "{c}", "--data", "{d}"],
    "toy": [],
    "finetune": ["--ckpt", "{c}", "--input", "{v}", "--speed", "3", "--fps", "10"],
    "eval-sequences": ["--ckpt", "{c}", "--data", "{d}"],
    "fly": ["--depth", "oracle"],
    "export": ["--ckpt", "{c}"],
}


def test_every_command_with_an_out_is_listed():
    with_out = {n for n, c in cli.cli.commands.items() if any(p.name == "out" for p in c.params)}
    assert with_out - {"report", "fly-compare"} == set(ARGS)  # those two write beside their runs


@pytest.fixture(scope="module")
def inputs(default_dataset, tmp_path_factory) -> dict[str, Path]:
    """A copy of the session's rendered dataset (nothing may land in the shared one), a depth
    checkpoint and a folder of video frames."""
    d = tmp_path_factory.mktemp("confine")
    dataset = d / "ds"
    shutil.copytree(default_dataset, dataset)
    ckpt = write_checkpoint(d / "tiny.pt", camera={"width": 64, "height": 64, "fov_deg": 90.0})
    return {"d": dataset, "c": ckpt, "v": _write_folder(d / "video", _frames())}


def _files(root: Path) -> list[Path]:
    return sorted(p.relative_to(root) for p in root.rglob("*"))


@pytest.mark.parametrize("command", sorted(ARGS))
def test_bench_commands_refuse_an_out_inside_a_dataset(command, inputs):
    dataset = inputs["d"]
    before = _files(dataset)
    args = [a.format(**inputs) for a in ARGS[command]]
    out = dataset / chunk_name(0) / ("net.onnx" if command == "export" else "out")
    proc = invoke_main(cli.main, command, *args, "--out", out)
    assert_bench_error(proc, "--out", "inside the dataset")
    assert _files(dataset) == before


def test_preview_refuses_an_out_inside_a_dataset(inputs):
    dataset = inputs["d"]
    before = _files(dataset)
    proc = invoke_cli("preview", dataset, "--out", dataset / "preview.png")
    assert_user_error(proc, "--out", "inside the dataset")
    assert _files(dataset) == before


def test_generating_into_a_folder_inside_a_dataset_is_refused(inputs):
    dataset = inputs["d"]
    before = _files(dataset)
    proc = invoke_cli("--scenes", 1, "--res", 64, "--out", dataset / "nested")
    assert_user_error(proc, "--out", "inside the dataset")
    assert _files(dataset) == before


@pytest.mark.parametrize("command", sorted(ARGS))
def test_bench_commands_refuse_an_out_that_cannot_be_made_before_any_work(command, inputs):
    """/proc refuses a new folder even to root, whose permissions say it may write there."""
    args = [a.format(**inputs) for a in ARGS[command]]
    out = Path("/proc/stillbox-none") / ("net.onnx" if command == "export" else "out")
    proc = invoke_main(cli.main, command, *args, "--out", out)
    assert_bench_error(proc, "--out", "/proc")
    assert "Traceback" not in proc.stderr and proc.stdout == ""
