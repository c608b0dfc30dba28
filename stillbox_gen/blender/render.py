"""Worker-process side of rendering: one-time Cycles set-up, then one call per scene.

A worker process imports bpy once (about 0.75 s) and renders many scenes; the pool replaces it
after ``recycle_after`` scenes to bound memory. The frames of a scene are rendered by one
animation render (persistent data on: the scene is synced once, then only the camera moves; a
frame-change handler sets each frame's pose and seed) to temporary multilayer EXRs, read back and
written as 8-bit sRGB + float32 depth. The files are byte-identical to those of one still render
per frame (compared file by file when this replaced the stills), and a 64 px worker spends about
10 % less time per frame.

Each scene's statistics hold the wall and CPU seconds of its phases (stillbox_gen.phases): the
animation render is split per frame by Blender's render_pre, frame_change_post and render_post
handlers (:class:`_RenderClock`), and with ``WorkerSetup.profile`` Cycles' own time further into
sync, sampling and result by its render status messages (the render_stats handler).
"""

from __future__ import annotations

import os
import resource
import time
from pathlib import Path

import bpy
import cv2
import numpy as np

from .. import config, formats, layout, phases
from ..worker_setup import WorkerSetup
from . import build, devices

_STATE: dict = {}


def init_worker(setup: WorkerSetup, silence_stdout: bool = True) -> None:
    """Configure Cycles once per process; ``setup.device`` is CPU_DEVICE or one of
    config.GPU_BACKENDS (RuntimeError when Cycles finds no such device). The frame size is set
    per scene, from its CameraSpec (:func:`_set_frame_size`)."""
    render = setup.render
    if silence_stdout:  # Blender prints a line per saved file on stdout
        os.dup2(os.open(os.devnull, os.O_WRONLY), 1)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    cy = scene.cycles
    devices.use_device(setup.device)
    cy.samples = render.samples
    cy.use_adaptive_sampling = False
    cy.use_light_tree = render.light_tree
    # Box filter one pixel wide: a pixel is the mean of its samples over its own area (no blur
    # across neighbours), i.e. anti-aliasing by area integration.
    cy.pixel_filter_type = "BOX"
    cy.filter_width = 1.0
    cy.use_denoising = render.denoise
    cy.denoiser = "OPENIMAGEDENOISE"
    cy.denoising_prefilter = "FAST"
    direct = render.shading == "direct"
    cy.max_bounces = render.max_bounces
    cy.diffuse_bounces = 0 if direct else min(1, render.max_bounces)
    cy.glossy_bounces = render.max_bounces
    cy.transmission_bounces = 0
    cy.volume_bounces = 0
    cy.transparent_max_bounces = 0
    cy.caustics_reflective = False
    cy.caustics_refractive = False
    r = scene.render
    r.resolution_percentage = 100
    r.use_persistent_data = render.persistent
    r.use_motion_blur = False
    if setup.threads > 0:
        r.threads_mode = "FIXED"
        r.threads = setup.threads
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    layer = scene.view_layers[0]
    layer.use_pass_z = True
    layer.cycles.denoising_store_passes = False
    img = r.image_settings
    img.media_type = "MULTI_LAYER_IMAGE"
    img.file_format = "OPEN_EXR_MULTILAYER"
    img.color_depth = "16"  # the Z pass stays float32 in half-float EXRs
    img.exr_codec = "NONE"  # temporary files, read back at once: compressing them is wasted time
    _STATE.update(setup=setup, scenes=0, job=None, clock=None)
    _set_handler(bpy.app.handlers.frame_change_pre, _pose_frame, True)
    _set_handler(bpy.app.handlers.render_pre, _clock_render_pre, True)
    _set_handler(bpy.app.handlers.frame_change_post, _clock_frame_change_post, True)
    _set_handler(bpy.app.handlers.render_post, _clock_render_post, True)
    _set_handler(bpy.app.handlers.render_stats, _clock_render_stats, setup.profile)
    # wall and CPU s from process start to here: the first scene's statistics carry them
    _STATE["startup"] = [phases.process_age(), time.process_time()]


def _set_handler(handlers: list, handler, on: bool) -> None:
    """Register ``handler`` in Blender's handler list ``handlers`` once, or remove it."""
    if on and handler not in handlers:
        handlers.append(handler)
    elif not on and handler in handlers:
        handlers.remove(handler)


