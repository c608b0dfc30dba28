"""What a Blender worker process is set up with, once, before it renders scenes: one typed,
picklable object built by :func:`worker_setup` (every pool, local or Ray, the quality bench and
``stats --flicker`` use it), read by stillbox_gen.blender.render.init_worker.

The frame size is not part of it: it comes from each scene's CameraSpec (``width``, ``height``),
the one source of the resolution, which stillbox_gen.blender.render sets per scene with the
camera built from the same spec; a worker can thus not render a scene at a size other than the
one its intrinsics were drawn for.
"""

from __future__ import annotations

from dataclasses import dataclass

from .config import CPU_DEVICE, DatasetConfig, RenderConfig


@dataclass(frozen=True)
class WorkerSetup:
    """The Cycles set-up of a worker process (stillbox_gen.blender.render.init_worker)."""

    render: RenderConfig  # Cycles settings (the dataset config's render section)
    threads: int  # Cycles threads per worker; 0 = all cores
    textures_dir: str | None  # the --textures folder (photos), None for the bundled ones
    device: str = CPU_DEVICE  # CPU_DEVICE or a GPU backend (workers.choose_device)


def worker_setup(cfg: DatasetConfig, threads: int, device: str = CPU_DEVICE) -> WorkerSetup:
    """The worker set-up rendering the scenes of ``cfg`` with ``threads`` Cycles threads on the
    Cycles ``device``."""
    return WorkerSetup(cfg.render, threads, cfg.materials.textures_dir, device)
