"""Cycles' render devices (imports bpy): which GPU backends have a device, and a worker's set-up.

``python -m stillbox_gen.blender.devices`` prints :func:`gpu_devices` as one JSON line; the
driver runs it in a subprocess (stillbox_gen.workers.find_gpus), since Cycles prints driver
warnings on stderr while it looks, and broken drivers can crash it.
"""

from __future__ import annotations

import json

import bpy

from ..config import CPU_DEVICE, GPU_BACKENDS


def _preferences():
    return bpy.context.preferences.addons["cycles"].preferences


def gpu_devices() -> dict[str, list[str]]:
    """{backend: device names} of every GPU backend (GPU_BACKENDS order) with a device."""
    prefs = _preferences()
    prefs.refresh_devices()  # Cycles does not look for devices on its own
    found = {}
    for backend in GPU_BACKENDS:
        names = [d.name for d in prefs.get_devices_for_type(backend) if d.type == backend]
        if names:
            found[backend] = names
    return found


def use_device(backend: str) -> list[str]:
    """Render the current scene on ``backend``: CPU_DEVICE, or every device of a GPU backend
    (the CPU not added); returns the device names. RuntimeError when Cycles finds none."""
    scene = bpy.context.scene
    if backend == CPU_DEVICE:
        scene.cycles.device = "CPU"
        return [CPU_DEVICE]
    prefs = _preferences()
    prefs.refresh_devices()
    devices = prefs.get_devices_for_type(backend)
    names = [d.name for d in devices if d.type == backend]
    if not names:
        raise RuntimeError(f"Cycles finds no {backend} device in this worker process")
    prefs.compute_device_type = backend
    for d in devices:
        d.use = d.type == backend
    scene.cycles.device = "GPU"
    return names


if __name__ == "__main__":
    print(json.dumps(gpu_devices()))
