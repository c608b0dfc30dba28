"""stillbox_gen.live: frames rendered on demand by one persistent Blender worker, identical to
the generator's files for the same pose, and planar depth against an analytic box."""

from __future__ import annotations

import dataclasses
import os
import signal
import time

import numpy as np
import pytest

from stillbox_gen import camera, config, formats, layout
from stillbox_gen.config import DatasetConfig
from stillbox_gen.dataset import Dataset
from stillbox_gen.errors import ConfigError
from stillbox_gen.live import LiveRenderer, WorkerDied, WorkerHung
from stillbox_gen.record import SceneSpec, spec_from_record
from stillbox_gen.scene import sample_scene
from stillbox_gen.worker_setup import NO_BLENDER


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _check_scene_frames(live: LiveRenderer, ds: Dataset, index: int, frames) -> None:
    scene = ds.scene(index)
    live.load(SceneSpec.from_dict(spec_from_record(scene.record)))
    for f in frames:
        rgb, depth = live.render(scene.cam2world[f], frame=f)
        assert _same_bits(rgb, scene.load_rgb(f)), (index, f)
        assert _same_bits(depth, scene.load_depth(f)), (index, f)


@pytest.mark.render
@pytest.mark.parametrize("name", ["custom_dataset", "default_dataset"])
def test_live_frames_are_the_dataset_files_bit_for_bit(name, request):
    """A dataset's poses rendered live give its PNG and depth files' exact bits: photos of
    --textures, an off-centre K, non-square frames and per-frame rotations (custom_dataset), the
    bundled photos (default_dataset); scenes loaded one after the other in one worker, the first
    one again at the end (nothing of a scene stays behind in the worker)."""
    ds = Dataset(request.getfixturevalue(name))
    cfg = config.from_dict(ds.info["config"])
    first, second = ds.indices()[:2]
    with LiveRenderer(cfg, threads=1) as live:
        _check_scene_frames(live, ds, first, [0, 9, 4])
        _check_scene_frames(live, ds, second, [3])
        _check_scene_frames(live, ds, first, [7])


@pytest.mark.render
def test_frame_selects_the_path_shading_seed_of_that_frame(tmp_path):
    """Under "path" shading each frame has its own Cycles seed: frame f rendered live (in any
    order) is the generator's frame f bit for bit, and the same pose with another frame's seed
    is not."""
    from test_render import render_spec

    cfg = config.replace(
        DatasetConfig(seed=4),
        camera={"width": 24, "height": 24, "frames": 3},
        render={"shading": "path", "samples": 2},
    )
    spec = sample_scene(cfg, 0)
    render_spec(spec, cfg, tmp_path)
    files = [formats.read_rgb(tmp_path / layout.rgb_name(0, f)) for f in range(3)]
    poses = spec.camera.cam2world
    with LiveRenderer(cfg, threads=1) as live:
        live.load(spec)
        for f in (2, 0, 1):
            assert _same_bits(live.render(poses[f], frame=f)[0], files[f]), f
        assert not np.array_equal(live.render(poses[1], frame=0)[0], files[1])


# An empty box (no primitives), walls at these distances from the origin (m): the planar depth
# of every pixel follows from the pose and K alone.
BOX_CENTRE = np.array([0.5, -1.0, 2.0])
BOX_HALF = np.array([6.0, 9.0, 4.0])


def _empty_box_scene(width: int, height: int) -> SceneSpec:
    cfg = config.replace(DatasetConfig(seed=1), camera={"width": width, "height": height})
    spec = sample_scene(cfg, 0)
    box = dataclasses.replace(spec.box, center=BOX_CENTRE.tolist(), half_extents=BOX_HALF.tolist())
    return dataclasses.replace(spec, primitives=[], box=box)


def _box_depth(K: np.ndarray, cam2world: np.ndarray, width: int, height: int) -> np.ndarray:
    """Planar depth (m) of the inside of the box seen from ``cam2world`` (OpenCV axes): the ray
    through pixel (u, v) is R K^-1 (u, v, 1), which has depth 1, so the depth is the ray
    parameter of the nearest wall hit."""
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    pix = np.stack([u, v, np.ones_like(u)], axis=-1).astype(np.float64)
    rays = pix @ np.linalg.inv(K).T @ cam2world[:3, :3].T  # (H, W, 3) world
    origin = cam2world[:3, 3]
    with np.errstate(divide="ignore"):
        far = BOX_CENTRE + np.sign(rays) * BOX_HALF  # the wall each ray goes towards, per axis
        t = (far - origin) / rays
    return np.where(np.isfinite(t), t, np.inf).min(axis=-1)


def _pose(yaw_deg: float, pitch_deg: float, position) -> np.ndarray:
    """OpenCV cam2world looking along world +X turned by ``yaw`` about +Z, then pitched up."""
    look_x = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # x, y, z columns
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1.0]])
    ry = np.array(
        [[np.cos(pitch), 0, -np.sin(pitch)], [0, 1.0, 0], [np.sin(pitch), 0, np.cos(pitch)]]
    )
    return camera.pose_matrix(rz @ ry @ look_x, position)


