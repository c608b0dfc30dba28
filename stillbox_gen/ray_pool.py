"""Ray backend of ``stillbox-gen generate --backend ray``: Blender workers as Ray actors.

Each actor sets Cycles up once (``init_worker``), renders scenes into a private temporary folder
and returns the files' bytes; the driver writes them into the dataset and commits each scene
exactly as with local workers, so the output folder only has to exist on the driver's machine and
the result is the same files as a local run with the same seed. Every node needs this package
(``pip install '.[ray]'``) and, with ``--textures``, the texture folder at the same path.

An actor is retired after ``recycle_after`` scenes (bounded memory); a dead actor
(``RayActorError``) makes the run loop (``generate.render_pending``) replace the pool and retry
its scenes. RayPool has the interface of ``workers.LocalPool``.
Requires the optional ``ray`` extra; nothing else in the package imports ``ray``.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import threading
from concurrent.futures import Future
from pathlib import Path

from .config import DatasetConfig
from .errors import ConfigError
from .worker_setup import WorkerSetup, worker_setup
from .workers import init_worker, render_scene


def _import_ray():
    try:
        import ray
    except ImportError:
        raise ConfigError(
            "--backend ray: Ray is not installed (pip install 'stillbox-gen[ray]')"
        ) from None
    return ray


def require_ray() -> None:
    """ConfigError naming --backend when Ray is missing (checked before anything is written)."""
    _import_ray()


class RenderActor:
    """One Blender worker process on a Ray node (wrapped by ``ray.remote`` in RayPool)."""

    def __init__(self, setup: WorkerSetup) -> None:
        init_worker(setup)

    def render(self, spec: dict, image_format: str, legacy: bool) -> dict:
        """Render a scene; return its statistics plus ``files``: {file name: bytes}."""
        with tempfile.TemporaryDirectory(prefix="stillbox-ray-") as tmp:
            stats = render_scene(spec, tmp, image_format, legacy)
            stats["files"] = {p.name: p.read_bytes() for p in sorted(Path(tmp).iterdir())}
        return stats


def connect(address: str | None) -> bool:
    """Join the Ray cluster at ``address`` ("auto", "HOST:PORT", "ray://HOST:PORT"), or start a
    local instance when None; return True when this call started Ray."""
    ray = _import_ray()
    if ray.is_initialized():
        return False
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    try:
        ray.init(
            address=address,
            include_dashboard=False,
            log_to_driver=False,
            configure_logging=False,
        )
    except (ConnectionError, ValueError) as e:
        hint = ""
        if os.environ.get("RAY_AUTH_MODE") != "token":
            hint = "; a cluster with token authentication needs RAY_AUTH_MODE=token here"
        raise ConfigError(
            f"--ray-address: cannot join the Ray cluster at {address!r} ({e}{hint})"
        ) from None
    return True


@contextlib.contextmanager
def ray_session(address: str | None):
    """Connected to Ray inside the block; a Ray instance started here is stopped after it."""
    started = connect(address)
    try:
        yield
    finally:
        if started:
            _import_ray().shutdown()


class RayPool:
    """``workers`` RenderActors; each reserves ``threads`` CPUs of the cluster (1 when
    ``threads`` is 0) and renders with that many Cycles threads, so Ray's CPU accounting
    holds on many-core nodes. Scenes go to the actor with the fewest in flight; an actor is
    replaced after ``recycle_after`` scenes."""

    def __init__(self, cfg: DatasetConfig, workers: int, threads: int, recycle_after: int):
        ray = self._ray = _import_ray()
        self.died_errors = (ray.exceptions.RayActorError, ray.exceptions.WorkerCrashedError)
        threads = max(threads, 1)
        self._actor_cls = ray.remote(RenderActor).options(
            num_cpus=threads,
            max_restarts=0,
            # Ray starts workers at niceness 15; at that priority any other load on a node
            # (measured: a training job) slowed rendering 17x. Render like local workers.
            runtime_env={"env_vars": {"RAY_worker_niceness": "0"}},
        )
        self._setup = worker_setup(cfg, threads)
        self._lock = threading.Lock()
        self._recycle_after = recycle_after
        self._slots = [self._new_slot() for _ in range(workers)]

    def _new_slot(self) -> dict:
        return {"actor": self._actor_cls.remote(self._setup), "given": 0, "in_flight": 0}

    def submit(self, spec: dict, tmp_dir: Path, image_format: str, legacy: bool) -> Future:
        with self._lock:
            i = min(range(len(self._slots)), key=lambda j: self._slots[j]["in_flight"])
            slot = self._slots[i]
            if slot["given"] >= self._recycle_after:  # retire it after its queued scenes
                slot["actor"].__ray_terminate__.remote()
                slot = self._slots[i] = self._new_slot()
            slot["given"] += 1
            slot["in_flight"] += 1
        fut = slot["actor"].render.remote(spec, image_format, legacy).future()
        fut.add_done_callback(lambda _f, s=slot: self._finished(s))
        return fut

    def _finished(self, slot: dict) -> None:
        with self._lock:
            slot["in_flight"] -= 1

    def kill(self) -> None:
        for slot in self._slots:
            self._ray.kill(slot["actor"], no_restart=True)

    def shutdown(self) -> None:
        for slot in self._slots:
            slot["actor"].__ray_terminate__.remote()
