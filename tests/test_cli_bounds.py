"""Every numeric option of every ``stillbox-bench`` command, walked from the click definitions
of the command group (a new command or option is covered without a new test): it has a row in
the one table of bounds (benchmark/cli/limits.py), its default lies within it, values within it
parse, and values beyond it (negative, zero where the table excludes it, huge, nan, inf) are
refused by click in one line naming the flag (exit code 2, no traceback) before the command
reads or writes anything. In-process (click's CliRunner isolation): the whole walk takes
seconds.
"""

from __future__ import annotations

import math
from pathlib import Path

import click
import pytest
from conftest import invoke_main

from benchmark import cli as bench
from benchmark.cli import limits
from benchmark.cli.limits import Bound, Bounded, Numbers, Resolution


def _flag(param: click.Parameter) -> str:
    return max(param.opts, key=len)


def _numeric() -> list[tuple[str, click.Parameter]]:
    """(command, option) of every option taking a number or a resolution, by click's type, of
    every command: INTEGER, FLOAT, click's ranges and the project's own numeric types (a
    number, a resolution, a list of numbers)."""
    numeric = (click.types.IntParamType, click.types.FloatParamType, Bounded, Resolution, Numbers)
    return [
        (name, p)
        for name, command in sorted(bench.cli.commands.items())
        for p in command.params
        if isinstance(p.type, numeric) and not getattr(p, "is_flag", False)
    ]


NUMERIC = _numeric()


def _inside(bound: Bound, value: float) -> bool:
    """The table's meaning, written out again here (not Bound.problem, which is under test)."""
    if not math.isfinite(value):
        return False
    above_low = value > bound.low if bound.above else value >= bound.low
    below_high = value < bound.high if bound.below else value <= bound.high
    return above_low and below_high


def _is_int(param: click.Parameter) -> bool:
    base = param.type.base if isinstance(param.type, (Bounded, Numbers)) else param.type
    return isinstance(base, click.types.IntParamType) or isinstance(param.type, Resolution)


def _bound(command: str, param: click.Parameter) -> Bound:
    bound = limits.bound_of(command, _flag(param))
    assert bound is not None, f"{command} {_flag(param)}: no row in benchmark/cli/limits.LIMITS"
    return bound


def _numbers(bound: Bound, integer: bool) -> list[float]:
    """Candidate values around and far beyond ``bound``; the callers keep those it refuses or
    accepts (decided by :func:`_inside`)."""
    low, high = bound.low, bound.high
    values = [-1, 0, low, high, low - 1, high + 1, 10 * high + 1, 10**30]
    if integer:
        return sorted({int(v) for v in values})
    middle = (low + high) / 2
    return sorted({float(v) for v in [*values, low / 2, middle, high * 1.5, 1e308]})


def _texts(command: str, param: click.Parameter) -> list[tuple[str, bool]]:
    """(command-line text, within the table) for the option: numbers around its bound, and
    nan, inf, -inf and an overflowing 1e400 (within: never)."""
    bound = _bound(command, param)
    integer = _is_int(param)
    cases = [(str(v) if integer else repr(v), _inside(bound, v)) for v in _numbers(bound, integer)]
    cases += [(text, False) for text in ("nan", "inf", "-inf", "1e400")]
    if isinstance(param.type, Resolution):  # each side on its own: WxH with one bad side
        side = int(bound.high)
        cases += [(f"64x{v}", _inside(bound, v) and _inside(bound, 64)) for v in (0, side + 1)]
        cases += [(f"{side}x64", True)]
    if isinstance(param.type, Numbers):  # each value of a list on its own
        inside = [text for text, ok in cases if ok]
        cases += [(f"{inside[0]},{text}", ok) for text, ok in cases if not ok]
        cases += [(",".join(inside), True)]
    return cases


def _required(command: click.Command, tmp: Path, skip: click.Parameter) -> list[str]:
    """Placeholder values of the command's other required parameters (so that the option under
    test is the one thing wrong): paths that do not exist, a choice's first, a word."""
    argv: list[str] = []
    for p in command.params:
        if p is skip or not p.required:
            continue
        if isinstance(p.type, click.Path):
            value = str(tmp / f"missing-{p.name}")
        elif isinstance(p.type, click.Choice):
            value = str(p.type.choices[0])
        else:
            value = "placeholder"
        argv += [value] if isinstance(p, click.Argument) else [_flag(p), value]
    return argv


def _outs(command: click.Command, tmp: Path) -> list[str]:
    """--out in ``tmp`` for a command that has one and does not require it (the required one
    is in _required)."""
    out = [p for p in command.params if "--out" in p.opts and not p.required]
    return ["--out", str(tmp / "missing-out")] if out else []


REFUSED = [
    pytest.param(name, p, text, id=f"{name} {_flag(p)} {text}")
    for name, p in NUMERIC
    for text, inside in _texts(name, p)
    if not inside
]
ACCEPTED = [
    pytest.param(name, p, text, id=f"{name} {_flag(p)} {text}")
    for name, p in NUMERIC
    for text, inside in _texts(name, p)
    if inside
]