@pytest.mark.render
def test_live_depth_of_an_empty_box_is_the_analytic_one():
    """Facing a wall squarely the planar depth is one constant (the wall's distance); at other
    poses each pixel's depth is that of its ray's first wall (relative error 1e-4: Cycles
    intersects in float32, 3.5e-5 measured, RENDER_NOTES.md)."""
    w, h = 24, 16
    spec = _empty_box_scene(w, h)
    K = np.asarray(spec.camera.K)
    with LiveRenderer(DatasetConfig(), threads=1) as live:
        live.load(spec)
        square = _pose(0.0, 0.0, [1.5, -1.0, 2.0])
        rgb, depth = live.render(square)
        assert rgb.shape == (h, w, 3) and rgb.dtype == np.uint8 and rgb.max() > 0
        assert depth.shape == (h, w) and depth.dtype == np.float32
        wall = BOX_CENTRE[0] + BOX_HALF[0] - 1.5  # 5.0 m
        np.testing.assert_allclose(depth, wall, rtol=1e-4)
        for yaw, pitch, position in [(30.0, 10.0, [0.0, 1.0, 1.0]), (-120.0, -25.0, [2, -3, 4])]:
            pose = _pose(yaw, pitch, position)
            _, depth = live.render(pose)
            np.testing.assert_allclose(depth, _box_depth(K, pose, w, h), rtol=1e-4)


@pytest.mark.render
def test_a_dead_worker_is_an_error_not_a_hang():
    spec = _empty_box_scene(8, 8)
    live = LiveRenderer(DatasetConfig(), threads=1)
    try:
        live.load(spec)
        live.render(_pose(0.0, 0.0, [0.0, 0.0, 0.0]))
        os.kill(live.pid, signal.SIGKILL)
        t0 = time.monotonic()
        with pytest.raises(WorkerDied, match="died"):
            live.render(_pose(0.0, 0.0, [0.0, 0.0, 0.0]))
        assert time.monotonic() - t0 < 10
        with pytest.raises(WorkerDied):  # and stays an error
            live.load(spec)
        assert not os.path.exists(live._folder)  # its temp folder (Blender's too) is gone
    finally:
        live.close()


@pytest.mark.render
def test_a_hung_worker_is_stopped_after_the_timeout():
    """A worker that lives but does not answer (here: stopped with SIGSTOP) is killed after
    ``timeout`` seconds and the request raises WorkerHung naming it; later calls raise too."""
    spec = _empty_box_scene(8, 8)
    live = LiveRenderer(DatasetConfig(), threads=1)  # Blender's start may be slow on a busy CPU
    try:
        live.load(spec)
        live.render(_pose(0.0, 0.0, [0.0, 0.0, 0.0]))
        live.timeout = 2.0
        os.kill(live.pid, signal.SIGSTOP)
        t0 = time.monotonic()
        with pytest.raises(WorkerHung, match=r"no answer to a 'render' request in 2 s"):
            live.render(_pose(0.0, 0.0, [0.0, 0.0, 0.0]))
        assert 2.0 <= time.monotonic() - t0 < 10
        assert live._proc.poll() is not None  # killed, not left stopped
        with pytest.raises(WorkerHung):
            live.load(spec)
        assert not os.path.exists(live._folder)
    finally:
        live.close()


@pytest.mark.render
def test_the_worker_dies_with_a_killed_driver(tmp_path):
    """kill -9 of the process holding a LiveRenderer ends its Blender worker too (its temp
    folder stays, without frames, holding Blender's session folder)."""
    import subprocess
    import sys

    from conftest import alive_of, descendants

    code = (
        "from stillbox_gen.config import DatasetConfig\n"
        "from stillbox_gen.live import LiveRenderer\n"
        "live = LiveRenderer(DatasetConfig(), threads=1)\n"
        "print(live.pid, flush=True)\n"
        "import time; time.sleep(600)\n"
    )
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    cmd = [sys.executable, "-c", code]
    driver = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env=env)
    try:
        worker = int(driver.stdout.readline())
        procs = {p: t for p, t in descendants(driver.pid).items() if p == worker}
        assert procs, "the worker is not a child of the driver"
    finally:
        driver.kill()
        driver.wait()
    deadline = time.monotonic() + 10
    while alive_of(procs) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert alive_of(procs) == []
    folders = list(tmp_path.glob("stillbox-live-*"))
    assert len(folders) == 1 and not list(folders[0].glob("*.exr"))


@pytest.mark.render
def test_requests_the_driver_refuses():
    with LiveRenderer(DatasetConfig(), threads=1) as live:
        with pytest.raises(RuntimeError, match="no scene loaded"):
            live.render(np.eye(4))
        live.load(_empty_box_scene(8, 8))
        with pytest.raises(ValueError, match="4x4"):
            live.render(np.eye(3))
        with pytest.raises(ValueError, match="4x4"):
            live.render(np.full((4, 4), np.nan))
        assert live.render(_pose(0.0, 0.0, [0.0, 0.0, 0.0]))[1].shape == (8, 8)  # still works


def test_an_unknown_device_is_refused_before_a_worker_starts():
    with pytest.raises(ConfigError, match="--device"):
        LiveRenderer(DatasetConfig(), device="tpu")
    with pytest.raises(ValueError, match="timeout must be > 0 seconds"):
        LiveRenderer(DatasetConfig(), timeout=0)


def test_without_blender_one_line_naming_the_extra(monkeypatch):
    from test_packaging import _without_bpy

    _without_bpy(monkeypatch)
    with pytest.raises(ConfigError) as e:
        LiveRenderer(DatasetConfig())
    assert str(e.value) == NO_BLENDER and "[gen]" in str(e.value)
