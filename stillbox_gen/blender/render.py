"""Worker-process side of rendering: one-time Cycles set-up, then one call per scene.

A worker process imports bpy once (about 0.75 s) and renders many scenes; the pool replaces it
after ``recycle_after`` scenes to bound memory. The frames of a scene are rendered by one
animation render (persistent data on: the scene is synced once, then only the camera moves; a
frame-change handler sets each frame's pose and seed) to temporary multilayer EXRs, read back and
written as 8-bit sRGB + float32 depth. The files are byte-identical to those of one still render
per frame (compared file by file when this replaced the stills), and a 64 px worker spends about
10 % less time per frame.
"""

from __future__ import annotations

import os
import resource
import time
from pathlib import Path

import bpy
import cv2
import numpy as np

from .. import config, formats, layout
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
    _STATE.update(setup=setup, scenes=0, job=None)
    handlers = bpy.app.handlers.frame_change_pre
    if _pose_frame not in handlers:
        handlers.append(_pose_frame)


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

    Files are named as in formats.py; returns timing and memory statistics. When a file cannot
    be written or read back for lack of space, raises the OSError of a full disk
    (formats.is_disk_full): the run stops there instead of retrying the scene.
    """
    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = bpy.context.scene
    cam = load_scene(spec)
    t_build = time.perf_counter() - t0
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
        try:
            bpy.ops.render.render(animation=True)
        finally:
            _STATE["job"] = None
        for f in range(len(poses)):
            tmp = Path(scene.render.frame_path(frame=f))
            rgb, depth = frame_arrays(tmp)
            tmp.unlink()
            bgr = rgb[..., ::-1]
            _imwrite(out / layout.rgb_name(local, f, image_format), bgr, params)
            formats.write_depth_exr(out / layout.depth_name(local, f), depth)
            if legacy:
                if image_format != "jpg":
                    _imwrite(out / layout.rgb_name(local, f, "jpg"), bgr, params)
                np.save(out / layout.depth_name(local, f, "npy"), depth)
    except Exception as e:
        if not formats.is_disk_full(e):  # Blender and OpenCV write without reporting errno
            formats.check_space(out, _probe_bytes(scene.render))
        raise
    _STATE["scenes"] += 1
    return {
        "index": spec["index"],
        "seconds": time.perf_counter() - t0,
        "build_seconds": t_build,
        "frames": len(poses),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "pid": os.getpid(),
    }
