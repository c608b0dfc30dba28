"""Bad input: one-line error naming the flag or file, exit code 2, nothing written.

Most cases run ``cli.main`` in this process (conftest.invoke_cli: click's CliRunner); a few run
the command in a subprocess, end to end (conftest.run_cli).
"""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest
from conftest import CliResult, assert_user_error, invoke_cli, run_cli

from stillbox_gen import config


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
        (["--ray-address", "h:1"], ["--ray-address: only with --backend ray"]),
        (["--res", ""], ["--res: expected N or WxH in pixels, got ''"]),
        (["--res", "100000"], ["--res: must be at most 8,192 pixels, got 100,000"]),
        (["--samples", "1000000000000"], ["--samples: must be at most 4,096 samples per pixel"]),
        (["--threads", "100000000000"], ["--threads: must be at most 1,024 threads"]),
        (["--scenes", "1000000000000"], ["--scenes: must be at most 10,000,000 scenes"]),
    ],
)
def test_bad_flag_is_a_one_line_error_and_writes_nothing(tmp_path, args, words):
    out = tmp_path / "out"
    assert_user_error(invoke_cli(*args, "--out", out), *words)
    assert not out.exists()


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--res", "big"], ["--res", "big"]),
        (["--no-such-flag"], ["--no-such-flag"]),
        (["validate", "{tmp}/nope"], ["nope"]),
    ],
)
def test_end_to_end_a_bad_command_exits_2_with_one_line_and_writes_nothing(tmp_path, args, words):
    """The real process: exit status 2, a single stderr line, nothing on stdout, nothing written."""
    out = tmp_path / "out"
    argv = [a.format(tmp=tmp_path) for a in args]
    proc = run_cli(*argv, *(["--out", out] if argv[0] != "validate" else []), check=False)
    assert_user_error(proc, *words)
    assert proc.stdout == ""
    assert sorted(tmp_path.iterdir()) == []


def test_scenes_beyond_the_limit_leave_no_folder_that_refuses_later_runs(tmp_path):
    """`--scenes 1e12` used to write dataset.json first, and every later run of the folder was
    refused as "fewer than the 1000000000000 scenes already in"."""
    out = tmp_path / "out"
    assert_user_error(invoke_cli("--scenes", 10**12, "--out", out), "--scenes: must be at most")
    assert not out.exists()


@pytest.mark.parametrize(
    "args",
    [
        ["--out", ""],
        ["stats", "{tmp}", "--out", ""],
        ["preview", "{tmp}", "--out", ""],
        ["merge", "", "{tmp}"],
        ["--textures", "", "--out", "{tmp}/out"],
        ["validate", ""],
        ["index", ""],
    ],
)
def test_empty_path_is_refused_not_the_current_folder(tmp_path, monkeypatch, args):
    """Path("") is the current folder: `--out ""` used to render into it."""
    monkeypatch.chdir(tmp_path)
    argv = [a.format(tmp=tmp_path) for a in args]
    assert_user_error(invoke_cli(*argv), "must be a path, got ''")
    assert sorted(tmp_path.iterdir()) == []


@pytest.mark.blender  # generate/bench check Blender before the folder
def test_out_whose_dataset_json_leads_outside_is_refused(tmp_path):
    """--out's dataset.json as a symlink to a file outside: refused, that file left alone."""
    outside = tmp_path / "elsewhere.json"
    outside.write_text("{}")
    out = tmp_path / "out"
    out.mkdir()
    (out / "dataset.json").symlink_to(outside)
    result = invoke_cli("--out", out)
    assert_user_error(result, f"--out: '{out}': 'dataset.json' leads through a symlink")
    assert outside.read_text() == "{}" and sorted(p.name for p in out.iterdir()) == ["dataset.json"]


def test_preset_that_is_not_utf8_is_one_line(tmp_path):
    preset = tmp_path / "latin1.toml"
    preset.write_bytes(b"# caf\xe9\n[camera]\n")
    out = tmp_path / "out"
    assert_user_error(invoke_cli("--preset", preset, "--out", out), f"preset {preset}: not UTF-8")
    assert not out.exists()


