"""Every path option of every ``stillbox-bench`` command, walked from the click definitions of
the command group (as tests/test_cli_bounds.py walks the numeric ones; a new path option
without a row in ROLES fails here): given a file where a folder is expected or a folder where a
file is, a missing input, or an output that cannot be made (under a regular file, or under a
folder without write permission), the command refuses in one line naming the option (exit code
2, no traceback) and writes nothing. Every other input is valid (tiny fixtures), so the option
under test is the one thing wrong. In-process (conftest.invoke_main).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import click
import pytest
from conftest import invoke_main
from test_bench_hardening import write_checkpoint
from test_infer import _frames, _write_folder

from benchmark import cli as bench

pytestmark = pytest.mark.usefixtures("one_torch_thread")

# what a path option must be
DATASET = "dataset"  # an input folder holding a dataset
FOLDER = "folder"  # another input folder (predictions, a run folder)
FILE = "file"  # an input file (a checkpoint, poses)
FOOTAGE = "footage"  # a video file or a folder of frames: either kind
OUT_DIR = "out folder"  # a folder written into (made when missing)
OUT_FILE = "out file"  # one file written (made when missing)
OUT_STEM = "out stem"  # OUT.md, OUT.csv...: files beside OUT, OUT itself never made

#: (command, flag or argument name) -> its role; arguments are named by their metavar
ROLES = {
    ("compare", "--data"): DATASET,
    ("compare", "--out"): OUT_DIR,
    ("eval", "--ckpt"): FILE,
    ("eval", "--predictions"): FOLDER,
    ("eval", "--data"): DATASET,
    ("eval", "--out"): OUT_DIR,
    ("eval-multishift", "--ckpt"): FILE,
    ("eval-multishift", "--data"): DATASET,
    ("eval-multishift", "--out"): OUT_DIR,
    ("eval-sequences", "--ckpt"): FILE,
    ("eval-sequences", "--data"): DATASET,
    ("eval-sequences", "--out"): OUT_DIR,
    ("export", "--ckpt"): FILE,
    ("export", "--out"): OUT_FILE,
    ("finetune", "--ckpt"): FILE,
    ("finetune", "--input"): FOOTAGE,
    ("finetune", "--poses"): FILE,
    ("finetune", "--out"): OUT_DIR,
    ("fly", "--data"): DATASET,
    ("fly", "--out"): OUT_DIR,
    ("fly-compare", "RUNS"): FOLDER,
    ("fly-compare", "--out"): OUT_STEM,
    ("infer", "--ckpt"): FILE,
    ("infer", "--input"): FOOTAGE,
    ("infer", "--poses"): FILE,
    ("infer", "--out"): OUT_DIR,
    ("report", "RUNS"): FOLDER,
    ("report", "--out"): OUT_STEM,
    ("run", "--data"): DATASET,
    ("run", "--pretrained"): FILE,
    ("run", "--out"): OUT_DIR,
    ("speed", "--data"): DATASET,
    ("speed", "--out"): OUT_DIR,
    ("toy", "--flower"): DATASET,
    ("toy", "--horizon"): DATASET,
    ("toy", "--out"): OUT_DIR,
}

#: each command's valid arguments but its outputs ({d} a dataset, {c} a depth checkpoint of
#: its frame size, {v} a folder of video frames, {f} a fly run, {r} a run, {fl} {ho} the toy
#: scenes), smallest work; an option given here is replaced when it is the one under test
ARGS = {
    "compare": ["--data", "{d}", "--models", "constant"],
    "eval": ["--ckpt", "{c}", "--data", "{d}"],
    "eval-multishift": ["--ckpt", "{c}", "--data", "{d}"],
    "eval-sequences": ["--ckpt", "{c}", "--data", "{d}"],
    "export": ["--ckpt", "{c}"],
    "finetune": ["--ckpt", "{c}", "--input", "{v}", "--speed", "3", "--fps", "10", "--steps", "1"],
    "fly": ["--depth", "oracle", "--renderer", "analytic", "--res", "32", "--episodes", "1"],
    "fly-compare": ["{f}"],
    "infer": ["--ckpt", "{c}", "--input", "{v}", "--speed", "3", "--fps", "10"],
    "report": ["{r}"],
    "run": ["constant", "--data", "{d}"],
    "speed": ["--train", "--data", "{d}", "--models", "depthnet-tiny", "--batches", "1"],
    "toy": [
        *("--flower", "{fl}", "--horizon", "{ho}", "--iterations", "1"),
        *("--losses", "tv", "--lambdas", "1", "--kappas", "1"),
    ],
}
#: the arguments replacing ARGS[command] when one option is under test (eval --predictions
#: takes the place of --ckpt)
ARGS_FOR = {
    ("eval", "--predictions"): ["--data", "{d}"],
    ("fly", "--data"): ["--depth", "constant", *ARGS["fly"][2:]],
}
#: --out of the command line (export writes one file whose suffix says its format)
OUT = {"export": "out.onnx"}


def _name(param: click.Parameter) -> str:
    return param.human_readable_name if isinstance(param, click.Argument) else max(param.opts)


def _paths() -> list[tuple[str, click.Parameter]]:
    """(command, parameter) of every option or argument whose type is a path: click.Path or a
    type of the project's own whose name says path."""
    return [
        (name, p)
        for name, command in sorted(bench.cli.commands.items())
        for p in command.params
        if isinstance(p.type, click.Path) or "path" in type(p.type).__name__.lower()
    ]


