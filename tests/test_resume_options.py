"""Every ``stillbox-bench`` command with --resume (found from the click definitions: a new one
without a row in RESUMED fails here) keeps every option its run recorded unless given again: a
tiny run started with options away from their defaults, left unfinished, resumed with --out
and --resume alone (and what must say how far to go), records the same options; and an option
given again with another value is refused in one line naming its flag, nothing written.
In-process (conftest.invoke_main), runs of 1-2 steps or episodes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from conftest import invoke_main
from test_infer import _checkpoint, _frames, _write_folder

from benchmark import cli as bench
from benchmark.unsupervised import toy

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@dataclass
class Resumed:
    """How one command's run is started, left unfinished and resumed ({d} the tiny dataset, {c}
    a depth checkpoint, {v} video frames, {fl} {ho} the toy scenes)."""

    start: list[str]  # the first session, with options away from their defaults
    resume: list[str]  # what the resumed session gives besides --out and --resume
    changed: list[str]  # an option given again with another value
    flag: str  # the flag the refusal names
    config: str = "config.json"  # where the run records its options, inside --out
    may_change: tuple[str, ...] = ()  # config entries the resumed session sets anew
    unfinished: str = field(default="")  # how the first session is left unfinished


RESUMED = {
    "run": Resumed(
        start=["run", "depthnet-tiny", "--data", "{d}", "--max-steps", "1", "--epochs", "2"]
        + ["--lr", "0.002", "--batch-size", "2", "--seed", "5", "--log-every", "1"],
        resume=["run", "depthnet-tiny", "--data", "{d}", "--max-steps", "2"],
        changed=["--lr", "0.003"],
        flag="--lr",
        may_change=("max_steps", "resume"),
        unfinished="max-steps",
    ),
    "finetune": Resumed(
        start=["finetune", "--ckpt", "{c}", "--input", "{v}", "--speed", "3", "--fps", "10"]
        + ["--steps", "1", "--lr", "0.0005", "--batch-size", "2", "--pose-warmup", "1"]
        + ["--log-every", "1", "--seed", "3"],
        resume=["finetune", "--ckpt", "{c}", "--input", "{v}", "--speed", "3", "--fps", "10"]
        + ["--steps", "2"],
        changed=["--lr", "0.001"],
        flag="--lr",
        may_change=("steps", "resume"),
        unfinished="max-steps",
    ),
    "fly": Resumed(
        start=["fly", "--depth", "oracle", "--renderer", "analytic", "--res", "32"]
        + ["--episodes", "1", "--seed", "2", "--max-steps", "299", "--yaw", "goal"],
        resume=["fly", "--episodes", "2"],
        changed=["--seed", "3"],
        flag="--seed",
        may_change=("episodes",),
        unfinished="summary",
    ),
    "toy": Resumed(
        start=["toy", "--flower", "{fl}", "--horizon", "{ho}", "--iterations", "2"]
        + ["--odm-every", "1", "--lambdas", "1", "--kappas", "0.5", "--losses", "tv"],
        # --losses chooses which runs the study holds (toy_runs.SELECTION): given each time
        resume=["toy", "--flower", "{fl}", "--horizon", "{ho}", "--losses", "tv"],
        changed=["--iterations", "3"],
        flag="--iterations",
        config="toy-runs/study.json",
        unfinished="interrupt",
    ),
}


def test_every_command_with_resume_is_listed():
    with_resume = {
        name for name, c in bench.cli.commands.items() if any(p.name == "resume" for p in c.params)
    }
    assert with_resume == set(RESUMED)


@pytest.fixture(scope="module")
def values(tiny_dataset, toy_data, tmp_path_factory) -> dict[str, str]:
    d = tmp_path_factory.mktemp("resume")
    return {
        "d": str(tiny_dataset),
        "c": str(_checkpoint(d / "tiny.pt", "depthnet-tiny")),
        "v": str(_write_folder(d / "video", _frames())),
        "fl": str(toy_data["flower"]),
        "ho": str(toy_data["horizon"]),
    }


def _bench(*args: object, ok: bool = True):
    proc = invoke_main(bench.main, *args)
    if ok:
        assert proc.returncode == 0, proc.stderr
    return proc


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def _unfinished(case: Resumed, values: dict, out: Path, monkeypatch) -> None:
    """The first session, left as a run to resume."""
    start = [a.format(**values) for a in case.start]
    if case.unfinished == "interrupt":  # Ctrl-C in the study's second run
        optimise, calls = toy.optimise, []

        def interrupted(*args, **kwargs):
            calls.append(1)
            if len(calls) == 2:
                raise KeyboardInterrupt
            return optimise(*args, **kwargs)

        monkeypatch.setattr(toy, "optimise", interrupted)
        assert _bench(*start, "--quiet", "--out", out, ok=False).returncode != 0
        monkeypatch.undo()
        assert (out / case.config).is_file()
        return
    _bench(*start, "--quiet", "--out", out)
    if case.unfinished == "summary":  # killed before its last episode ended
        (out / "summary.json").unlink()


@pytest.mark.parametrize("command", sorted(RESUMED))
def test_resume_keeps_every_recorded_option(command, values, tmp_path, monkeypatch):
    case = RESUMED[command]
    out = tmp_path / "run"
    _unfinished(case, values, out, monkeypatch)
    first = json.loads((out / case.config).read_text())
    resume = [a.format(**values) for a in case.resume]

    refused = _bench(*resume, *case.changed, "--quiet", "--out", out, "--resume", ok=False)
    lines = refused.stderr.strip().splitlines()
    assert refused.returncode == 2 and len(lines) == 1, refused.stderr
    assert lines[0].startswith("stillbox-bench: error: ") and case.flag in lines[0], lines[0]
    assert "Traceback" not in refused.stderr

    before = _tree(out)
    again = _bench(*resume, *case.changed, "--quiet", "--out", out, "--resume", ok=False)
    assert again.returncode == 2 and _tree(out) == before, "written before the refusal"

    _bench(*resume, "--quiet", "--out", out, "--resume")
    if (out / case.config).is_file():  # toy removes its study.json once the study is written
        then = json.loads((out / case.config).read_text())
        changed = {k for k in first.keys() | then.keys() if first.get(k) != then.get(k)}
        assert changed <= set(case.may_change), {k: (first.get(k), then.get(k)) for k in changed}


def test_fly_resume_keeps_a_constant_depth_taken_from_data(values, tmp_path):
    """--depth constant's depth, the median of --data's training split, is kept too: neither
    --data nor --constant-depth needs giving again (the default --data does not exist here)."""
    out = tmp_path / "fly"
    fly = ["fly", "--renderer", "analytic", "--res", "32", "--quiet", "--out", out]
    _bench(*fly, "--depth", "constant", "--data", values["d"], "--episodes", "1")
    (out / "summary.json").unlink()
    first = json.loads((out / "config.json").read_text())
    _bench(*fly, "--resume", "--episodes", "2")
    then = json.loads((out / "config.json").read_text())
    assert {k for k in first if first[k] != then[k]} == {"episodes"}
    assert "median of the training split" in then["constant_rule"]
