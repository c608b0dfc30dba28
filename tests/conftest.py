"""Shared fixtures: tiny real datasets rendered once per test session through the CLI.

Markers: a test that renders with Blender carries ``render`` (``pytest -m "not render"`` is the
fast suite); tests using a fixture in RENDER_FIXTURES get it here, at collection.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

CLI = [sys.executable, "-m", "stillbox_gen.cli"]
TINY_SHARES = (0.5, 0.25, 0.25)  # train/val/test shares of tiny_dataset

# Fixtures that render a dataset with Blender (here and in test_stats.py).
RENDER_FIXTURES = frozenset(
    {
        "default_dataset",
        "custom_dataset",
        "tiny_dataset",
        "rotating_dataset",
        "one_scene_dataset",
        "close_range_scene",
        "toy_data",
    }
)


@pytest.hookimpl(tryfirst=True)  # before -m deselects by marker
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark ``render`` every test that uses a rendering fixture, directly or through another."""
    for item in items:
        if RENDER_FIXTURES.intersection(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.render)


@dataclass
class CliResult:
    """Exit code and output of ``stillbox-gen``, run in a subprocess or in this process."""

    returncode: int
    stdout: str
    stderr: str


def assert_user_error(proc: CliResult | subprocess.CompletedProcess, *words: str) -> None:
    """A user mistake: exit 2 and one stderr line ``stillbox-gen: error: ...`` naming ``words``
    (so no traceback and no other output on stderr)."""
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("stillbox-gen: error: "), proc.stderr
    for w in words:
        assert w in lines[0], (w, lines[0])


def run_cli(*args: str, check: bool = True, timeout: float = 600) -> subprocess.CompletedProcess:
    """``stillbox-gen ARGS`` in a subprocess (end to end: entry point, exit code, real stderr)."""
    proc = subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=timeout)
    if check and proc.returncode != 0:
        raise AssertionError(f"stillbox-gen {' '.join(map(str, args))} failed:\n{proc.stderr}")
    return proc


def invoke_cli(*args: object) -> CliResult:
    """``stillbox-gen ARGS`` in this process (see invoke_main)."""
    from stillbox_gen import cli

    return invoke_main(cli.main, *args)


def invoke_main(main: Callable[[list[str]], None], *args: object) -> CliResult:
    """A command line's ``main(argv)`` (``stillbox_gen.cli.main``, ``benchmark.cli.main``) run in
    this process, its error handling included, under click's CliRunner isolation: milliseconds
    instead of a Python start-up. An exception that ``main`` does not turn into an exit code
    propagates, failing the test with its traceback. For checks that need no subprocess (exit
    code, Python-level output); C libraries writing to file descriptor 2 are not captured, so keep
    those end to end (run_cli)."""
    from click.testing import CliRunner

    with CliRunner().isolation() as (out, err, _):
        try:
            main([str(a) for a in args])
            code = 0
        except SystemExit as e:
            code = 0 if e.code is None else e.code if isinstance(e.code, int) else 1
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
    return CliResult(code, out.getvalue().decode(), err.getvalue().decode())


def file_tree(root: Path) -> dict[str, bytes]:
    """{relative path: bytes} of every file under ``root`` but dataset.json (whose ``run`` block
    records how a run went)."""
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != "dataset.json"
    }


# ---------------------------------------------------------------- processes (Linux /proc)


def _proc_stat(pid: int) -> tuple[int, int] | None:
    """(parent pid, start time in clock ticks) of a live process (None: gone or a zombie)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2 :].split()
    return None if fields[0] == "Z" else (int(fields[1]), int(fields[19]))


def descendants(root: int) -> dict[int, int]:
    """{pid: start time} of every live process below ``root`` (snapshot it before ``root`` dies:
    orphans are re-parented and no longer found below it)."""
    children: dict[int, list[tuple[int, int]]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and (st := _proc_stat(int(entry.name))):
            children.setdefault(st[0], []).append((int(entry.name), st[1]))
    found, todo = {}, [root]
    while todo:
        for pid, start in children.get(todo.pop(), []):
            found[pid] = start
            todo.append(pid)
    return found


def cmdline(pid: int) -> bytes:
    """The NUL-separated command line of a process (b"" when gone)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


def alive_of(procs: dict[int, int]) -> list[int]:
    """Those of ``procs`` (a :func:`descendants` snapshot) still running (same pid and start
    time: not a reused pid)."""
    return [pid for pid, start in procs.items() if (st := _proc_stat(pid)) and st[1] == start]


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch thread for a test module (``pytestmark = pytest.mark.usefixtures(...)``): its
    64 px tiny networks gain nothing from more, and on a busy machine extra threads wait."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def photo_dir(tmp_path_factory) -> Path:
    """A folder of a few synthetic 'photos' (smooth colour noise) for --textures."""
    import cv2

    d = tmp_path_factory.mktemp("photos")
    rng = np.random.default_rng(0)
    for i in range(3):
        small = rng.integers(0, 256, size=(8, 8, 3), dtype=np.uint8)
        cv2.imwrite(str(d / f"photo{i}.png"), cv2.resize(small, (64, 64), cv2.INTER_CUBIC))
    (d / "notes.txt").write_text("not an image")
    return d


