"""docs/RELIABILITY.md's table names every ``stillbox-bench`` command that writes (found from
the click definitions: a new command without a row fails here)."""

from __future__ import annotations

import re
from pathlib import Path

from benchmark import cli as bench

PAGE = Path(__file__).resolve().parents[1] / "docs" / "RELIABILITY.md"


def _rows() -> set[str]:
    """The commands named in the first cell of the table's rows: `stillbox-bench a`, `b`."""
    named = set()
    for line in PAGE.read_text().splitlines():
        first = line.split("|")[1] if line.startswith("| `stillbox-bench ") else ""
        named.update(re.findall(r"`(?:stillbox-bench )?([a-z-]+)`", first))
    return named


def test_every_command_that_writes_has_a_row():
    writers = {
        name
        for name, command in bench.cli.commands.items()
        if any(p.name == "out" for p in command.params)
    }
    assert writers - _rows() == set()
    assert _rows() - set(bench.cli.commands) == set(), "a row names no command"
