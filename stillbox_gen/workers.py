"""Blender worker processes on this machine, seen from the driver (nothing here imports bpy).

:func:`init_worker` and :func:`render_scene` are the functions a worker process runs; they
import ``stillbox_gen.blender.render`` (and so bpy) inside the worker only. :class:`LocalPool`
is a pool of such processes with the interface the run loop (stillbox_gen.generate) expects of
every backend (see also stillbox_gen.ray_pool.RayPool):

- ``submit(spec, tmp_dir, image_format, legacy) -> Future`` of the render statistics;
- ``died_errors``: exceptions meaning a worker died (its pool must be replaced);
- ``kill()``: stop crashed or hung workers at once; ``shutdown()``: wait for them to end.

Workers end with the driver (:func:`exit_with_parent`), and SIGTERM of the driver is turned into a
KeyboardInterrupt (:func:`sigterm_as_interrupt`, used by the command line) so that the run loop
kills its workers and exits as on Ctrl-C.

:func:`choose_device` turns ``--device`` into the Cycles device the workers use, asking Blender
(:func:`find_gpus`, in a subprocess) which GPU backends have a device.
"""

from __future__ import annotations

import contextlib
import functools
import json
import multiprocessing
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from .config import CPU_DEVICE, GPU_BACKENDS, DatasetConfig
from .errors import ConfigError
from .worker_setup import WorkerSetup, require_blender, worker_setup


class Terminated(KeyboardInterrupt):
    """SIGTERM (what ``timeout`` and job schedulers send), handled as Ctrl-C."""


def _raise_terminated(signum: int, frame: object = None) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM ends the process at once
    raise Terminated()


@contextlib.contextmanager
def sigterm_as_interrupt():
    """Within the block, SIGTERM raises :class:`Terminated` (a KeyboardInterrupt) in the main
    thread, so it stops the workers and exits as Ctrl-C does (exit code 128 + 15); in another
    thread, where Python cannot set signal handlers, nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def sigterm_deferred():
    """Within :func:`sigterm_as_interrupt`, hold a SIGTERM back until the end of the block (then
    raise :class:`Terminated`): around the spawn of a worker, which an exception would cut short
    between starting the process and sending it its start-up data (the new process would then
    print an EOFError traceback)."""
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGTERM) is not _raise_terminated
    ):
        yield
        return
    got: list[int] = []
    signal.signal(signal.SIGTERM, lambda signum, frame: got.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, _raise_terminated)
        if got:
            _raise_terminated(got[0])


def init_worker(setup: WorkerSetup) -> None:
    """Set Cycles up once in a worker process (see stillbox_gen.worker_setup)."""
    from .blender.render import init_worker as init

    init(setup)


def render_scene(spec: dict, tmp_dir: str, image_format: str, legacy: bool) -> dict:
    """Render a SceneSpec dict's frames into ``tmp_dir`` (named as in stillbox_gen.layout);
    returns timing and memory statistics (``peak_rss_mb``)."""
    from .blender.render import render_scene as render

    return render(spec, tmp_dir, image_format, legacy)


@functools.cache
def find_gpus() -> dict[str, list[str]]:
    """{backend: device names} of the GPU backends Cycles finds a device of on this machine
    (GPU_BACKENDS order; empty on a CPU-only machine). Blender looks in a subprocess (about a
    second, once per process), which also keeps its driver warnings off our stderr;
    RuntimeError when that subprocess fails."""
    cmd = [sys.executable, "-m", "stillbox_gen.blender.devices"]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        lines = proc.stdout.strip().splitlines()
        if proc.returncode != 0 or not lines:
            raise RuntimeError(f"exit code {proc.returncode}")
        return json.loads(lines[-1])
    except (OSError, subprocess.TimeoutExpired, ValueError) as e:
        raise RuntimeError(str(e)) from None


def choose_device(choice: str, backend: str = "local") -> tuple[str, str]:
    """The Cycles device of ``--device CHOICE`` (config.DEVICES) and a one-line report of it,
    e.g. ("CPU", "render device: CPU (no GPU backend found by Cycles)").

    "auto": the first GPU backend of GPU_BACKENDS with a device, else the CPU. An explicit GPU
    backend without a device is a ConfigError naming --device. Ray actors (``backend`` "ray")
    render on CPUs: "auto" gives the CPU there without looking, a GPU backend is refused.
    """
    require_blender()
    if choice == "cpu":
        return CPU_DEVICE, f"render device: {CPU_DEVICE}"
    if backend == "ray":
        if choice == "auto":
            return CPU_DEVICE, f"render device: {CPU_DEVICE} (--backend ray renders on CPUs)"
        raise ConfigError(f"--device {choice}: --backend ray renders on CPUs (use cpu or auto)")
    wanted = GPU_BACKENDS if choice == "auto" else (choice.upper(),)
    try:
        found, failed = find_gpus(), ""
    except RuntimeError as e:
        found, failed = {}, f"Cycles' device detection failed: {e}"
    usable = [b for b in wanted if b in found]
    if usable:
        return usable[0], f"render device: {usable[0]} ({', '.join(found[usable[0]])})"
    if choice == "auto":
        return CPU_DEVICE, f"render device: CPU ({failed or 'no GPU backend found by Cycles'})"
    seen = ", ".join(["CPU", *found]) if found else "CPU only"
    raise ConfigError(
        f"--device {choice}: no {wanted[0]} device found by Cycles ({failed or f'found: {seen}'})"
    )


PR_SET_PDEATHSIG = 1  # prctl(2) option: the signal a process gets when its parent ends
PARENT_POLL_SECONDS = 1.0  # without prctl: how often a worker checks that its parent lives


def exit_with_parent(parent: int) -> None:
    """End this process when its parent, process ``parent``, ends, however it ends (kill -9
    included): a Blender worker (about 500 MB) must not outlive the run that started it.

    On Linux the kernel sends SIGKILL at the parent's death (prctl PR_SET_PDEATHSIG): immediate,
    even in the middle of a render (which may hold the GIL for minutes, stalling any thread),
    and free. The kernel tracks the thread that spawned the process; the pool's workers are
    spawned by the main thread or the pool's manager thread, which both live as long as the
    pool's workers do. Elsewhere, a daemon thread polls os.getppid() every
    PARENT_POLL_SECONDS. Either way, a parent that died before this call ends the process now.
    """
    if sys.platform.startswith("linux"):
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            _poll_parent(parent)
    else:
        _poll_parent(parent)
    if os.getppid() != parent:  # the parent died before the death signal was set up
        os._exit(1)


def _poll_parent(parent: int) -> None:
    """A daemon thread ending the process once ``parent`` is no longer its parent."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_SECONDS)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _init_local_worker(parent: int, setup: WorkerSetup) -> None:
    """Initializer of a process_pool worker: die with the driver, then :func:`init_worker`."""
    exit_with_parent(parent)
    init_worker(setup)


