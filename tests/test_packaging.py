"""Packaging: the generator's and the benchmark's dependencies are extras of one distribution,
so that the reader and the benchmark install (and run) without Blender.

`make test` runs the suite in .venv (both extras), then `make test-bench-only` runs every test
that neither renders nor needs bpy in .venv-bench (the `bench` extra only) with
STILLBOX_EXPECT_NO_BPY=1: there the first test below proves bpy really is absent, so the rest of
that run proves the reader and the benchmark work without it.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _names(requirements: list[str]) -> set[str]:
    """Distribution names of PEP 508 requirement strings, lower case."""
    return {re.match(r"[A-Za-z0-9_.-]+", r).group(0).lower() for r in requirements}


def test_bpy_is_installed_exactly_when_expected():
    """.venv has Blender (the `gen` extra); .venv-bench must not, or its run proves nothing."""
    expect_absent = os.environ.get("STILLBOX_EXPECT_NO_BPY") == "1"
    assert (importlib.util.find_spec("bpy") is None) == expect_absent


def test_blender_and_torch_are_extras_not_base_dependencies():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    base = _names(project["dependencies"])
    extras = {k: _names(v) for k, v in project["optional-dependencies"].items()}
    assert not base & {"bpy", "torch", "kornia", "tensorboard", "numba"}
    assert extras["gen"] == {"bpy", "numpy", "opencv-python-headless", "pyarrow"}
    # only bpy needs numpy < 2 (and the OpenCV and pyarrow releases built for it): no cap in base
    base_pins = {_names([r]).pop(): r for r in project["dependencies"]}
    for name in ("numpy", "opencv-python-headless", "pyarrow"):
        assert "<" not in base_pins[name], base_pins[name]
    assert "numpy<2" in project["optional-dependencies"]["gen"]
    assert {"torch", "kornia"} <= extras["bench"]
    # TensorBoard logs are optional (steps.csv holds the same values): their own extra
    assert extras["tb"] == {"tensorboard"} and "tensorboard" not in extras["bench"]
    assert "bpy" not in extras["bench"]
    # numba (which caps numpy below 2.3) only for the toy study
    assert extras["toy"] == {"numba"} and "numba" not in extras["bench"]


def _without_bpy(monkeypatch) -> None:
    """Make bpy look uninstalled in this process (it is, in .venv-bench)."""
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "bpy" else real(name, *a)
    )


def test_rendering_without_blender_is_a_one_line_error_naming_the_extra(tmp_path, monkeypatch):
    """generate needs bpy: without it, one line naming the `gen` extra, before anything is
    written."""
    from conftest import assert_user_error, invoke_cli

    _without_bpy(monkeypatch)
    out = tmp_path / "d"
    assert_user_error(invoke_cli("--res", "64", "--scenes", "1", "--out", out), "[gen]", "bpy")
    assert not out.exists()


def test_stats_reads_without_blender_but_flicker_renders(default_dataset, tmp_path, monkeypatch):
    from conftest import assert_user_error, invoke_cli

    _without_bpy(monkeypatch)
    out = tmp_path / "stats"
    assert_user_error(invoke_cli("stats", default_dataset, "--flicker", "1", "--out", out), "[gen]")
    assert not out.exists()
    assert invoke_cli("stats", default_dataset, "--scenes", "2", "--out", out).returncode == 0
    assert (out / "stats.json").is_file()


def test_the_benchmark_without_torch_is_a_one_line_error():
    """stillbox-bench installed without the `bench` extra: one line naming it, exit code 2."""
    code = (
        "import importlib.util, sys\n"
        "real = importlib.util.find_spec\n"
        "importlib.util.find_spec = lambda n, *a: None if n == 'torch' else real(n, *a)\n"
        "from benchmark.cli import main\n"
        "main(['list'])\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        "stillbox-bench: error: the benchmark needs PyTorch: pip install 'stillbox-gen[bench]'"
    ]


def test_license_and_citation_agree_with_the_package_metadata():
    """LICENSE holds the licence pyproject.toml declares; CITATION.cff names the same version and
    licence, and cites the thesis."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == "MIT"
    assert (ROOT / "LICENSE").read_text().startswith("MIT License\n")
    cff = (ROOT / "CITATION.cff").read_text()
    fields = dict(re.findall(r"^([a-z-]+): *(.+)$", cff, re.MULTILINE))
    assert fields["cff-version"] == "1.2.0"
    assert fields["version"] == project["version"]
    assert fields["license"] == project["license"]
    assert "type: thesis" in cff and "family-names: Pinard" in cff
