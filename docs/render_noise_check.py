"""Render noise against motion signal on far surfaces, for a few scenes of a dataset.

Re-renders frame 0 of the first scenes with another noise seed and compares, on pixels farther
than 30 m, |frame 0 - frame 0 re-rendered| (render noise) with |frame 0 - frame 3| (what 0.3 m of
camera motion changes). Usage::

    .venv/bin/python docs/render_noise_check.py data/stillbox-64 [SCENES]
"""

from __future__ import annotations

import json
import multiprocessing
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from stillbox_gen import formats, generate


def main(root: Path, scenes: int) -> None:
    info = json.loads((root / "dataset.json").read_text())
    cam = info["config"]["camera"]
    init = (info["config"]["render"], cam["width"], cam["height"], 0, None)
    ctx = multiprocessing.get_context("spawn")
    with (
        tempfile.TemporaryDirectory() as tmp,
        ProcessPoolExecutor(1, ctx, initializer=generate._worker_init, initargs=init) as pool,
    ):
        for k in range(scenes):
            chunk = root / formats.chunk_name(k)
            rec = json.loads(formats.record_path(root, k).read_text())
            keys = ("K", "time_step", "speed", "orientation", "cam2world", "near_clip", "far_clip")
            spec = {
                "index": k,
                "seed": rec["seed"] + 12345,  # another noise seed, same scene
                "rejected": 0,
                "camera": {"width": cam["width"], "height": cam["height"],
                           **{key: rec[key] for key in keys}},
                "primitives": rec["primitives"],
                "box": rec["box"],
                "light": rec["light"],
            }  # fmt: skip
            out = Path(tmp) / str(k)
            pool.submit(generate._worker_render, spec, str(out), "png", False).result()
            local = formats.local_index(k)
            a = cv2.imread(str(chunk / rec["rgb"][0])).astype(float)
            b = cv2.imread(str(out / formats.rgb_name(local, 0))).astype(float)
            c = cv2.imread(str(chunk / rec["rgb"][3])).astype(float)
            far = formats.read_depth_exr(chunk / rec["depth_exr"][0]) > 30
            print(
                f"scene {k}: far pixels {far.mean():4.0%}  noise {np.abs(a - b)[far].mean():5.2f}"
                f"  motion (frame 0 vs 3) {np.abs(a - c)[far].mean():5.2f} grey levels"
            )


if __name__ == "__main__":
    main(Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 6)
