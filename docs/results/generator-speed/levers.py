"""Cycles settings ("levers") timed against the current defaults in one Blender process (issue 26).

    python docs/results/generator-speed/levers.py --res 64 --scenes 8 --threads 1 \
        --levers base,light_tree_on,spatial_splits,samples_3 --reference-scenes 4

Each default-preset scene is rendered once per lever, levers in turn (order reversed every other
scene, so that a drifting machine hits them alike), exactly as a worker renders it
(stillbox_gen.blender.render.render_scene, phases timed with Cycles' sampling split out). Printed
per lever, in ms per frame: the whole scene call, the build, Cycles' sync, sampling and result;
then how many scenes gave the same bytes as the first lever, the PSNR (dB) of the frames
against the first lever's, and with ``--reference-scenes N`` against 256-sample renders of frames
0 and 9 of the first N scenes (the bench's quality measure). The first scene build of a process
also makes its photo levels: compare builds on later levers, or use the phase table of
``stillbox-gen bench --profile`` for builds.
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import os
import sys
import tempfile
from pathlib import Path

import bpy
import cv2
import numpy as np

from stillbox_gen import bench, config
from stillbox_gen.blender import render
from stillbox_gen.scene import sample_scene
from stillbox_gen.worker_setup import worker_setup

# lever -> {Cycles setting (scene.cycles, or scene.render with "render."): value}
LEVERS = {
    "base": {},
    "light_tree_on": {"use_light_tree": True},
    "light_tree_off": {"use_light_tree": False},
    "spatial_splits": {"debug_use_spatial_splits": True},
    "compact_bvh": {"debug_use_compact_bvh": True},
    "no_glossy_bounce": {"max_bounces": 0, "glossy_bounces": 0},
    "no_compositing": {"render.use_compositing": False, "render.use_sequencer": False},
    "blue_noise": {"sampling_pattern": "BLUE_NOISE"},
    "samples_1": {"samples": 1},
    "samples_2": {"samples": 2},
    "samples_3": {"samples": 3},
    "adaptive_4": {
        "use_adaptive_sampling": True,
        "adaptive_threshold": 0.02,
        "adaptive_min_samples": 1,
    },
    "adaptive_8": {
        "samples": 8,
        "use_adaptive_sampling": True,
        "adaptive_threshold": 0.02,
        "adaptive_min_samples": 2,
    },
}
REFERENCE_FRAMES = (0, 9)


def _target(scene, key: str):
    """(object, attribute) of a lever key."""
    if key.startswith("render."):
        return scene.render, key.removeprefix("render.")
    return scene.cycles, key


def _render(spec: dict) -> tuple[dict, str, list[np.ndarray]]:
    """Render a scene like a worker: (its statistics, SHA-256 of all its files, its frames)."""
    with tempfile.TemporaryDirectory() as d:
        stats = render.render_scene(spec, d, "png", False)
        digest, frames = hashlib.sha256(), []
        for f in sorted(Path(d).iterdir()):
            digest.update(f.read_bytes())
            if f.suffix == ".png":
                frames.append(cv2.imread(str(f)))
    return stats, digest.hexdigest(), frames


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--res", type=int, default=64)
    p.add_argument("--scenes", type=int, default=8)
    p.add_argument("--threads", type=int, default=1, help="Cycles threads (0 = all cores)")
    p.add_argument("--levers", default="base,light_tree_on", help=f"from {', '.join(LEVERS)}")
    p.add_argument("--reference-scenes", type=int, default=0)
    args = p.parse_args()
    names = args.levers.split(",")
    unknown = [n for n in names if n not in LEVERS]
    if unknown:
        sys.exit(f"--levers: unknown {', '.join(unknown)}")
    cfg = config.replace(
        config.load_preset("stillbox"), camera={"width": args.res, "height": args.res}
    )
    out = os.fdopen(os.dup(1), "w")  # init_worker sends fd 1 (Blender's chatter) to /dev/null
    render.init_worker(worker_setup(cfg, args.threads, profile=True), silence_stdout=True)
    scene = bpy.context.scene
    keys = {k for n in names for k in LEVERS[n]} | {"samples"}
    defaults = {k: getattr(*_target(scene, k)) for k in keys}
    ms = {n: {} for n in names}  # lever -> phase -> summed wall seconds
    digests, psnr_first, psnr_ref = ({n: [] for n in names} for _ in range(3))
    for i in range(args.scenes):
        spec = sample_scene(cfg, i).to_dict()
        frames = {}
        for name in names if i % 2 == 0 else names[::-1]:
            for k, v in {**defaults, **LEVERS[name]}.items():
                setattr(*_target(scene, k), v)
            stats, digest, frames[name] = _render(spec)
            digests[name].append(digest)
            ms[name]["total"] = ms[name].get("total", 0.0) + stats["seconds"]
            for phase, (wall, _cpu) in stats["phases"].items():
                ms[name][phase] = ms[name].get(phase, 0.0) + wall
        for k, v in defaults.items():
            setattr(*_target(scene, k), v)
        for name in names:
            psnr_first[name] += [
                bench.psnr(a, b) for a, b in zip(frames[name], frames[names[0]], strict=True)
            ]
        if i < args.reference_scenes:
            still = copy.deepcopy(spec)
            poses = spec["camera"]["cam2world"]
            still["camera"]["cam2world"] = [poses[f] for f in REFERENCE_FRAMES]
            scene.cycles.samples = bench.REFERENCE_SAMPLES
            reference = _render(still)[2]
            scene.cycles.samples = defaults["samples"]
            for name in names:
                got = [frames[name][f] for f in REFERENCE_FRAMES]
                psnr_ref[name] += [bench.psnr(a, b) for a, b in zip(got, reference, strict=True)]
    frames_done = args.scenes * cfg.camera.frames
    print(
        f"{args.res} px, {args.scenes} scenes, {args.threads} Cycles threads; ms per frame:",
        file=out,
    )
    for name in names:
        t = {k: 1000 * v / frames_done for k, v in ms[name].items()}
        same = sum(a == b for a, b in zip(digests[name], digests[names[0]], strict=True))
        finite = [v for v in psnr_first[name] if np.isfinite(v)]
        vs_first = f"{np.mean(finite):5.1f}" if finite else "  inf"
        ref = f"  PSNR vs 256 samples {np.mean(psnr_ref[name]):5.2f} dB" if psnr_ref[name] else ""
        print(
            f"{name:16s} total {t['total']:7.2f}  build {t.get('build', 0):5.2f}  "
            f"sync {t.get('cycles_sync', 0):5.2f}  sampling {t.get('cycles_sampling', 0):7.2f}  "
            f"result {t.get('cycles_result', 0):5.2f}  same bytes as {names[0]} "
            f"{same}/{args.scenes}  PSNR vs {names[0]} {vs_first} dB{ref}",
            file=out,
        )


if __name__ == "__main__":
    main()
