"""Bad input: one-line error naming the flag or file, exit code 2, nothing written."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from conftest import assert_user_error, run_cli


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--preset", "nope"], ["--preset", "nope", "stillbox"]),
        (["--preset", "missing.toml"], ["--preset", "missing.toml"]),
        (["--res", "-5"], ["--res"]),
        (["--res", "0x64"], ["--res"]),
        (["--res", "big"], ["--res", "big"]),
        (["--fov", "0"], ["--fov"]),
        (["--fov", "90", "--focal", "32"], ["--fov", "--focal"]),
        (["--principal-point", "500,3"], ["--principal-point"]),
        (["--principal-point", "3"], ["--principal-point"]),
        (["--frames", "1"], ["--frames"]),
        (["--displacement", "0"], ["--displacement"]),
        (["--scenes", "0"], ["--scenes"]),
        (["--image-format", "gif"], ["--image-format"]),
        (["--textures", "/no/such/folder"], ["--textures", "/no/such/folder"]),
        (["--no-such-flag"], ["--no-such-flag"]),
        (["--focal", "inf"], ["--focal: must be a finite number, got inf"]),
        (["--rotation-noise", "nan"], ["--rotation-noise: must be a finite number, got nan"]),
        (["--seed", "-1"], ["--seed: must be a non-negative integer, got -1"]),
        (["--scene-timeout", "nan"], ["--scene-timeout"]),
    ],
)
def test_bad_flag_is_a_one_line_error_and_writes_nothing(tmp_path, args, words):
    out = tmp_path / "out"
    proc = run_cli(*args, "--out", out, check=False)
    assert_user_error(proc, *words)
    assert not out.exists()


def test_texture_folder_without_images_is_refused(tmp_path):
    empty = tmp_path / "photos"
    empty.mkdir()
    (empty / "readme.txt").write_text("no images here")
    proc = run_cli("--textures", empty, "--out", tmp_path / "out", check=False)
    assert_user_error(proc, "--textures", "no readable images")
    assert not (tmp_path / "out").exists()


def test_bad_preset_file_names_file_and_key(tmp_path):
    preset = tmp_path / "mine.toml"
    preset.write_text("[camera]\nfov = 60\n")
    proc = run_cli("--preset", preset, "--out", tmp_path / "out", check=False)
    assert_user_error(proc, "mine.toml", "camera.fov")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[objects]\ncount = 2.5\n", "objects.count must be an integer, got 2.5"),
        ("[objects]\nsize_range = [-1, 3]\n", "objects.size_range must be [min, max]"),
    ],
)
def test_bad_preset_value_names_file_and_key_and_writes_nothing(tmp_path, text, message):
    preset = tmp_path / "x.toml"
    preset.write_text(text)
    out = tmp_path / "out"
    proc = run_cli("--preset", preset, "--out", out, check=False)
    assert_user_error(proc, f"preset {preset}: {message}")
    assert not out.exists()


def test_truncated_texture_file_is_refused(tmp_path):
    """A JPEG whose data is cut off (valid header) is named, with no decoder noise."""
    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    ok, jpeg = cv2.imencode(".jpg", cv2.resize(rng.integers(0, 256, (8, 8, 3), np.uint8), (64, 64)))
    (photos / "whole.jpg").write_bytes(jpeg.tobytes())
    (photos / "cut.jpg").write_bytes(jpeg.tobytes()[: len(jpeg) // 2])
    proc = run_cli("--textures", photos, "--out", tmp_path / "out", check=False)
    assert_user_error(proc, f"--textures: '{photos / 'cut.jpg'}' cannot be decoded")
    assert not (tmp_path / "out").exists()


def test_output_path_that_is_a_file_is_refused_and_kept(tmp_path):
    target = tmp_path / "afile"
    target.write_text("precious")
    proc = run_cli("--out", target, check=False)
    assert_user_error(proc, "--out", "is a file")
    assert target.read_text() == "precious"


def test_foreign_folder_is_refused_and_kept(tmp_path):
    (tmp_path / "mine.txt").write_text("precious")
    proc = run_cli("--out", tmp_path, check=False)
    assert_user_error(proc, "--out", "not a stillbox-gen dataset")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.txt"]


def test_dataset_with_other_parameters_is_not_mixed(tmp_path):
    """Resuming into a folder made with another seed is refused before anything changes."""
    out = tmp_path / "ds"
    out.mkdir()
    info = {"fingerprint": "0000", "preset": "stillbox", "seed": 1, "scenes": 1}
    (out / "dataset.json").write_text(json.dumps(info))
    proc = run_cli("--out", out, "--seed", "2", check=False)
    assert_user_error(proc, "--out", "other parameters")
    assert json.loads((out / "dataset.json").read_text()) == info


def test_validate_and_preview_refuse_missing_dataset(tmp_path):
    assert_user_error(run_cli("validate", tmp_path / "nope", check=False), "nope")
    assert_user_error(run_cli("preview", tmp_path, check=False), "manifest.parquet")


def test_validate_reports_problems_by_file(tmp_path):
    (tmp_path / "dataset.json").write_text("{not json")
    proc = run_cli("validate", tmp_path, check=False)
    assert proc.returncode == 1
    assert "dataset.json" in proc.stdout


@pytest.mark.parametrize("value", ["2/2", "1", "a/b", "0/0", "-1/3"])
def test_bad_shard_is_refused_before_any_write(tmp_path, value):
    proc = run_cli("--shard", value, "--out", tmp_path / "x", check=False)
    assert proc.returncode == 2 and "--shard" in proc.stderr
    assert not (tmp_path / "x").exists()


def test_unknown_bench_config_is_refused():
    proc = run_cli("bench", "--configs", "default,ultra", check=False)
    assert proc.returncode == 2 and "--configs: unknown ultra" in proc.stderr
