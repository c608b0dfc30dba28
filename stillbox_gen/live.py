"""Frames rendered on demand by one persistent Blender worker, seen from the driver (nothing
here imports bpy): the camera of a closed-loop flight (benchmark.flight.simulate's ``render``).

:class:`LiveRenderer` starts one worker process (``python -m stillbox_gen.blender.live``) set
up as the generator's workers are (stillbox_gen.worker_setup, the same Cycles settings), builds a
scene in it on :meth:`~LiveRenderer.load` (the generator's build path, frame size from the
scene's CameraSpec) and renders one frame per :meth:`~LiveRenderer.render` call at any pose:
the RGB and depth the dataset's files would hold for that pose. Requests and answers are
pickles over the worker's stdin and a pipe of its own (stillbox_gen.blender.live documents them).

The worker ends with :meth:`~LiveRenderer.close` (or the ``with`` block), and with this process
however it ends (stillbox_gen.workers.exit_with_parent; on Linux the kernel kills it when the
thread that created the LiveRenderer ends, so create it in a thread that lives as long as it is
used). A worker that dies raises :class:`WorkerDied` in the driver at the next call, never a
hang; one that lives but gives no answer within ``timeout`` seconds (stopped, deadlocked, a
driver of its GPU stuck) is killed and raises :class:`WorkerHung`.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import select
import shutil
import subprocess
import sys
import tempfile

import numpy as np

from .config import DEVICES, DatasetConfig
from .errors import ConfigError, WorkerDied, WorkerHung
from .record import SceneSpec
from .worker_setup import require_blender

CLOSE_SECONDS = 10.0  # how long close() waits for the worker to end before killing it
#: how long one request may wait for the worker's first byte of answer (s): far above Blender's
#: start (seconds) and a frame of the largest closed-loop sizes; a worker this late is hung
ANSWER_SECONDS = 600.0


class LiveRenderer:
    """One persistent Blender worker rendering frames on demand (see the module docstring).

    ``device``: a ``--device`` choice (config.DEVICES; "auto" looks for a GPU as the generator
    does); ``threads``: Cycles threads (0: all cores); ``timeout``: seconds a request waits for
    the start of its answer before the worker is killed (:class:`WorkerHung`). ConfigError (one
    line) without Blender or for a device Cycles does not find. :attr:`device_report` is the
    worker's one-line report of its render device (``render device: CPU``).
    """

    def __init__(
        self,
        cfg: DatasetConfig,
        device: str = "cpu",
        threads: int = 0,
        timeout: float = ANSWER_SECONDS,
    ) -> None:
        if device not in DEVICES:
            raise ConfigError(f"--device {device}: not one of {', '.join(DEVICES)}")
        if not timeout > 0:
            raise ValueError(f"timeout must be > 0 seconds, got {timeout!r}")
        require_blender()
        self.timeout = float(timeout)
        self._scene: SceneSpec | None = None
        self._gone: Exception | None = None  # what calls raise from now on (closed, died)
        # the worker's frame files, and its TMPDIR: Blender's own session folder goes there too,
        # so that close() removes everything even after the worker was killed
        self._folder = tempfile.mkdtemp(prefix="stillbox-live-")
        answers, write_end = os.pipe()  # not stdout: Blender prints there
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-m", "stillbox_gen.blender.live", str(write_end), self._folder],
                stdin=subprocess.PIPE,
                pass_fds=(write_end,),
                env={**os.environ, "TMPDIR": self._folder},
            )
        except BaseException:
            os.close(answers)
            shutil.rmtree(self._folder, ignore_errors=True)
            raise
        finally:
            os.close(write_end)  # the worker's copy only: its death ends our reads (EOF)
        self._answers = os.fdopen(answers, "rb")
        try:
            self.device_report: str = self._call(cfg, threads, device)
        except BaseException:
            self.close()
            raise

    @property
    def pid(self) -> int:
        """Process id of the worker."""
        return self._proc.pid

    def load(self, spec: SceneSpec) -> None:
        """Build the scene of ``spec`` in the worker (replacing the previous one), as the
        generator builds it; its camera (size, intrinsics, clipping) is ``spec.camera``."""
        self._scene = None
        self._call("load", spec.to_dict())
        self._scene = spec

    def render(self, cam2world: np.ndarray, frame: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """The frame of the loaded scene seen from ``cam2world`` (4x4 OpenCV camera-to-world: x
        right, y down, z forward; world +Z up; metres): RGB (H, W, 3) uint8 sRGB and planar
        depth (H, W) float32 m (misses: about 1e10), exactly as the dataset's frame and depth
        files would hold them. ``frame`` selects the Cycles seed as the dataset's frame of that
        number (stillbox_gen.blender.render.render_seed; the default "direct" shading uses one
        seed per scene, so it matters only for "path" shading)."""
        if self._scene is None:
            raise RuntimeError("LiveRenderer.render: no scene loaded (call load(spec) first)")
        pose = np.asarray(cam2world, dtype=np.float64)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise ValueError(f"cam2world must be a finite 4x4 matrix, got shape {pose.shape}")
        if int(frame) != frame or frame < 0:
            raise ValueError(f"frame must be an integer >= 0, got {frame!r}")
        return self._call("render", pose, int(frame))

    def close(self) -> None:
        """End the worker (waits up to CLOSE_SECONDS, then kills it); idempotent."""
        proc = self._proc
        self._gone = self._gone or RuntimeError("LiveRenderer: closed")
        if proc.poll() is None:
            with contextlib.suppress(OSError):
                pickle.dump(("close",), proc.stdin)
                proc.stdin.flush()
            try:
                proc.wait(CLOSE_SECONDS)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for pipe in (proc.stdin, self._answers):
            with contextlib.suppress(OSError):
                pipe.close()
        shutil.rmtree(self._folder, ignore_errors=True)

    def __enter__(self) -> LiveRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_proc", None) is not None:
            self.close()

    def _call(self, *request):
        """Send one request, return its answer; ConfigError / RuntimeError of a failed request,
        WorkerDied when the worker is gone, WorkerHung when no answer starts within
        ``self.timeout`` seconds."""
        if self._gone is not None:
            raise type(self._gone)(str(self._gone))
        try:
            pickle.dump(request, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._proc.stdin.flush()
            # the answer pipe holds nothing between requests (one answer per request, read
            # whole), so its descriptor turns readable exactly when this answer starts
            if not select.select([self._answers], [], [], self.timeout)[0]:
                raise self._hung(request[0] if isinstance(request[0], str) else "start")
            answer = pickle.load(self._answers)
        except (OSError, EOFError, pickle.UnpicklingError):
            raise self._died() from None
        except WorkerHung:
            raise
        except BaseException:  # Ctrl-C, SIGTERM: the answer would come to the next request
            self._gone = RuntimeError("LiveRenderer: a request was interrupted (worker stopped)")
            self._proc.kill()
            self.close()
            raise
        if answer[0] == "ok":
            return answer[1]
        _, kind, message = answer
        raise (ConfigError if kind == "config" else RuntimeError)(message)

    def _hung(self, what: str) -> WorkerHung:
        self._proc.kill()
        self._proc.wait()
        return self._gone_with(
            WorkerHung(
                f"the live Blender worker (pid {self._proc.pid}) gave no answer to a {what!r} "
                f"request in {self.timeout:g} s and was stopped"
            )
        )

    def _died(self) -> WorkerDied:
        try:
            code = self._proc.wait(CLOSE_SECONDS)
        except subprocess.TimeoutExpired:  # its output closed but it lives on: end it
            self._proc.kill()
            code = self._proc.wait()
        return self._gone_with(
            WorkerDied(
                f"the live Blender worker (pid {self._proc.pid}) died (exit code {code}); "
                "its stderr above may say why"
            )
        )

    def _gone_with(self, error: WorkerDied) -> WorkerDied:
        """Close for good: every later call raises a copy of ``error``; returns one to raise."""
        self._gone = error
        self.close()
        return type(error)(str(error))
