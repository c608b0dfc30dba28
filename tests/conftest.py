"""Shared fixtures: tiny real datasets rendered once per test session through the CLI."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")

CLI = [sys.executable, "-m", "stillbox_gen.cli"]


def assert_user_error(proc: subprocess.CompletedProcess, *words: str) -> None:
    """A user mistake: exit 2 and one stderr line ``stillbox-gen: error: ...`` naming ``words``."""
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("stillbox-gen: error: "), proc.stderr
    for w in words:
        assert w in lines[0], (w, lines[0])


def run_cli(*args: str, check: bool = True, timeout: float = 600) -> subprocess.CompletedProcess:
    proc = subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=timeout)
    if check and proc.returncode != 0:
        raise AssertionError(f"stillbox-gen {' '.join(map(str, args))} failed:\n{proc.stderr}")
    return proc


def file_tree(root: Path) -> dict[str, bytes]:
    """{relative path: bytes} of every file under ``root`` but dataset.json (whose ``run`` block
    records how a run went)."""
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != "dataset.json"
    }


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
