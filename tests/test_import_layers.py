"""The benchmark's layers (docs/ARCHITECTURE.md, "Import directions"): ``core`` at the bottom,
``engine`` (training, scoring, running a network) on it, the chapters (``supervised``,
``unsupervised``, ``video``, ``flight``) on both and never on each other, ``cli`` on top.

Read from the source with ``ast``: every import statement of every module under benchmark/,
function-level ones included, relative ones resolved to the package they name.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARK = ROOT / "benchmark"
CHAPTERS = ("supervised", "unsupervised", "video", "flight")
#: {layer: the benchmark packages its modules may import (besides their own)}
ALLOWED = {
    "core": set(),
    "engine": {"core"},
    **{chapter: {"core", "engine"} for chapter in CHAPTERS},
}


def benchmark_imports(path: Path) -> set[str]:
    """The benchmark packages (``core``, ``engine``, …) the module at ``path`` imports;
    ``benchmark`` itself for ``from benchmark import x`` / ``from .. import x``."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    package = parts[:-1]  # the package a relative import starts from (also for __init__.py)
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name.split(".") for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = list(package[: len(package) - node.level + 1]) if node.level else []
            base += node.module.split(".") if node.module else []
            names = [base + [alias.name] for alias in node.names] if len(base) == 1 else [base]
        else:
            continue
        found.update(n[1] for n in names if len(n) > 1 and n[0] == "benchmark")
    return found


def layer_violations() -> list[str]:
    """``module imports package`` for every import that crosses the layers the wrong way."""
    bad = []
    for path in sorted(BENCHMARK.rglob("*.py")):
        layer = path.relative_to(BENCHMARK).parts[0]
        if layer not in ALLOWED:  # cli (the top) and benchmark/__init__.py
            continue
        allowed = ALLOWED[layer] | {layer}
        for package in sorted(benchmark_imports(path) - allowed):
            bad.append(f"{path.relative_to(ROOT)} imports benchmark.{package}")
    return bad


def test_the_walk_resolves_relative_and_absolute_imports(tmp_path):
    module = tmp_path / "benchmark" / "video" / "m.py"
    module.parent.mkdir(parents=True)
    module.write_text(
        "from ..core import data\nfrom . import footage\nimport benchmark.flight.world\n"
        "def f():\n    from ..engine.train import Trainer\n    from .. import supervised\n"
    )
    global ROOT
    saved, ROOT = ROOT, tmp_path
    try:
        assert benchmark_imports(module) == {"core", "video", "flight", "engine", "supervised"}
    finally:
        ROOT = saved


def test_the_walk_sees_known_imports():
    assert "core" in benchmark_imports(BENCHMARK / "engine" / "train.py")
    assert "engine" in benchmark_imports(BENCHMARK / "cli" / "supervised.py")


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_every_layer_exists(layer):
    assert (BENCHMARK / layer / "__init__.py").is_file()


def test_layers_import_only_the_layers_below():
    """core imports no other benchmark package; engine only core; each chapter only core and
    engine (what two chapters share lives in one of those)."""
    assert not (violations := layer_violations()), "\n".join(violations)
