"""The renderers of the closed loop: one persistent Blender worker (the dataset's renderer and
settings: ``stillbox_gen.live.LiveRenderer``), or the analytic depth-only raycaster (raycast.py,
for tests and for depth sources that ignore the image).

:func:`open_renderer` is a context manager giving ``for_episode(episode) -> render``, where
``render(cam2world) -> (rgb (H, W, 3) uint8, planar depth (H, W) float32 m)`` is what
simulate.fly calls at each control step. Blender is imported only when ``kind`` is "blender",
inside :func:`open_renderer`, so the benchmark imports without bpy.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import numpy as np

from stillbox_gen.config import DatasetConfig

from . import raycast
from .choices import RENDERERS
from .episodes import Episode
from .simulate import Render

#: renderers whose frames carry an image (a learned depth source needs one)
WITH_IMAGES = ("blender",)


def analytic_render(episode: Episode, width: int, height: int) -> Render:
    """The analytic depth of ``episode``'s World, with raycast.shade's grey stand-in image."""

    def render(cam2world: np.ndarray):
        depth = raycast.render_depth(episode.world, episode.K, width, height, cam2world)
        return raycast.shade(depth), depth

    return render


def check_renderer(kind: str) -> None:
    """Before anything starts: ValueError for an unknown ``kind``; for "blender", a one-line
    ConfigError when bpy is not installed (stillbox_gen.worker_setup.require_blender: it names
    the ``gen`` extra)."""
    if kind not in RENDERERS:
        raise ValueError(f"renderer must be one of {RENDERERS}, got {kind!r}")
    if kind == "blender":
        from stillbox_gen.worker_setup import require_blender

        require_blender()


@contextlib.contextmanager
def open_renderer(
    kind: str, scene_cfg: DatasetConfig, device: str = "cpu"
) -> Iterator[Callable[[Episode], Render]]:
    """A renderer for the episodes of ``scene_cfg`` (their frame size): "analytic", or
    "blender" (one LiveRenderer worker for every episode, closed at the end; ConfigError of one
    line when bpy is not installed, naming the ``gen`` extra). ``device``: the render device
    given to the LiveRenderer."""
    width, height = scene_cfg.camera.width, scene_cfg.camera.height
    if kind == "analytic":
        yield lambda episode: analytic_render(episode, width, height)
        return
    check_renderer(kind)
    from stillbox_gen.live import LiveRenderer

    with LiveRenderer(scene_cfg, device) as live:

        def for_episode(episode: Episode) -> Render:
            live.load(episode.scene)
            frames = iter(range(1 << 62))
            return lambda cam2world: live.render(cam2world, next(frames))

        yield for_episode
