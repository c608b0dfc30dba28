"""Usage: python docs/results/finetune/footage_from_dataset.py DATA SPLIT OUT [SCENES]

The footage of the fine-tuning proof (docs/UNSUPERVISED.md, "Fine-tuning on your own footage"):
the stabilised
scenes of one split of a stillbox-gen dataset (the first SCENES, default all) as one folder of
frames, ``OUT/frames/NNNNNN.png`` in order, and ``OUT/poses.csv`` with columns t,x,y,z: seconds
and the camera position in metres, in the scenes' camera axes (x right, y down, z forward; one
frame's axes are every frame's in a stabilised scene), so that ``finetune``'s ``pose_cosine``
compares PoseNet with the truth. The first frame of each scene repeats the previous frame's
position (the camera "hovers" between scenes), so ``finetune`` cuts its moving stretches at scene
boundaries and no training sequence spans two scenes. Then:

    stillbox-bench finetune --ckpt C --input OUT/frames --poses OUT/poses.csv --out runs/ft

Only the frames and the camera motion are written: no depth reaches the fine-tuning.
"""

import shutil
import sys
from pathlib import Path

import numpy as np

from stillbox_gen.dataset import Dataset


def main(data: str, split: str, out: str, scenes: str | None = None) -> None:
    chosen = Dataset(data).scenes(split)[: int(scenes) if scenes else None]
    if not chosen or not all(s.stabilised for s in chosen):
        raise SystemExit(f"{data}: needs stabilised scenes in split '{split}'")
    folder = Path(out) / "frames"
    folder.mkdir(parents=True)
    rows, position, t, n = ["t,x,y,z"], np.zeros(3), 0.0, 0
    for scene in chosen:
        start = position
        for f in range(scene.frames):
            position = start + scene.translation(0, f)
            shutil.copyfile(scene.rgb[f], folder / f"{n:06d}{scene.rgb[f].suffix}")
            rows.append(",".join(f"{v:.9g}" for v in (t, *position)))
            t, n = t + scene.time_step, n + 1
    (Path(out) / "poses.csv").write_text("\n".join(rows) + "\n")
    print(f"{n} frames of {len(chosen)} scenes in {folder}, poses in {Path(out) / 'poses.csv'}")


if __name__ == "__main__":
    main(*sys.argv[1:])