def test_the_walk_finds_the_options_of_the_issue():
    """The walk sees what issue 40 named (so an empty walk cannot pass the tests below)."""
    seen = {(name, _flag(p)) for name, p in NUMERIC}
    for name in ("run", "finetune", "fly", "toy"):
        assert (name, "--threads") in seen
    assert {("fly", "--res"), ("fly", "--seed"), ("infer", "--speed"), ("infer", "--fps")} <= seen
    assert {("speed", "--resolutions"), ("speed", "--batches"), ("toy", "--lambdas")} <= seen
    assert ("eval-multishift", "--shifts") in seen  # a list of counts, bounded by click too
    assert len(REFUSED) > 5 * len(NUMERIC) and len(ACCEPTED) >= len(NUMERIC)


@pytest.mark.parametrize(("command", "param"), NUMERIC, ids=[f"{n} {_flag(p)}" for n, p in NUMERIC])
def test_every_numeric_option_is_bounded_by_its_row(command, param):
    """Each numeric option has a row in LIMITS and a type that checks it (a new option without
    a row, or declared with click's int or float, fails here, naming it)."""
    bound = _bound(command, param)
    types = "limits.INT, FLOAT, RESOLUTION, INTS or FLOATS"
    bounded = (Bounded, Resolution, Numbers)
    assert isinstance(param.type, bounded), f"{command} {_flag(param)}: not {types}"
    assert bound.low <= bound.high and math.isfinite(bound.low) and math.isfinite(bound.high)


def test_every_row_of_the_table_bounds_an_option():
    """No stale row: each key is a command's flag ("fly --res") or a flag some command takes
    without a row of its own ("--threads")."""
    numeric = {(name, _flag(p)) for name, p in NUMERIC}
    for key in limits.LIMITS:
        command, _, flag = key.rpartition(" ")
        if command:
            assert (command, flag) in numeric, key
        else:
            users = [n for n, f in numeric if f == flag and f"{n} {f}" not in limits.LIMITS]
            assert users, key


@pytest.mark.parametrize(("command", "param", "text"), REFUSED)
def test_a_value_beyond_the_bounds_is_one_line_before_anything(
    tmp_path, monkeypatch, command, param, text
):
    """Exit code 2, one stderr line naming the flag, no traceback, nothing written (--out, or a
    default output folder relative to the working directory, which is ``tmp_path`` here)."""
    monkeypatch.chdir(tmp_path)
    cmd = bench.cli.commands[command]
    flag = _flag(param)
    argv = [command, flag, text, *_required(cmd, tmp_path, param), *_outs(cmd, tmp_path)]
    proc = invoke_main(bench.main, *argv)
    lines = proc.stderr.strip().splitlines()
    assert "Traceback" not in proc.stderr + proc.stdout
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"stillbox-bench: error: Invalid value for '{flag}': "), lines[0]
    assert proc.stdout == ""
    assert list(tmp_path.iterdir()) == [], "written before the refusal"


@pytest.mark.parametrize(("command", "param", "text"), ACCEPTED)
def test_a_value_within_the_bounds_parses(tmp_path, command, param, text):
    """click parses the command line (every other option at its default, which must lie
    within its own bound too) without calling the command."""
    cmd = bench.cli.commands[command]
    argv = [_flag(param), text, *_required(cmd, tmp_path, param)]
    with cmd.make_context(command, argv) as ctx:
        value = ctx.params[param.name]
    if isinstance(param.type, Resolution):
        w, h = value
        assert text in (str(w), f"{w}x{h}")
    elif isinstance(param.type, Numbers):
        assert value == tuple((int if _is_int(param) else float)(v) for v in text.split(","))
    else:
        assert value == (int(text) if _is_int(param) else float(text))


def test_the_message_says_the_bound_and_the_unit():
    """One example of each side, as the issue's ``--threads 100000`` and ``fly --seed -1``."""
    threads = limits.LIMITS["--threads"]
    assert threads.problem(100_000) == f"must be at most {threads.high:,} threads, got 100,000"
    assert limits.LIMITS["--seed"].problem(-1) == "must be at least 0, got -1"
    assert limits.LIMITS["--speed"].problem(math.inf) == "must be a finite number, got inf"
    assert limits.LIMITS["--fov"].problem(180.0) == "must be in (0, 180) degrees, got 180"
    assert limits.LIMITS["--ema"].problem(-0.5) == "must be in [0, 1), got -0.5"
    assert limits.LIMITS["--lr"].problem(0.0) == "must be above 0, got 0"


# ---------------------------------------------------------------- end to end, as the issue found


FLY = ("--renderer", "analytic", "--res", "32", "--episodes", "1", "--quiet")


@pytest.mark.parametrize(
    ("args", "flag"),
    [
        # a traceback from numpy's SeedSequence, after --out was made
        (("--depth", "oracle", "--seed", "-1"), "--seed"),
        # flew, and config.json held Infinity (not JSON)
        (("--depth", "constant", "--constant-depth", "inf"), "--constant-depth"),
    ],
)
def test_fly_refuses_what_it_used_to_run_with(tmp_path, args, flag):
    out = tmp_path / "run"
    proc = invoke_main(bench.main, "fly", *args, "--out", out, *FLY)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert f"'{flag}'" in lines[0]
    assert not out.exists()
