"""The module structure: no import cycles among the project's modules, and bpy only under
stillbox_gen/blender/. Read from the source (every import statement, function-level ones
included; imports under ``if TYPE_CHECKING:`` are annotations only and are left out)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("stillbox_gen", "benchmark")
BLENDER_ONLY = ("bpy", "mathutils")  # modules that exist inside Blender's Python only


def _modules() -> dict[str, Path]:
    """{dotted module name: file} of every module of the project's packages."""
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            found[name] = path
    return found


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _import_nodes(tree: ast.AST):
    """Import statements anywhere in ``tree`` but under ``if TYPE_CHECKING:``."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and _is_type_checking(node):
            yield from (n for child in node.orelse for n in _import_nodes_of(child))
            continue
        yield from _import_nodes_of(node)


def _import_nodes_of(node: ast.AST):
    if isinstance(node, (ast.Import, ast.ImportFrom)):
        yield node
    yield from _import_nodes(node)


def imported_names(name: str, path: Path) -> set[str]:
    """Dotted names module ``name`` imports: ``import a.b`` gives a.b; ``from .m import x``
    gives <package>.m and <package>.m.x (x may be a submodule)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    names = set()
    for node in _import_nodes(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
            continue
        base = node.module or ""
        if node.level:
            anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
            base = ".".join([*anchor, *([base] if base else [])])
        names.add(base)
        names.update(f"{base}.{alias.name}" for alias in node.names)
    return names


def import_graph() -> dict[str, set[str]]:
    """{module: project modules it imports}."""
    modules = _modules()
    return {
        name: {m for m in imported_names(name, path) if m in modules and m != name}
        for name, path in modules.items()
    }


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as [a, b, ..., a], or None when it is acyclic."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_cycle_finder_finds_cycles():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_relative_imports_resolve_to_modules(tmp_path):
    """``from . import x``, ``from .m import y`` and ``from .. import z`` (inside a function too)
    name the modules they load."""
    src = tmp_path / "m.py"
    src.write_text(
        "from . import formats\nfrom .layout import CHUNK_SIZE\n"
        "def f():\n    from .. import config\n"
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .generate import X\n"
    )
    names = imported_names("stillbox_gen.blender.m", src)
    assert names >= {"stillbox_gen.blender.formats", "stillbox_gen.blender.layout"}
    assert names >= {"stillbox_gen.config", "typing"}
    assert not any("generate" in n for n in names)


def test_the_graph_sees_the_known_edges():
    """A sanity check of the walk itself: edges that must be there."""
    graph = import_graph()
    assert "stillbox_gen.writer" in graph["stillbox_gen.generate"]
    assert "stillbox_gen.workers" in graph["stillbox_gen.ray_pool"]
    assert "stillbox_gen.blender.render" in graph["stillbox_gen.workers"]  # in a function
    assert "stillbox_gen.dataset" in graph["benchmark.core.data"]
    assert "benchmark.core.models" in graph["benchmark.cli.supervised"]
    assert "benchmark.cli.supervised" in graph["benchmark.cli"]


def test_no_import_cycles():
    """Every module can be read, and imported, without the ones that import it."""
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


#: benchmark's groups of modules (the code map of docs/ARCHITECTURE.md): each may import
#: benchmark.core, never the other way round (the other layers: test_import_layers.py)
BENCHMARK_GROUPS = ("engine", "supervised", "unsupervised", "video", "flight", "cli")


def test_benchmark_core_imports_none_of_the_other_groups():
    """benchmark.core is what every chapter uses: it imports no chapter's group nor the CLI."""
    graph = import_graph()
    core = [m for m in graph if m == "benchmark.core" or m.startswith("benchmark.core.")]
    assert "benchmark.core.data" in core
    others = tuple(f"benchmark.{group}" for group in BENCHMARK_GROUPS)
    offenders = [
        f"{m} imports {i}"
        for m in core
        for i in sorted(graph[m])
        if i in others or i.startswith(tuple(f"{o}." for o in others))
    ]
    assert not offenders, offenders


def test_only_the_cli_imports_the_cli():
    """The command line sits on top: no library module imports benchmark.cli."""
    graph = import_graph()
    offenders = [
        f"{m} imports {i}"
        for m in graph
        if not m.startswith("benchmark.cli")
        for i in graph[m]
        if i.startswith("benchmark.cli")
    ]
    assert not offenders, offenders


def test_only_the_blender_package_imports_bpy():
    offenders = []
    for name, path in _modules().items():
        if name.startswith("stillbox_gen.blender"):
            continue
        for imported in imported_names(name, path):
            if imported.split(".")[0] in BLENDER_ONLY:
                offenders.append(f"{name} imports {imported}")
    assert not offenders, offenders


def test_importing_every_other_module_loads_no_bpy():
    """The same at run time: importing all but stillbox_gen.blender leaves bpy unloaded."""
    names = [n for n in _modules() if not n.startswith("stillbox_gen.blender")]
    code = (
        f"import importlib, sys\nfor n in {names!r}:\n    importlib.import_module(n)\n"
        f"print(sorted(m for m in sys.modules if m.split('.')[0] in {BLENDER_ONLY!r}))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


# The data contract: what of stillbox_gen the benchmark may load (itself or through what it
# imports). The readers (a folder and its pack), the conventions, the file formats and layout,
# the record and the camera model; never the generator's config, sampling, workers, writer or
# Blender.
BENCHMARK_MAY_LOAD = frozenset(
    f"stillbox_gen{suffix}"
    for suffix in (
        "",
        ".arguments",
        ".camera",
        ".conventions",
        ".dataset",
        ".errors",
        ".formats",
        ".layout",
        ".lock",
        ".manifest",
        ".packed",
        ".portable",
        ".record",
    )
)
BENCHMARK_MUST_NOT_LOAD = (
    "stillbox_gen.writer",
    "stillbox_gen.generate",
    "stillbox_gen.workers",
    "stillbox_gen.config",
    "stillbox_gen.scene",
    "stillbox_gen.photos",
    "stillbox_gen.blender",
)
# The closed-loop flight samples its own scenes, so it may also load the generator's config and
# scene sampling (as `stillbox-bench fly` needs the `gen` extra); never the writer or Blender.
FLIGHT = "benchmark.flight"
FLIGHT_MAY_ALSO_LOAD = frozenset(
    {"stillbox_gen.config", "stillbox_gen.scene", "stillbox_gen.shapes", "stillbox_gen.photos"}
)
# The one place that starts Blender for `fly --renderer blender`: inside a function (never at
# import), it checks for bpy (stillbox_gen.worker_setup.require_blender) and starts the persistent
# worker (stillbox_gen.live). The walks below do not follow these edges; the test of that module
# checks they stay inside functions.
FLIGHT_RENDERER = "benchmark.flight.render"
FLIGHT_RENDERER_STARTS = ("stillbox_gen.worker_setup", "stillbox_gen.live")


def reachable(graph: dict[str, set[str]], starts: set[str], stop=lambda m: False) -> set[str]:
    """Every module of ``graph`` reached from ``starts`` (themselves included), not going on
    from the modules where ``stop(module)`` is true."""
    seen: set[str] = set()
    stack = list(starts)
    while stack:
        node = stack.pop()
        if node not in seen:
            seen.add(node)
            if node in starts or not stop(node):
                stack.extend(graph.get(node, ()))
    return seen


def _benchmark_modules(names, flight: bool = False) -> set[str]:
    """The benchmark's modules among ``names``: those of the flight package, or all others."""
    return {n for n in names if n.split(".")[0] == "benchmark" and n.startswith(FLIGHT) == flight}


def _generator_modules_of_benchmark(graph: dict[str, set[str]], flight: bool = False) -> set[str]:
    """The stillbox_gen modules that benchmark modules (of flight, or all others) import,
    directly or not. The others' walk stops at the flight package (the `fly` command imports it
    inside its functions: what flight loads is the flight test's); the flight walk leaves out
    the renderer's start of Blender (FLIGHT_RENDERER_STARTS)."""
    starts = _benchmark_modules(graph, flight)
    graph = {
        m: {i for i in imports if not (m == FLIGHT_RENDERER and i in FLIGHT_RENDERER_STARTS)}
        for m, imports in graph.items()
    }
    found = reachable(graph, starts, stop=lambda m: not flight and m.startswith(FLIGHT))
    return {n for n in found if n.split(".")[0] == "stillbox_gen"}


def test_reachable_follows_chains():
    graph = {"benchmark.a": {"stillbox_gen.x"}, "stillbox_gen.x": {"stillbox_gen.y"}}
    assert _generator_modules_of_benchmark(graph) == {"stillbox_gen.x", "stillbox_gen.y"}


def test_the_contract_lists_are_disjoint():
    assert not any(m.startswith(BENCHMARK_MUST_NOT_LOAD) for m in BENCHMARK_MAY_LOAD)


def test_benchmark_imports_only_the_data_contract():
    """Read from the source: every stillbox_gen module a benchmark module imports, directly or
    through other modules, is one of the contract's (never the writer, config or Blender)."""
    loaded = _generator_modules_of_benchmark(import_graph())
    assert "stillbox_gen.dataset" in loaded  # the walk sees the reader
    assert loaded <= BENCHMARK_MAY_LOAD, sorted(loaded - BENCHMARK_MAY_LOAD)
    assert not any(m.startswith(BENCHMARK_MUST_NOT_LOAD) for m in loaded)


def test_flight_loads_the_scene_sampling_but_never_the_writer_or_blender():
    loaded = _generator_modules_of_benchmark(import_graph(), flight=True)
    assert "stillbox_gen.scene" in loaded  # the walk sees the sampling
    assert loaded <= BENCHMARK_MAY_LOAD | FLIGHT_MAY_ALSO_LOAD, sorted(loaded)
    for forbidden in ("stillbox_gen.writer", "stillbox_gen.generate", "stillbox_gen.blender"):
        assert not any(m.startswith(forbidden) for m in loaded)


def test_the_flight_renderer_starts_blender_inside_a_function_only():
    """benchmark.flight.render imports workers and live lazily: importing the flight package
    (and the command line) loads neither, nor bpy."""
    tree = ast.parse(_modules()[FLIGHT_RENDERER].read_text())
    top = {a.name for n in tree.body if isinstance(n, ast.Import) for a in n.names}
    top |= {
        f"{n.module}.{a.name}" for n in tree.body if isinstance(n, ast.ImportFrom) for a in n.names
    }
    top |= {n.module for n in tree.body if isinstance(n, ast.ImportFrom) and n.module}
    assert not top & set(FLIGHT_RENDERER_STARTS), top
    names = sorted(n for n in _modules() if n.startswith((FLIGHT, "benchmark.cli")))
    code = (
        f"import importlib, sys\nfor n in {names!r}:\n    importlib.import_module(n)\n"
        f"print(sorted(m for m in sys.modules if m in {FLIGHT_RENDERER_STARTS!r} or m == 'bpy'))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


def test_importing_the_benchmark_loads_only_the_data_contract():
    """The same at run time: importing every benchmark module loads no other stillbox_gen
    module, and neither bpy."""
    names = sorted(_benchmark_modules(_modules()))
    code = (
        f"import importlib, sys\nfor n in {names!r}:\n    importlib.import_module(n)\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('stillbox_gen', 'bpy')))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    loaded = set(ast.literal_eval(proc.stdout))
    assert "stillbox_gen.dataset" in loaded
    assert loaded <= BENCHMARK_MAY_LOAD, sorted(loaded - BENCHMARK_MAY_LOAD)


def test_every_package_is_installed():
    """pyproject.toml's [tool.setuptools] packages name every folder of modules (a sub-package
    left out would be missing from an installed stillbox-bench)."""
    import tomllib

    listed = set(
        tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    )
    found = {
        ".".join(init.parent.relative_to(ROOT).parts)
        for package in PACKAGES
        for init in (ROOT / package).rglob("__init__.py")
    }
    assert found <= listed, sorted(found - listed)