PATHS = _paths()


def test_every_path_option_has_a_role():
    """A new path option (or a stale row) fails here, naming it."""
    walked = {(name, _name(p)) for name, p in PATHS}
    assert walked == set(ROLES), (walked - set(ROLES), set(ROLES) - walked)
    assert {("run", "--out"), ("toy", "--flower"), ("report", "RUNS")} <= walked


#: the bad values of each role: (case id, maker of the bad path in a scratch folder)
def _regular_file(tmp: Path) -> Path:
    (tmp / "a-file").write_text("not what was asked for\n")
    return tmp / "a-file"


def _folder(tmp: Path) -> Path:
    (tmp / "a-folder").mkdir()
    return tmp / "a-folder"


def _missing(tmp: Path) -> Path:
    return tmp / "missing"


def _under_a_file(tmp: Path) -> Path:
    return _regular_file(tmp) / "out"


def _under_a_read_only_folder(tmp: Path) -> Path:
    parent = tmp / "read-only"
    parent.mkdir()
    parent.chmod(0o500)
    if os.access(parent, os.W_OK):
        parent.chmod(0o700)
        pytest.skip("running as root: a folder's permissions do not stop its writes")
    return parent / "out"


def _md_is_a_folder(tmp: Path) -> Path:
    (tmp / "table.md").mkdir()
    return tmp / "table"


CASES = {
    DATASET: {"a file": _regular_file, "missing": _missing},
    FOLDER: {"a file": _regular_file, "missing": _missing},
    FILE: {"a folder": _folder, "missing": _missing},
    FOOTAGE: {"missing": _missing},
    OUT_DIR: {
        "a file": _regular_file,
        "under a file": _under_a_file,
        "under a read-only folder": _under_a_read_only_folder,
    },
    OUT_FILE: {
        "a folder": _folder,
        "under a file": _under_a_file,
        "under a read-only folder": _under_a_read_only_folder,
    },
    OUT_STEM: {
        "OUT.md a folder": _md_is_a_folder,
        "under a file": _under_a_file,
        "under a read-only folder": _under_a_read_only_folder,
    },
}

WALK = [
    pytest.param(command, p, case, id=f"{command} {_name(p)} {case}")
    for command, p in PATHS
    for case in CASES[ROLES[command, _name(p)]]
]


