"""Blender worker processes on this machine, seen from the driver (nothing here imports bpy).

:func:`init_worker` and :func:`render_scene` are the functions a worker process runs; they
import ``stillbox_gen.blender.render`` (and so bpy) inside the worker only. :class:`LocalPool`
is a pool of such processes with the interface the run loop (stillbox_gen.generate) expects of
every backend (see also stillbox_gen.ray_pool.RayPool):

- ``submit(spec, tmp_dir, image_format, legacy) -> Future`` of the render statistics;
- ``died_errors``: exceptions meaning a worker died (its pool must be replaced);
- ``kill()``: stop crashed or hung workers at once; ``shutdown()``: wait for them to end.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from .config import DatasetConfig


def init_worker(render: dict, width: int, height: int, threads: int, textures: str | None):
    """Set Cycles up once in a worker process (``render``: RenderConfig as a dict; ``threads``
    Cycles threads, 0 = all cores; ``textures``: the --textures folder or None)."""
    from .blender.render import init_worker as init

    init(render, width, height, threads, textures)


def render_scene(spec: dict, tmp_dir: str, image_format: str, legacy: bool) -> dict:
    """Render a SceneSpec dict's frames into ``tmp_dir`` (named as in stillbox_gen.layout);
    returns timing and memory statistics (``peak_rss_mb``)."""
    from .blender.render import render_scene as render

    return render(spec, tmp_dir, image_format, legacy)


def worker_init_args(cfg: DatasetConfig, threads: int) -> tuple:
    """Arguments of :func:`init_worker` for a dataset, with ``threads`` Cycles threads."""
    c, mat = cfg.camera, cfg.materials
    return (cfg.to_dict()["render"], c.width, c.height, threads, mat.textures_dir)


def process_pool(workers: int, init_args: tuple, recycle_after: int | None = None):
    """A ProcessPoolExecutor of ``workers`` spawned processes set up by :func:`init_worker`
    (each replaced after ``recycle_after`` scenes when given). Submit :func:`render_scene`."""
    return ProcessPoolExecutor(
        max_workers=workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=init_worker,
        initargs=init_args,
        max_tasks_per_child=recycle_after,
    )


class LocalPool:
    """``workers`` Blender processes on this machine (spawned, each replaced after
    ``recycle_after`` scenes); a worker writes a scene's files into its temporary folder."""

    died_errors: tuple[type[BaseException], ...] = (BrokenProcessPool,)

    def __init__(self, cfg: DatasetConfig, workers: int, threads: int, recycle_after: int):
        self._pool = process_pool(workers, worker_init_args(cfg, threads), recycle_after)

    def submit(self, spec: dict, tmp_dir: Path, image_format: str, legacy: bool) -> Future:
        return self._pool.submit(render_scene, spec, str(tmp_dir), image_format, legacy)

    def kill(self) -> None:
        """Stop workers that crashed or hang (kills the processes, waits for nothing)."""
        for proc in list((getattr(self._pool, "_processes", None) or {}).values()):
            if proc.is_alive():
                proc.kill()
        self._pool.shutdown(wait=False, cancel_futures=True)

    def shutdown(self) -> None:
        self._pool.shutdown(wait=True)
