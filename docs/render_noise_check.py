"""Render noise against motion signal on far surfaces, for a few scenes of a dataset.

Renders the first scenes twice with two noise seeds (A, B) and compares, on pixels farther than
30 m, |A frame 0 - B frame 0| (render noise) with |A frame 0 - A frame 3| (what 0.3 m of camera
motion changes, plus noise). SAMPLES and DENOISE (1/0) override the dataset's render settings::

    .venv/bin/python docs/render_noise_check.py data/stillbox-64 [SCENES [SAMPLES DENOISE]]
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


def main(root: Path, scenes: int, samples: int | None, denoise: bool | None) -> None:
    info = json.loads((root / "dataset.json").read_text())
    cam, render = info["config"]["camera"], info["config"]["render"]
    if samples is not None:
        render = {**render, "samples": samples, "denoise": denoise}
    init = (render, cam["width"], cam["height"], 0, None)
    print(f"samples {render['samples']}, denoise {render['denoise']}")
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
                "seed": rec["seed"],
                "rejected": 0,
                "camera": {"width": cam["width"], "height": cam["height"],
                           **{key: rec[key] for key in keys}},
                "primitives": rec["primitives"],
                "box": rec["box"],
                "light": rec["light"],
            }  # fmt: skip
            frames = {}
            for run in ("A", "B"):
                out = Path(tmp) / f"{k}{run}"
                spec["seed"] = rec["seed"] + (1 if run == "A" else 2)
                pool.submit(generate._worker_render, spec, str(out), "png", False).result()
                local = formats.local_index(k)
                frames[run] = [
                    cv2.imread(str(out / formats.rgb_name(local, f))).astype(float) for f in (0, 3)
                ]
            far = formats.read_depth_exr(chunk / rec["depth_exr"][0]) > 30
            noise = np.abs(frames["A"][0] - frames["B"][0])[far].mean()
            motion = np.abs(frames["A"][0] - frames["A"][1])[far].mean()
            print(f"scene {k}: far pixels {far.mean():4.0%}  noise {noise:5.2f}  "
                  f"motion + noise {motion:5.2f} grey levels")  # fmt: skip


if __name__ == "__main__":
    args = sys.argv[1:]
    main(
        Path(args[0]),
        int(args[1]) if len(args) > 1 else 6,
        int(args[2]) if len(args) > 2 else None,
        bool(int(args[3])) if len(args) > 3 else None,
    )