class _RenderClock:
    """The phases of one animation render (stillbox_gen.phases), from Blender's handler calls.

    Blender 5 calls, per frame f: render_pre, frame_change_pre (:func:`_pose_frame`),
    frame_change_post, then Cycles syncs, samples and hands the result over, the temporary EXR
    is written, then render_post; after the last frame it restores the scene's current frame
    (another frame change). Each call closes the running phase: render call to the first
    render_pre is ``render_setup``; render_pre to frame_change_post (and render_post to the next
    render_pre) ``frame_step``; frame_change_post to render_post ``cycles``; the last render_post
    to the end of the call ``render_finish``. With ``detail``, Cycles' status messages
    (render_stats: "... | Sample 0/4", "... | Finished") split ``cycles`` into ``cycles_sync``,
    ``cycles_sampling`` and ``cycles_result``, and ``cycles`` is their sum. A call out of that
    order (none seen) changes nothing: its time stays in the running phase.
    """

    def __init__(self, times: phases.PhaseTimes, last_frame: int, detail: bool):
        self.times, self.last_frame, self.detail = times, last_frame, detail
        self.phase: str | None = "render_setup"
        self.wall, self.cpu = phases.clocks()

    def switch(self, phase: str | None) -> None:
        """Close the running phase now and start ``phase`` (None: stop)."""
        wall, cpu = phases.clocks()
        if self.phase is not None:
            self.times.add(self.phase, wall - self.wall, cpu - self.cpu)
        self.phase, self.wall, self.cpu = phase, wall, cpu

    def render_pre(self) -> None:
        if self.phase in ("render_setup", "frame_step"):
            self.switch("frame_step")

    def frame_change_post(self) -> None:
        if self.phase == "frame_step":
            self.switch("cycles_sync" if self.detail else "cycles")

    def status(self, text: str) -> None:
        if self.phase == "cycles_sync" and "| Sample " in text:
            self.switch("cycles_sampling")
        elif self.phase == "cycles_sampling" and "| Finished" in text:
            self.switch("cycles_result")

    def render_post(self, frame: int) -> None:
        if self.phase is not None and self.phase.startswith("cycles"):
            self.switch("render_finish" if frame >= self.last_frame else "frame_step")

    def stop(self) -> None:
        """Close the running phase; with ``detail``, add ``cycles`` as the sum of its parts."""
        self.switch(None)
        if self.detail:
            parts = phases.CYCLES_PARTS
            wall = sum(self.times.wall.get(k, 0.0) for k in parts)
            cpu = sum(self.times.cpu.get(k, 0.0) for k in parts)
            self.times.add("cycles", wall, cpu)


@bpy.app.handlers.persistent
def _clock_render_pre(scene, depsgraph=None) -> None:
    if (clock := _STATE.get("clock")) is not None:
        clock.render_pre()


@bpy.app.handlers.persistent
def _clock_frame_change_post(scene, depsgraph=None) -> None:
    if (clock := _STATE.get("clock")) is not None:
        clock.frame_change_post()


@bpy.app.handlers.persistent
def _clock_render_post(scene, depsgraph=None) -> None:
    if (clock := _STATE.get("clock")) is not None:
        clock.render_post(scene.frame_current)


@bpy.app.handlers.persistent
def _clock_render_stats(text: str) -> None:
    if (clock := _STATE.get("clock")) is not None:
        clock.status(text)


@bpy.app.handlers.persistent
def _pose_frame(scene, depsgraph=None) -> None:
    """Frame-change handler: the camera pose and Cycles seed of the frame being rendered."""
    job = _STATE.get("job")
    f = scene.frame_current
    # the render also restores the scene's previous current frame at its end: not a job frame
    if job is None or not 0 <= f < len(job["poses"]):
        return
    build.set_camera_pose(job["camera"], job["poses"][f])
    set_seed(scene, job["seed"], f)


def set_seed(scene, scene_seed: int, frame: int) -> None:
    """The Cycles seed of frame ``frame`` of the scene of seed ``scene_seed`` (render_seed)."""
    seed = render_seed(scene_seed, frame, _STATE["setup"].render.shading)
    if scene.cycles.seed != seed:
        scene.cycles.seed = seed
        scene.update_tag()  # an animation render re-reads the seed only from a tagged scene


def _set_frame_size(scene, width: int, height: int) -> None:
    """Frame size in pixels, and the denoiser mode that follows from it, of the scene about to
    be rendered: from its CameraSpec, the one source of the resolution (its K was drawn for it)."""
    r = scene.render
    if (r.resolution_x, r.resolution_y) != (width, height):
        r.resolution_x, r.resolution_y = width, height
    quality = config.denoise_quality(_STATE["setup"].render.denoise_quality, width, height)
    if scene.cycles.denoising_quality != quality.upper():
        scene.cycles.denoising_quality = quality.upper()


def render_seed(scene_seed: int, frame: int, shading: str) -> int:
    """Cycles seed of a frame.

    "direct" shading draws no random light (see build.py), so the seed only places the samples
    inside each pixel. One seed per scene keeps that placement fixed on screen, like a
    supersampling grid: an unchanged view renders identically and sub-pixel motion changes
    pixels smoothly, where a per-frame seed would add frame-to-frame noise at every edge.
    "path" shading samples light at random: there a seed per frame keeps its noise from
    sticking to the screen while the camera moves.
    """
    if shading == "path":
        return int((scene_seed * 1_000_003 + frame * 7_919) % (2**31 - 1))
    return int(scene_seed % (2**31 - 1))


