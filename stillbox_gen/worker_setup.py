"""What a Blender worker process is set up with, once, before it renders scenes: one typed,
picklable object built by :func:`worker_setup` (every pool, local or Ray, the quality bench and
``stats --flicker`` use it), read by stillbox_gen.blender.render.init_worker.

The frame size is not part of it: it comes from each scene's CameraSpec (``width``, ``height``),
the one source of the resolution, which stillbox_gen.blender.render sets per scene with the
camera built from the same spec; a worker can thus not render a scene at a size other than the
one its intrinsics were drawn for.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass

from .config import CPU_DEVICE, DatasetConfig, RenderConfig
from .errors import ConfigError

NO_BLENDER = (
    "rendering needs Blender as a Python module (bpy 5.0.1, Python 3.11): "
    "pip install 'stillbox-gen[gen]'"
)


def require_blender() -> None:
    """A ConfigError (one line) when bpy is not installed, before anything is written: the
    reader and the benchmark install without it (the `bench` extra), the renderer does not.
    Here rather than in stillbox_gen.workers so that a driver needing no pool (stillbox_gen.live)
    can check without importing the pool's module."""
    if importlib.util.find_spec("bpy") is None:
        raise ConfigError(NO_BLENDER)


@dataclass(frozen=True)
class WorkerSetup:
    """The Cycles set-up of a worker process (stillbox_gen.blender.render.init_worker)."""

    render: RenderConfig  # Cycles settings (the dataset config's render section)
    threads: int  # Cycles threads per worker; 0 = all cores
    textures_dir: str | None  # the --textures folder (photos), None for the bundled ones
    device: str = CPU_DEVICE  # CPU_DEVICE or a GPU backend (workers.choose_device)
    # time Cycles' sync, sampling and result apart (stillbox_gen.phases), from its status
    # messages: a Python call per message, about 30 a frame; changes no pixel
    profile: bool = False


def worker_setup(
    cfg: DatasetConfig, threads: int, device: str = CPU_DEVICE, profile: bool = False
) -> WorkerSetup:
    """The worker set-up rendering the scenes of ``cfg`` with ``threads`` Cycles threads on the
    Cycles ``device`` (``profile``: see WorkerSetup)."""
    return WorkerSetup(cfg.render, threads, cfg.materials.textures_dir, device, profile)