def process_pool(workers: int, setup: WorkerSetup, recycle_after: int | None = None):
    """A ProcessPoolExecutor of ``workers`` spawned processes set up by :func:`init_worker`
    (each replaced after ``recycle_after`` scenes when given), each ending when this process
    ends (:func:`exit_with_parent`). Submit :func:`render_scene`."""
    return ProcessPoolExecutor(
        max_workers=workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_init_local_worker,
        initargs=(os.getpid(), setup),
        max_tasks_per_child=recycle_after,
    )


class LocalPool:
    """``workers`` Blender processes on this machine (spawned, each replaced after
    ``recycle_after`` scenes); a worker writes a scene's files into its temporary folder."""

    died_errors: tuple[type[BaseException], ...] = (BrokenProcessPool,)

    def __init__(
        self,
        cfg: DatasetConfig,
        workers: int,
        threads: int,
        recycle_after: int,
        device: str = CPU_DEVICE,
        profile: bool = False,
    ):
        setup = worker_setup(cfg, threads, device, profile)
        self._pool = process_pool(workers, setup, recycle_after)

    def submit(self, spec: dict, tmp_dir: Path, image_format: str, legacy: bool) -> Future:
        with sigterm_deferred():  # submit may spawn a worker
            return self._pool.submit(render_scene, spec, str(tmp_dir), image_format, legacy)

    def kill(self) -> None:
        """Stop workers that crashed or hang: kill the processes, then shut the pool down once
        its manager thread has seen them die. (Python 3.11's ``shutdown(wait=False)`` here races
        with that thread, which may then print an OSError traceback: CPython gh-132969.)"""
        procs = list((getattr(self._pool, "_processes", None) or {}).values())
        for proc in procs:
            if proc.is_alive():
                proc.kill()
        for proc in procs:
            proc.join(timeout=10)
        self._pool.shutdown(wait=True, cancel_futures=True)

    def shutdown(self) -> None:
        self._pool.shutdown(wait=True)
