"""``stillbox-bench infer`` end to end on a tiny real network and a real (synthetic) video: the
files it writes, the displacement scaling, poses vs constant speed, folder vs video, hovering
frames, one-line errors before anything is written, and the crop geometry on numbers.

The video is a smooth random texture panning 1 px per frame (64×64, 8 frames): the rendered test
datasets have 10-frame scenes but need Blender, and this file must stay fast.
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import invoke_main

from benchmark import cli
from benchmark.core import registry
from benchmark.core.footage import (
    Crop,
    constant_speed_positions,
    crop_box,
    focal_px,
    read_poses,
)
from benchmark.core.multishift import displacements
from benchmark.engine.network import depth_network

FRAMES, SIZE, FPS = 8, 64, 10.0


def _checkpoint(path: Path, name: str, **changes) -> Path:
    """A checkpoint as Trainer.checkpoint writes it, of a freshly initialised registry network;
    ``changes`` replace entries (None removes one)."""
    torch.manual_seed(0)
    model = registry.build_model(name)
    ck = {
        "model": model.state_dict(),
        "model_name": name,
        "nominal_displacement": 0.3,
        "shift": 3,
        "config": {"data": str(path.parent / "no-dataset")},
        "state": {"step": 0},
        "camera": {"width": SIZE, "height": SIZE, "fov_deg": 90.0},
    }
    ck.update(changes)
    torch.save({k: v for k, v in ck.items() if v is not None}, path)
    return path


def _frames(width: int = SIZE, height: int = SIZE) -> list[np.ndarray]:
    """FRAMES RGB frames of a smooth random texture panning 1 px per frame."""
    rng = np.random.default_rng(0)
    texture = cv2.resize(
        rng.integers(0, 256, (height // 4, width // 4 + 4, 3), dtype=np.uint8),
        (width + 16, height),
        interpolation=cv2.INTER_CUBIC,
    )
    return [np.ascontiguousarray(texture[:, k : k + width]) for k in range(FRAMES)]


def _write_video(path: Path, frames: list[np.ndarray], fourcc: str) -> Path:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), FPS, (w, h))
    for f in frames:
        writer.write(f[..., ::-1].copy())
    writer.release()
    return path


GARBLED_AT = 3  # the first frame of the "garbled" video that does not decode


def _garble(path: Path, frame: int) -> Path:
    """Spoil an MP4's sample-size table entry of ``frame``: frames before it decode, the
    container still lists every frame."""
    data = bytearray(path.read_bytes())
    entries = data.find(b"stsz") + 16  # tag, version+flags, sample size, count, then entries
    data[entries + 4 * frame : entries + 4 * frame + 4] = b"\x7f\xff\xff\xff"
    path.write_bytes(bytes(data))
    return path


def _write_folder(path: Path, frames: list[np.ndarray]) -> Path:
    path.mkdir()
    for k, f in enumerate(frames):
        cv2.imwrite(str(path / f"frame_{k:03d}.png"), f[..., ::-1])
    return path


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("infer")
    frames = _frames()
    (d / "notes.txt").write_text("not a video")
    (d / "empty").mkdir()
    return {
        "ckpt": _checkpoint(d / "tiny.pt", "depthnet-tiny"),
        "flow_ckpt": _checkpoint(d / "flow.pt", "flownets-flow-tiny"),
        "mp4": _write_video(d / "pan.mp4", frames, "mp4v"),
        "lossless": _write_video(d / "pan.avi", frames, "FFV1"),
        "folder": _write_folder(d / "pngs", frames),
        "narrow": _write_folder(d / "narrow", _frames(96, 80)),
        "garbled": _garble(_write_video(d / "garbled.mp4", frames, "mp4v"), GARBLED_AT),
        "text": d / "notes.txt",
        "empty": d / "empty",
        "dir": d,
    }


def infer(files: dict, out: Path, *args: object, ok: bool = True):
    proc = invoke_main(cli.main, "infer", "--ckpt", files["ckpt"], "--out", out, "--quiet", *args)
    if ok:
        assert proc.returncode == 0, proc.stderr
    return proc


def depths(out: Path) -> np.ndarray:
    return np.stack([np.load(p) for p in sorted((out / "depth").glob("*.npy"))])


def test_video_end_to_end(files, tmp_path):
    out = tmp_path / "out"
    proc = infer(files, out, "--input", files["mp4"], "--speed", 3, "--shifts", 2)
    assert proc.stderr == ""
    assert f"{FRAMES - 1} of {FRAMES} frames with depth" in proc.stdout
    names = sorted(p.name for p in (out / "depth").iterdir())
    assert names == [f"{t:06d}.npy" for t in range(1, FRAMES)]  # frame 0 has none
    d = depths(out)
    assert d.shape == (FRAMES - 1, SIZE, SIZE) and d.dtype == np.float32
    assert np.isfinite(d).all() and (d > 0).all()
    assert len(list((out / "depth_png").glob("*.png"))) == FRAMES - 1
    assert cv2.imread(str(out / "depth_png" / "000001.png")).shape == (SIZE, SIZE, 3)
    cap = cv2.VideoCapture(str(out / "preview.mp4"))
    shown = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        assert frame.shape == (SIZE, 2 * SIZE, 3)  # frame | depth colours
        shown += 1
    assert shown == FRAMES - 1
    s = json.loads((out / "summary.json").read_text())
    assert (s["frames_in"], s["frames_with_depth"], s["frames_without_motion"]) == (8, 7, 0)
    assert s["model"] == "depthnet-tiny" and s["nominal_displacement_m"] == 0.3
    assert s["preview_fps"] == pytest.approx(FPS)
    assert s["camera"]["crop"] == {"x": 0, "y": 0, "width": SIZE, "height": SIZE}
    assert s["camera"]["fov_factor"] == 1.0
    assert sum(s["shifts_histogram"].values()) >= FRAMES - 1
    assert s["fps_network"] > 0 and s["fps_loop"] > 0 and s["max_shift"] == 8
    rows = list(csv.DictReader((out / "frames.csv").open()))
    assert [r["status"] for r in rows] == ["first frame (no earlier frame)"] + ["depth"] * 7
    # the first pair aims at d0 = 0.3 m: 3 m/s at 10 frames/s is 0.3 m per frame -> shift 1
    assert rows[1]["shifts"] == "1" and float(rows[1]["d_opt_m"]) == pytest.approx(0.3)
    assert float(rows[1]["mean_depth_m"]) == pytest.approx(d[0].mean(), rel=1e-4)
    assert not list(out.parent.glob(".out.tmp-*"))


def test_depth_is_proportional_to_speed(files, tmp_path):
    """Same pairs (--fixed-shift 1), twice the speed: exactly twice the depth (eq. 6.1)."""
    a, b = tmp_path / "a", tmp_path / "b"
    common = ("--input", files["folder"], "--fps", FPS, "--fixed-shift", 1)
    infer(files, a, *common, "--speed", 2)
    infer(files, b, *common, "--speed", 4, "--depth-format", "exr")
    from stillbox_gen.formats import read_depth_exr

    exr = np.stack([read_depth_exr(p) for p in sorted((b / "depth").glob("*.exr"))])
    assert np.allclose(exr, 2 * depths(a), rtol=1e-5)


def test_poses_equal_constant_speed(files, tmp_path):
    """Positions along a diagonal at 3 m/s, and constant velocities with a t column, give the
    depth of --speed 3 (adaptive shifts, 2 clusters)."""
    speed = tmp_path / "speed"
    infer(files, speed, "--input", files["folder"], "--fps", FPS, "--speed", 3, "--shifts", 2)
    step = 3 / FPS / math.sqrt(2)  # metres per frame along x and along z
    xyz = tmp_path / "xyz.csv"
    xyz.write_text("frame,x,y,z\n" + "".join(f"{k},{k * step},0,{k * step}\n" for k in range(8)))
    vel = tmp_path / "vel.csv"
    vel.write_text("t,vx,vy,vz\n" + "".join(f"{k / FPS},0,-3,0\n" for k in range(8)))
    for name, poses, fps in (("xyz", xyz, ("--fps", FPS)), ("vel", vel, ())):
        out = tmp_path / name
        infer(files, out, "--input", files["folder"], "--poses", poses, "--shifts", 2, *fps)
        assert np.allclose(depths(out), depths(speed), rtol=1e-5), name
    summary = json.loads((tmp_path / "vel" / "summary.json").read_text())
    assert summary["preview_fps"] == pytest.approx(FPS)  # from the t column


def test_folder_equals_lossless_video(files, tmp_path):
    infer(files, tmp_path / "f", "--input", files["folder"], "--fps", FPS, "--speed", 3)
    infer(files, tmp_path / "v", "--input", files["lossless"], "--speed", 3)
    assert np.array_equal(depths(tmp_path / "f"), depths(tmp_path / "v"))


def test_hovering_frames_and_narrow_video(files, tmp_path):
    """Frames 1 and 2 hover at the start position (no shift has any motion): no depth, counted.
    The 96x80 video at the training 90° is narrower vertically: one warning line, factor 5/6."""
    poses = tmp_path / "hover.csv"
    xs = [0, 0, 0, 0.3, 0.6, 0.9, 1.2, 1.5]
    poses.write_text("x,y,z\n" + "".join(f"{x},0,0\n" for x in xs))
    out = tmp_path / "out"
    proc = infer(files, out, "--input", files["narrow"], "--poses", poses, "--fps", FPS)
    s = json.loads((out / "summary.json").read_text())
    assert (s["frames_with_depth"], s["frames_without_motion"]) == (5, 2)
    assert sorted(p.name for p in (out / "depth").iterdir())[0] == "000003.npy"
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("stillbox-bench: warning: ")
    assert "0.833" in lines[0]
    assert s["camera"]["crop"] == {"x": 8, "y": 0, "width": 80, "height": 80}


def _bad_csv(d: Path, name: str, text: str) -> Path:
    (d / name).write_text(text)
    return d / name


ERRORS = [
    # (arguments, flag named in the one error line)
    (("--speed", 3), "--input"),
    (("--input", "{dir}/missing.mp4", "--speed", 3), "--input"),
    (("--input", "{text}", "--speed", 3), "--input"),
    (("--input", "{empty}", "--speed", 3, "--fps", 10), "--input"),
    (("--input", "{mp4}"), "--speed"),
    (("--input", "{mp4}", "--speed", 3, "--poses", "{dir}/x.csv"), "--speed"),
    (("--input", "{mp4}", "--speed", 0), "--speed"),
    (("--input", "{mp4}", "--speed", -2), "--speed"),
    (("--input", "{mp4}", "--speed", "nan"), "--speed"),
    (("--input", "{folder}", "--speed", 3), "--fps"),
    (("--input", "{mp4}", "--speed", 3, "--shifts", 0), "--shifts"),
    (("--input", "{mp4}", "--speed", 3, "--shifts", 5), "--shifts"),
    (("--input", "{mp4}", "--speed", 3, "--res", "100x64"), "--res"),
    (("--input", "{mp4}", "--speed", 3, "--res", "64000x64000"), "--res"),
    (("--input", "{mp4}", "--speed", 3, "--fixed-shift", 1000), "--fixed-shift"),
    (("--input", "{mp4}", "--speed", 3, "--fixed-shift", FRAMES), "--fixed-shift"),
    (("--input", "{mp4}", "--speed", 3, "--fixed-shift", 5, "--max-shift", 4), "--fixed-shift"),
    (("--input", "{garbled}", "--speed", 3), "--input"),
    (("--input", "{mp4}", "--speed", 3, "--fov", 200), "--fov"),
    (("--input", "{mp4}", "--speed", 3, "--beta-mean", 0.9), "--beta-mean"),
    (("--input", "{mp4}", "--speed", 3, "--ckpt", "{flow_ckpt}"), "--ckpt"),
    (("--input", "{mp4}", "--poses", "{short_csv}"), "--poses"),
    (("--input", "{mp4}", "--poses", "{bad_csv}"), "--poses"),
    (("--input", "{mp4}", "--poses", "{header_csv}"), "--poses"),
]


@pytest.mark.parametrize(
    ("args", "flag"), ERRORS, ids=[f"{f}-{i}" for i, (_, f) in enumerate(ERRORS)]
)
def test_errors_are_one_line_before_writing(files, tmp_path, args, flag):
    paths = {k: str(v) for k, v in files.items()}
    paths["short_csv"] = str(_bad_csv(tmp_path, "s.csv", "x,y,z\n0,0,0\n0.1,0,0\n"))
    rows = "".join(f"{k * 0.1},0,0\n" for k in range(8)).replace("0.2,0,0", "0.2,abc,0")
    paths["bad_csv"] = str(_bad_csv(tmp_path, "b.csv", "x,y,z\n" + rows))
    paths["header_csv"] = str(_bad_csv(tmp_path, "h.csv", "a,b,c\n1,2,3\n"))
    out = tmp_path / "out"
    argv = [str(a).format(**paths) for a in args]
    if "--ckpt" in argv:  # replaces the default checkpoint
        k = argv.index("--ckpt")
        ckpt = argv.pop(k + 1)
        argv.pop(k)
        proc = invoke_main(cli.main, "infer", "--ckpt", ckpt, "--out", out, "--quiet", *argv)
    else:
        proc = infer(files, out, *argv, ok=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("stillbox-bench: error: "), proc.stderr
    assert flag in lines[0], lines[0]
    if "bad_csv" in str(args):
        assert "row 4, column 'y'" in lines[0]
    assert not out.exists()
    assert not list(tmp_path.glob(".out.tmp-*"))


def test_garbled_video_gives_both_frame_counts(files, tmp_path):
    """A video decoding fewer frames than its container lists is refused (not cut short
    silently): one line with both counts, nothing written."""
    assert cv2.VideoCapture(str(files["garbled"])).get(cv2.CAP_PROP_FRAME_COUNT) == FRAMES
    out = tmp_path / "out"
    proc = infer(files, out, "--input", files["garbled"], "--speed", 3, ok=False)
    assert proc.returncode == 2, proc.stderr
    assert f"decodes {GARBLED_AT} of the {FRAMES} frames" in proc.stderr
    assert f"(frame {GARBLED_AT} fails)" in proc.stderr
    assert not out.exists() and not list(tmp_path.glob(".out.tmp-*"))


def test_garbled_video_error_is_the_only_line_on_stderr(files, tmp_path):
    """End to end (FFmpeg writes to file descriptor 2 itself, which CliRunner cannot see)."""
    env = {k: v for k, v in os.environ.items() if k != "OPENCV_FFMPEG_LOGLEVEL"}
    proc = subprocess.run(
        [sys.executable, "-m", "benchmark.cli", "infer", "--ckpt", files["ckpt"], "--input",
         files["garbled"], "--speed", "3", "--out", tmp_path / "out", "--quiet"],
        capture_output=True, text=True, env=env, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [proc.stderr.strip()], proc.stderr
    assert proc.stderr.startswith("stillbox-bench: error: --input:")


def test_out_must_be_new_or_empty(files, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    proc = infer(files, out, "--input", files["mp4"], "--speed", 3, ok=False)
    assert proc.returncode == 2 and "--out" in proc.stderr
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


def test_crop_box_numbers():
    """Training camera at 90°: f = 32 px at 64 px wide (64 at 128)."""
    assert focal_px(64, 90.0) == pytest.approx(32.0)
    assert focal_px(64, 90.0, focal=50.0) == 50.0
    # same field of view, twice the pixels: the whole frame
    assert crop_box(128, 128, 64, 64, 64.0, 32.0) == Crop(0, 0, 128, 128, 1.0)
    # wider video (200 px at f = 64): the central 128x128
    c = crop_box(200, 128, 64, 64, 64.0, 32.0)
    assert (c.x, c.y, c.width, c.height, c.factor) == (36, 0, 128, 128, 1.0)
    # 1080p at 90°, 128x64 output at 90°: 1920x960, centred vertically
    c = crop_box(1920, 1080, 128, 64, focal_px(1920, 90.0), focal_px(128, 90.0))
    assert (c.x, c.y, c.width, c.height, c.factor) == (0, 60, 1920, 960, 1.0)
    # 96x80 at 90° for a square 90° training camera: needs 96x96, the largest square is 80x80
    c = crop_box(96, 80, 64, 64, 48.0, 32.0)
    assert (c.x, c.y, c.width, c.height) == (8, 0, 80, 80)
    assert c.factor == pytest.approx(80 / 96)


def test_motion_numbers(tmp_path):
    p = constant_speed_positions(9.0, 30.0, 5)
    assert displacements(p, 4, 8).tolist() == pytest.approx([0.3, 0.6, 0.9, 1.2])
    assert displacements(p, 4, 2).tolist() == pytest.approx([0.3, 0.6])
    csv_path = tmp_path / "v.csv"
    csv_path.write_text("t,vx,vy,vz\n0,0,0,0\n1,2,0,0\n2,2,0,0\n")  # trapezoid: x = 0, 1, 3
    positions, times = read_poses(csv_path, 3, None)
    assert positions[:, 0].tolist() == pytest.approx([0, 1, 3])
    assert times.tolist() == [0, 1, 2]
    csv_path.write_text("vx,vy,vz\n0,0,0\n0,4,0\n0,4,0\n")  # no t: fps 2 -> y = 0, 1, 3
    assert read_poses(csv_path, 3, 2.0)[0][:, 1].tolist() == pytest.approx([0, 1, 3])


def test_clamped_network_outputs_stay_in_its_range(files, tmp_path):
    """A network trained on [10, 60] m: θ_max = 60 m, and at the nominal displacement (0.3 m per
    frame, shift 1) every depth is its clamped output, inside [10, 60] m."""
    ckpt = _checkpoint(tmp_path / "clamped.pt", "depthnet-tiny", depth_range=[10.0, 60.0])
    _, scale, info = depth_network(ckpt)
    assert (scale.theta_max, scale.d0, info["clamp"]) == (60.0, 0.3, (10.0, 60.0))
    out = tmp_path / "out"
    args = ("--input", files["folder"], "--fps", FPS, "--speed", 3, "--fixed-shift", 1)
    proc = invoke_main(cli.main, "infer", "--ckpt", ckpt, "--out", out, "--quiet", *args)
    assert proc.returncode == 0, proc.stderr
    d = depths(out)
    assert d.min() >= 10 - 1e-4 and d.max() <= 60 + 1e-4


def test_training_camera_sources(files, tmp_path):
    """No 'camera' in the checkpoint: its dataset's dataset.json (focal_px -> FOV); neither: a
    one-line error naming --ckpt and --train-fov, and --train-fov with --res then works."""
    data = tmp_path / "data"
    data.mkdir()
    camera = {"width": 128, "height": 64, "fov_deg": 90.0, "focal_px": 64 / math.tan(math.pi / 3)}
    (data / "dataset.json").write_text(json.dumps({"config": {"camera": camera}}))
    ckpt = _checkpoint(tmp_path / "a.pt", "depthnet-tiny", camera=None, config={"data": str(data)})
    info = depth_network(ckpt)[2]
    assert (info["width"], info["height"], info["clamp"]) == (128, 64, None)
    assert info["fov_deg"] == pytest.approx(120.0)  # 2·atan(64 / f) with f = 64 / tan(60°)
    lost = _checkpoint(tmp_path / "b.pt", "depthnet-tiny", camera=None)
    out = tmp_path / "out"
    args = ("--input", files["mp4"], "--speed", 3)
    proc = invoke_main(cli.main, "infer", "--ckpt", lost, "--out", out, "--quiet", *args)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert "--ckpt" in lines[0] and "--train-fov" in lines[0] and not out.exists()
    args += ("--train-fov", 90, "--res", "64x64")
    proc = invoke_main(cli.main, "infer", "--ckpt", lost, "--out", out, "--quiet", *args)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((out / "summary.json").read_text())["camera"]["train_fov_deg"] == 90


def test_rendered_scene_as_mp4_and_as_frames(tiny_dataset, files, tmp_path):
    """A generated scene written to an MP4 (cv2.VideoWriter) runs end to end; its lossless frames
    with --fixed-shift 3 at 0.1 m per frame give the depth `eval` computes for the pairs
    (t − 3, t) (the same network, scale and upsampling)."""
    from benchmark.core.data import load_scenes
    from benchmark.engine.evaluate import Method, predict
    from benchmark.engine.runner import eval_split

    scene = load_scenes(tiny_dataset, "test")[0]
    frames = [scene.load_rgb(f) for f in range(scene.frames)]
    mp4 = _write_video(tmp_path / "scene.mp4", frames, "mp4v")
    out = tmp_path / "mp4"
    infer(files, out, "--input", mp4, "--speed", 3, "--fps", 30, "--shifts", 2)
    assert len(list((out / "depth").glob("*.npy"))) == scene.frames - 1
    assert json.loads((out / "summary.json").read_text())["frames_with_depth"] == scene.frames - 1

    folder = _write_folder(tmp_path / "pngs", frames)
    out = tmp_path / "pngs-out"
    infer(files, out, "--input", folder, "--speed", 3, "--fps", 30, "--fixed-shift", 3)
    got = depths(out)[2:]  # frames 3..: the pairs (t - 3, t)
    model, _, _ = depth_network(files["ckpt"])
    _, _, pairs = eval_split(tiny_dataset, "test", 3, progress=False)
    mine = range(scene.frames - 3)  # the first scene's pairs (0, 3), (1, 4), ...
    assert [pairs.items[i] for i in mine] == [(0, f) for f in mine]
    batch = torch.utils.data.default_collate([pairs[i] for i in mine])
    with torch.no_grad():
        want = predict(Method(registry.DEPTH, model, 0.3), batch, torch.device("cpu"))["depth"]
    np.testing.assert_allclose(got, want.numpy(), rtol=1e-4, atol=1e-4)
