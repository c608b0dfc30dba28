"""Worker side of stillbox_gen.live: one Blender process rendering frames on demand.

``python -m stillbox_gen.blender.live`` is started by :class:`stillbox_gen.live.LiveRenderer`;
it reads pickled requests on stdin and answers each with one pickle on the file descriptor
given as its first argument (a pipe of the driver: Blender prints on stdout, which goes to /dev/null
once the worker is set up, as in every worker):

- first ``(cfg, threads, device)``: a DatasetConfig, Cycles threads (0: all cores) and a
  ``--device`` choice; answer ``("ok", device report line)``;
- ``("load", SceneSpec dict)``: build that scene (render.load_scene, as the generator does);
  answer ``("ok", None)``;
- ``("render", cam2world, frame)``: one still render at that OpenCV pose with the Cycles seed of
  frame ``frame`` (render.render_seed); answer ``("ok", (rgb uint8, depth float32))``;
- ``("close",)``: end.

A request that fails answers ``("error", kind, message)``, kind "config" for a user mistake
(ConfigError) and "runtime" for anything else; the worker then waits for the next request.

A still render with persistent data re-syncs only the camera: the frame is the one of the
generator's animation render at that pose and seed (bit-identical, tests/test_live.py). Blender
in background mode keeps no pixels in its Render Result, so each frame goes through a multilayer
EXR in the temporary folder the driver gives as second argument (also this process's TMPDIR,
so Blender's session folder; the driver removes it), read back and deleted at once.
"""

from __future__ import annotations

import os
import pickle
import signal
import sys
from pathlib import Path

import bpy
import numpy as np

from ..errors import ConfigError
from ..worker_setup import worker_setup
from ..workers import choose_device, exit_with_parent
from . import build, render


def _start(request) -> str:
    """Set the worker up from the first request; returns the device report line."""
    cfg, threads, choice = request
    device, report = choose_device(choice)
    render.init_worker(worker_setup(cfg, threads, device))
    return report


def _load(state: dict, spec: dict) -> None:
    state.clear()  # a scene that fails to build leaves none loaded
    cam = render.load_scene(spec)
    state.update(camera=cam, seed=spec["seed"])


def _render(state: dict, folder: Path, cam2world: np.ndarray, frame: int):
    """RGB (H, W, 3) uint8 sRGB and planar depth (H, W) float32 m of one frame."""
    if "camera" not in state:
        raise RuntimeError("no scene loaded: call load(spec) before render")
    scene = bpy.context.scene
    build.set_camera_pose(state["camera"], cam2world)
    render.set_seed(scene, state["seed"], frame)
    path = folder / "live.exr"  # a still render's file name takes no frame number
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    try:
        return render.frame_arrays(path)
    finally:
        path.unlink(missing_ok=True)


def _answer(out, message) -> None:
    pickle.dump(message, out, protocol=pickle.HIGHEST_PROTOCOL)
    out.flush()


def serve(inp, out, folder: Path) -> None:
    """Answer requests from ``inp`` on ``out`` (binary files) until ("close",) or end of input;
    frames pass through ``folder``."""
    state: dict = {}
    while True:
        try:
            request = pickle.load(inp)
        except EOFError:
            return
        if request[0] == "close":
            return
        try:
            if request[0] == "load":
                result = _load(state, request[1])
            else:
                result = _render(state, folder, *request[1:])
        except ConfigError as e:
            _answer(out, ("error", "config", str(e)))
        except Exception as e:  # noqa: BLE001 - reported to the driver, which raises it
            _answer(out, ("error", "runtime", f"{type(e).__name__}: {e}"))
        else:
            _answer(out, ("ok", result))


def main() -> None:
    exit_with_parent(os.getppid())
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the driver, which ends us
    out = os.fdopen(int(sys.argv[1]), "wb")
    inp = sys.stdin.buffer
    try:
        report = _start(pickle.load(inp))
    except ConfigError as e:
        _answer(out, ("error", "config", str(e)))
        return
    except Exception as e:  # noqa: BLE001
        _answer(out, ("error", "runtime", f"{type(e).__name__}: {e}"))
        return
    _answer(out, ("ok", report))
    serve(inp, out, Path(sys.argv[2]))


if __name__ == "__main__":
    main()