@pytest.fixture(scope="session")
def default_dataset(tmp_path_factory) -> Path:
    """Default preset, 64 px, 4 scenes, 2 workers."""
    out = tmp_path_factory.mktemp("ds") / "default"
    run_cli("--res", 64, "--scenes", 4, "--seed", 3, "--out", out, "--quiet")
    return out


@pytest.fixture(scope="session")
def custom_dataset(tmp_path_factory, photo_dir) -> Path:
    """Every scene feature on: photos, non-square frames, custom K, rotations, legacy files."""
    out = tmp_path_factory.mktemp("ds") / "custom"
    run_cli(
        "--res",
        "80x48",
        "--focal",
        50,
        "--principal-point",
        "30,20",
        "--scenes",
        3,
        "--seed",
        5,
        "--textures",
        photo_dir,
        "--rotation-noise",
        0.3,
        "--rotation-speed",
        0.5,
        "--legacy",
        "--workers",
        1,
        "--out",
        out,
        "--quiet",
    )
    return out


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """Six 64 px scenes (10 frames) whose seed puts at least one scene in every split (shares
    0.5, 0.25, 0.25): the benchmark's smoke runs."""
    from stillbox_gen.manifest import split_of

    seed = next(
        s
        for s in range(100)
        if {split_of(s, k, TINY_SHARES) for k in range(6)} == {"train", "val", "test"}
    )
    out = tmp_path_factory.mktemp("bench") / "tiny"
    run_cli(
        "--res",
        64,
        "--scenes",
        6,
        "--seed",
        seed,
        "--split",
        ",".join(map(str, TINY_SHARES)),
        "--out",
        out,
        "--quiet",
    )
    return out


@pytest.fixture(scope="session")
def rotating_dataset(tmp_path_factory) -> Path:
    """The unstabilised preset spinning at 5°/frame (its 0.2° is a tenth of a pixel here), 64 px
    (DepthNet's smallest), 3 scenes of 6 frames, one per split: depthnet-unsup's --pose."""
    from stillbox_gen.manifest import split_of

    splits = {"train", "val", "test"}
    seed = next(s for s in range(100) if {split_of(s, k, TINY_SHARES) for k in range(3)} == splits)
    out = tmp_path_factory.mktemp("bench") / "rotating"
    run_cli(
        *("--preset", "stillbox-unstabilised", "--rotation-speed", 5, "--res", 64),
        *("--scenes", 3, "--frames", 6, "--seed", seed, "--quality", "fast", "--out", out),
        *("--split", ",".join(map(str, TINY_SHARES)), "--quiet"),
    )
    return out


#: Pixels of the toy presets' frames as the tests render them (the presets' 200 px rendered small).
TOY_RES = 64


@pytest.fixture(scope="session")
def toy_data(tmp_path_factory) -> dict[str, Path]:
    """Both toy presets rendered at TOY_RES px through the CLI, ``{scene name: dataset}`` (about
    3 s each): the toy study's tests and its timing scripts (tests/test_study_scripts.py)."""
    from benchmark.unsupervised import toy

    root = tmp_path_factory.mktemp("toy")
    out = {}
    for name, preset in toy.PRESETS.items():
        out[name] = root / preset
        run_cli("--preset", preset, "--res", TOY_RES, "--out", out[name], "--workers", 1, "--quiet")
    return out


#: The close-range domain of docs/results/finetune/close.toml (walls 12-18 m, objects 2-12 m),
#: copied here so that the test's scene does not move when that study's preset does.
CLOSE_RANGE_PRESET = """\
description = "Close range: walls 12-18 m, objects 2-12 m (tests' close_range_scene)"

[objects]
size_range = [0.0, 5.0]
distance_range = [2.0, 12.0]
distance_law = "uniform"

[box]
half_extent_range = [12.0, 18.0]
offset_max = 3.0
"""


@pytest.fixture(scope="session")
def close_range_scene(tmp_path_factory) -> Path:
    """One close-range scene (median depth about 5 m, no pixel beyond 25 m), 128 px, 17 frames
    of 0.1 m, stabilised, bundled photos: where the photometric loss sees depth at gaps of 2 to 8
    frames (docs/results/finetune/README.md). Seed 2's scene has textured walls: on seeds 0 and
    1 untextured walls and occlusions leave a third of the map undetermined (the video positive
    controls, tests/test_video_positive_controls.py). About 15 s on one worker."""
    d = tmp_path_factory.mktemp("close")
    preset = d / "close.toml"
    preset.write_text(CLOSE_RANGE_PRESET)
    out = d / "close-128"
    run_cli(
        *("--preset", preset, "--res", 128, "--scenes", 1, "--frames", 17, "--seed", 2),
        *("--workers", 1, "--out", out, "--quiet"),
    )
    return out