def test_preset_photos_outside_a_plain_name_are_refused_before_writing(tmp_path):
    """textures_dir = "/etc" with texture_files = ["passwd"] used to be accepted and fail late."""
    preset = tmp_path / "etc.toml"
    preset.write_text('[materials]\ntextures_dir = "/etc"\ntexture_files = ["passwd"]\n')
    out = tmp_path / "out"
    result = invoke_cli("--preset", preset, "--out", out)
    assert_user_error(result, f"preset {preset}: materials.texture_files '/etc/passwd' cannot be")
    assert not out.exists()


@pytest.mark.parametrize("value", ["nan", "inf", "0"])
def test_preview_max_depth_must_be_positive_and_finite(default_dataset, tmp_path, value):
    out = tmp_path / "sheet.png"
    result = invoke_cli("preview", default_dataset, "--out", out, "--max-depth", value)
    assert_user_error(result, f"--max-depth: must be a positive finite number, got {float(value)}")
    assert not out.exists()


def test_preview_out_that_is_a_folder_is_refused_and_leaves_nothing(default_dataset, tmp_path):
    """It used to end in a traceback and leave `.outdir.tmp.png` beside the folder."""
    folder = tmp_path / "outdir"
    folder.mkdir()
    assert_user_error(invoke_cli("preview", default_dataset, "--out", folder), "--out", "folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["outdir"]
    assert list(folder.iterdir()) == []
    missing = tmp_path / "no" / "sheet.png"
    assert_user_error(invoke_cli("preview", default_dataset, "--out", missing), "--out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["outdir"]


def test_texture_folder_without_images_is_refused(tmp_path):
    empty = tmp_path / "photos"
    empty.mkdir()
    (empty / "readme.txt").write_text("no images here")
    result = invoke_cli("--textures", empty, "--out", tmp_path / "out")
    assert_user_error(result, "--textures", "no readable images")
    assert not (tmp_path / "out").exists()


def test_bad_preset_file_names_file_and_key(tmp_path):
    preset = tmp_path / "mine.toml"
    preset.write_text("[camera]\nfov = 60\n")
    result = invoke_cli("--preset", preset, "--out", tmp_path / "out")
    assert_user_error(result, "mine.toml", "camera.fov")


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
    assert_user_error(invoke_cli("--preset", preset, "--out", out), f"preset {preset}: {message}")
    assert not out.exists()


def test_truncated_texture_file_is_refused(tmp_path):
    """A JPEG whose data is cut off (valid header) is named, with no decoder noise: end to end,
    since OpenCV's decoders write to file descriptor 2, which only a subprocess captures."""
    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    ok, jpeg = cv2.imencode(".jpg", cv2.resize(rng.integers(0, 256, (8, 8, 3), np.uint8), (64, 64)))
    (photos / "whole.jpg").write_bytes(jpeg.tobytes())
    (photos / "cut.jpg").write_bytes(jpeg.tobytes()[: len(jpeg) // 2])
    proc = run_cli("--textures", photos, "--out", tmp_path / "out", check=False)
    assert_user_error(proc, f"--textures: '{photos / 'cut.jpg'}' cannot be decoded")
    assert not (tmp_path / "out").exists()


@pytest.mark.blender  # generate/bench check Blender before the folder
def test_output_path_that_is_a_file_is_refused_and_kept(tmp_path):
    target = tmp_path / "afile"
    target.write_text("precious")
    assert_user_error(invoke_cli("--out", target), "--out", "is a file")
    assert target.read_text() == "precious"


@pytest.mark.blender  # generate/bench check Blender before the folder
def test_foreign_folder_is_refused_and_kept(tmp_path):
    (tmp_path / "mine.txt").write_text("precious")
    assert_user_error(invoke_cli("--out", tmp_path), "--out", "not a stillbox-gen dataset")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.txt"]


@pytest.mark.blender  # generate/bench check Blender before the folder
def test_dataset_with_other_parameters_is_not_mixed(tmp_path):
    """Resuming into a folder made with another seed is refused before anything changes."""
    out = tmp_path / "ds"
    out.mkdir()
    info = {"fingerprint": "0000", "preset": "stillbox", "seed": 1, "scenes": 1}
    (out / "dataset.json").write_text(json.dumps(info))
    assert_user_error(invoke_cli("--out", out, "--seed", "2"), "--out", "other parameters")
    assert json.loads((out / "dataset.json").read_text()) == info


def test_validate_and_preview_refuse_missing_dataset(tmp_path):
    assert_user_error(invoke_cli("validate", tmp_path / "nope"), "nope")
    assert_user_error(invoke_cli("preview", tmp_path), "manifest.parquet")


def test_validate_reports_problems_by_file(tmp_path):
    (tmp_path / "dataset.json").write_text("{not json")
    result = invoke_cli("validate", tmp_path)
    assert result.returncode == 1
    assert "dataset.json" in result.stdout


@pytest.mark.parametrize("value", ["2/2", "1", "a/b", "0/0", "-1/3"])
def test_bad_shard_is_refused_before_any_write(tmp_path, value):
    assert_user_error(invoke_cli("--shard", value, "--out", tmp_path / "x"), "--shard")
    assert not (tmp_path / "x").exists()


def test_bench_resolution_beyond_the_limit_is_refused():
    result = invoke_cli("bench", "--res", "100000:1")
    assert_user_error(result, "--res: must be at most 8,192 pixels, got 100,000 ('100000:1')")


def test_validate_refuses_a_scene_count_beyond_the_limit_without_looping(tmp_path):
    """A dataset.json claiming 10^12 scenes is reported at once, not walked chunk by chunk."""
    from stillbox_gen.writer import dataset_info

    info = dataset_info(config.DatasetConfig(), 10**12, complete=True)
    info.update(frames=10**13, rejected_scenes=0, split_scenes={}, run={})
    (tmp_path / "dataset.json").write_text(json.dumps(info))
    result = invoke_cli("validate", tmp_path)
    assert result.returncode == 1
    assert "dataset.json: scenes must be at most 10,000,000 scenes" in result.stdout


def test_unknown_bench_config_is_refused():
    assert_user_error(invoke_cli("bench", "--configs", "default,ultra"), "--configs: unknown ultra")


@pytest.mark.parametrize(
    "value, message",
    [("-1", "--threads: must be >= 0, got -1"), ("2000", "--threads: must be at most 1,024")],
)
def test_bench_bad_threads_are_refused(value, message):
    assert_user_error(invoke_cli("bench", "--threads", value), message)


# ---------------------------------------------------------------- the in-process runner


def test_in_process_runner_lets_an_unexpected_exception_fail_the_test(monkeypatch, tmp_path):
    """A crash is not an exit code: it propagates with its traceback instead of passing."""

    def crash(name):
        raise TypeError("a bug")

    monkeypatch.setattr(config, "load_preset", crash)
    with pytest.raises(TypeError, match="a bug"):
        invoke_cli("--out", tmp_path / "out")


@pytest.mark.parametrize(
    "result",
    [
        CliResult(1, "", "stillbox-gen: error: --res: bad\n"),  # wrong exit code
        CliResult(2, "", "Traceback (most recent call last):\nstillbox-gen: error: x\n"),
        CliResult(2, "", "stillbox-gen: error: --res: bad\nsomething else\n"),  # two lines
        CliResult(2, "", "error: --res: bad\n"),  # not our prefix
    ],
)
def test_assert_user_error_refuses_anything_but_one_line_and_exit_2(result):
    with pytest.raises(AssertionError):
        assert_user_error(result, "--res")


def test_generate_help_shows_the_dataclass_defaults():
    """Help texts are generated from the dataclasses, not typed in."""
    from stillbox_gen.generate import RunOptions

    result = invoke_cli("generate", "--help")
    assert result.returncode == 0, result.stderr
    text = " ".join(result.stdout.split())
    cam, mats, render = config.CameraConfig, config.MaterialsConfig, config.RenderConfig
    run = {f.name: f.default for f in dataclasses.fields(RunOptions)}
    for expected in [
        f"WxH. [default: preset, {cam.width}]",
        f"field of view, degrees. [default: preset, {cam.fov_deg:g}]",
        f"Frames per scene. [default: preset, {cam.frames}]",
        f"per frame, metres. [default: preset, {cam.displacement:g}]",
        f"texture ratio {mats.texture_ratio:g}",
        f"patterns only). [default: preset, {mats.photos}]",
        f"noise std, degrees. [default: preset, {cam.rotation_noise_deg:g}]",
        f"default {render.samples},",
        f"RGB file format. [default: {render.image_format}]",
        f"[default: {','.join(f'{s:g}' for s in config.DatasetConfig.split)}]",
        f"Blender worker processes. [default: {run['workers']}]",
        f"--threads INTEGER Cycles threads per worker (0 = all cores). [default: {run['threads']}]",
        f"[default: {run['scene_timeout']}]",
    ]:
        assert expected in text, expected