def load_scene(spec: dict):
    """Replace the worker's scene by the one of a SceneSpec dict, at the frame size of its
    CameraSpec; returns its camera object (posed per frame by build.set_camera_pose)."""
    scene = bpy.context.scene
    if scene.render.use_persistent_data:  # free the previous scene's cached render data, which
        scene.render.use_persistent_data = False  # otherwise grows RSS ~0.27 MB per scene
        scene.render.use_persistent_data = True
    _set_frame_size(scene, spec["camera"]["width"], spec["camera"]["height"])
    build.clear_scene()
    setup = _STATE["setup"]
    return build.build_scene(spec, setup.textures_dir, setup.render.shading)


def frame_arrays(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The RGB (H, W, 3) uint8 sRGB and planar depth (H, W) float32 m of a rendered multilayer
    EXR, exactly as the dataset's frame and depth files hold them."""
    rgb, depth = _channels(path)
    return formats.linear_to_srgb8(rgb), depth


def _channels(path: Path) -> tuple[np.ndarray, np.ndarray]:
    chans = formats.read_multilayer_exr(path)
    rgba = next(v for k, v in chans.items() if k.endswith("Combined"))
    depth = next(v for k, v in chans.items() if k.endswith("Depth.Z") or k.endswith("Depth"))
    return np.asarray(rgba[..., :3], dtype=np.float32), np.asarray(depth, dtype=np.float32)


def _imwrite(path: Path, img: np.ndarray, params: list[int]) -> None:
    """cv2.imwrite, raising OSError naming ``path`` when it fails (it only returns False)."""
    if not cv2.imwrite(str(path), img, params):
        raise OSError(f"cannot write '{path}'")


def _probe_bytes(render) -> int:
    """Bytes a frame needs on disk at most: its uncompressed temporary EXR (half RGBA, float
    depth: 12 bytes a pixel) and headers; check_space's probe size after a failed write."""
    return render.resolution_x * render.resolution_y * 16 + 65536


def render_scene(spec: dict, out_dir: str, image_format: str, legacy: bool) -> dict:
    """Render every frame of a SceneSpec dict into ``out_dir`` (a temporary folder).

    Files are named as in formats.py. Returns statistics: ``seconds`` and ``cpu_seconds`` (wall
    and CPU s of this call), ``build_seconds`` (wall s of the scene build), ``phases``
    ({phase name: [wall s, CPU s]}, stillbox_gen.phases; the first scene of a worker process
    also holds its ``startup``), ``process_cpu_seconds`` (the process's CPU s so far),
    ``peak_rss_mb``, ``pid``. When a file cannot be written or read back for lack of space,
    raises the OSError of a full disk (formats.is_disk_full): the run stops there instead of
    retrying the scene.
    """
    t0, c0 = phases.clocks()
    times = phases.PhaseTimes()
    if (startup := _STATE.get("startup")) is not None:  # removed once a scene succeeds
        times.add("startup", *startup)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = bpy.context.scene
    with times.measure("build"):
        cam = load_scene(spec)
    local = layout.local_index(spec["index"])
    # full-resolution chroma (4:4:4): 4:2:0 JPEGs differ from the PNGs by about 6/255 on average
    params = [
        cv2.IMWRITE_JPEG_QUALITY,
        95,
        cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
        cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444,
    ]
    poses = spec["camera"]["cam2world"]
    scene.frame_start, scene.frame_end = 0, len(poses) - 1
    scene.render.filepath = str(out / "_render_##")
    _STATE["job"] = {"camera": cam, "poses": poses, "seed": spec["seed"]}
    try:
        clock = _RenderClock(times, len(poses) - 1, _STATE["setup"].profile)
        _STATE["clock"] = clock
        try:
            bpy.ops.render.render(animation=True)
        finally:
            _STATE["job"] = _STATE["clock"] = None
            clock.stop()
        for f in range(len(poses)):
            tmp = Path(scene.render.frame_path(frame=f))
            with times.measure("exr_read"):
                linear, depth = _channels(tmp)
                tmp.unlink()
            with times.measure("to_srgb"):
                rgb = formats.linear_to_srgb8(linear)  # as frame_arrays gives it
            bgr = rgb[..., ::-1]
            with times.measure("rgb_write"):
                _imwrite(out / layout.rgb_name(local, f, image_format), bgr, params)
            with times.measure("depth_write"):
                formats.write_depth_exr(out / layout.depth_name(local, f), depth)
            if legacy:
                if image_format != "jpg":
                    with times.measure("rgb_write"):
                        _imwrite(out / layout.rgb_name(local, f, "jpg"), bgr, params)
                with times.measure("depth_write"):
                    np.save(out / layout.depth_name(local, f, "npy"), depth)
    except Exception as e:
        if not formats.is_disk_full(e):  # Blender and OpenCV write without reporting errno
            formats.check_space(out, _probe_bytes(scene.render))
        raise
    _STATE["scenes"] += 1
    _STATE.pop("startup", None)
    t1, c1 = phases.clocks()
    return {
        "index": spec["index"],
        "seconds": t1 - t0,
        "cpu_seconds": c1 - c0,
        "build_seconds": times.wall["build"],
        "phases": times.to_dict(),
        "process_cpu_seconds": c1,
        "frames": len(poses),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "pid": os.getpid(),
    }