@pytest.fixture(scope="module")
def inputs(tiny_dataset, toy_data, tmp_path_factory) -> dict[str, Path]:
    """Valid inputs of every command: a copy of the session's dataset, a depth checkpoint of its
    frame size, video frames, a finished `run constant` and a finished one-episode fly run."""
    d = tmp_path_factory.mktemp("paths")
    dataset = d / "ds"
    shutil.copytree(tiny_dataset, dataset)
    camera = {"width": 64, "height": 64, "fov_deg": 90.0}
    values = {
        "d": dataset,
        "c": write_checkpoint(d / "tiny.pt", camera=camera),
        "v": _write_folder(d / "video", _frames()),
        "r": d / "run",
        "f": d / "fly",
        "fl": toy_data["flower"],
        "ho": toy_data["horizon"],
    }
    for argv in (
        ["run", "constant", "--data", dataset, "--out", values["r"]],
        ["fly", *[a.format(**values) for a in ARGS["fly"]], "--quiet", "--out", values["f"]],
    ):
        proc = invoke_main(bench.main, *argv)
        assert proc.returncode == 0, proc.stderr
    return values


def _files(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def _argv(command: str, param: click.Parameter, bad: Path, values: dict, tmp: Path) -> list[str]:
    """The command line: valid arguments, outputs in ``tmp``, the parameter under test ``bad``."""
    name = _name(param)
    args = [a.format(**values) for a in ARGS_FOR.get((command, name), ARGS[command])]
    if isinstance(param, click.Argument):  # the one positional argument of report, fly-compare
        return [command, str(bad), *args[1:], "--out", str(tmp / OUT.get(command, "out"))]
    if name in args:  # replace the valid value
        i = args.index(name)
        args[i + 1] = str(bad)
    else:
        args += [name, str(bad)]
    if name != "--out":
        args += ["--out", str(tmp / OUT.get(command, "out"))]
    return [command, *args]


@pytest.mark.parametrize(("command", "param", "case"), WALK)
def test_a_wrong_path_is_one_line_naming_it(tmp_path, monkeypatch, inputs, command, param, case):
    """Exit code 2, one stderr line ``stillbox-bench: error: ...`` naming the option (or the
    argument), no traceback, nothing written (in ``tmp_path``, the working directory, where the
    default outputs would go, nor in the inputs)."""
    monkeypatch.chdir(tmp_path)
    role = ROLES[command, _name(param)]
    bad = CASES[role][case](tmp_path)
    argv = _argv(command, param, bad, inputs, tmp_path)
    before, inputs_before = _files(tmp_path), _files(inputs["d"].parent)
    try:
        proc = invoke_main(bench.main, *argv)
    finally:
        for p in tmp_path.rglob("*"):  # let pytest remove what a failing command made
            if p.is_dir():
                p.chmod(0o700)
    lines = proc.stderr.strip().splitlines()
    assert "Traceback" not in proc.stderr + proc.stdout, proc.stderr
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("stillbox-bench: error: "), lines[0]
    name = _name(param)
    assert name.rstrip("S") in lines[0], lines[0]  # RUNS: one of them, RUN, is named
    assert proc.stdout == ""
    assert _files(tmp_path) == before, "written before the refusal"
    assert _files(inputs["d"].parent) == inputs_before, "written into the inputs"


@pytest.mark.parametrize(
    "argv",
    [
        ["speed", "--models", "depthnet-tiny", "--data", "{d}"],  # timed on random inputs
        ["fly", *ARGS["fly"], "--data", "{d}"],  # the oracle reads no dataset
        ["fly", *ARGS["fly"][2:], "--depth", "constant", "--constant-depth", "5", "--data", "{d}"],
    ],
    ids=["speed without --train", "fly --depth oracle", "fly --constant-depth"],
)
def test_a_dataset_the_command_would_not_read_is_refused(tmp_path, monkeypatch, inputs, argv):
    """A --data that the command would ignore is a mistake named before anything runs (it used
    to run without it, whatever it was)."""
    monkeypatch.chdir(tmp_path)
    argv = [a.format(**inputs) for a in argv]
    proc = invoke_main(bench.main, *argv, "--out", tmp_path / "out")
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0].startswith("stillbox-bench: error: --data: only with"), lines[0]
    assert list(tmp_path.iterdir()) == []
