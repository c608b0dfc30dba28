"""Another method's depth maps, read from files and scored like a registered network
(``stillbox-bench eval --predictions DIR``; docs/RUNS.md "Scoring your own method").

The layout mirrors the dataset's depth files (core.runfolder.prediction_name; what
``--save-predictions`` writes): frame ``f`` of scene ``k`` is
``DIR/<k // 200>/depth_<k % 200:04d>_<f:02d>.<ext>``, at the frame's size (H, W), in metres, as

- ``.npy``: a 2-D floating-point array (float32 is enough);
- ``.png``: a 16-bit one-channel PNG holding depth × :data:`PNG_SCALE` (KITTI's convention:
  0.004 m steps up to 255.996 m).

Every frame the split's scoring needs (the second frame of each pair (i, i + shift)) must have a
file; any file may name any frame of a scene of the split, nothing else. Every needed file is
read and checked (shape, finite values) before anything is written.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import cv2
import numpy as np
import torch

from stillbox_gen import layout

from ..core.errors import FieldError
from ..core.runfolder import prediction_name

PNG_SCALE = 256.0  # PNG units per metre (KITTI depth maps)
EXTENSIONS = ("npy", "png")
_NAME = re.compile(r"(\d+)/depth_(\d{4})_(\d{2})\.(" + "|".join(EXTENSIONS) + ")")
#: a flow method's predicted flow, saved beside its depth (runfolder.flow_prediction_name): skipped
_FLOW_NAME = re.compile(r"\d+/flow_\d{4}_\d{2}_\d{2}\.flo")


def read_prediction(path: Path) -> np.ndarray:
    """A prediction file as float64 metres (a 2-D array unless the file is malformed); raises
    ValueError with the reason when it cannot be read."""
    if path.suffix == ".npy":
        try:
            depth = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise ValueError(f"not a NumPy array ({e})") from None
        if not np.issubdtype(depth.dtype, np.floating):
            raise ValueError(f"dtype {depth.dtype}, expected floating-point metres")
        return depth.astype(np.float64)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError("not a PNG image")
    if image.dtype != np.uint16:
        raise ValueError(f"a {image.dtype} PNG, expected 16 bits (depth × {PNG_SCALE:g})")
    return image.astype(np.float64) / PNG_SCALE


class PredictionFiles:
    """The checked prediction files of one split: :meth:`batch` reads the depth of pairs.

    ``root``: the predictions folder; ``frames``: scene index → its frame count (every scene of
    the split); ``needed``: the (scene, frame) pairs scored; ``size``: (H, W) of the frames.
    Raises FieldError on ``predictions`` naming the first faulty file.
    """

    def __init__(
        self,
        root: Path,
        frames: dict[int, int],
        needed: list[tuple[int, int]],
        size: tuple[int, int],
    ):
        self.root = Path(root)
        if not self.root.is_dir():
            raise FieldError("predictions", f"no such folder '{root}'")
        found = self._scan(frames)
        exts = {ext for _, ext in found.values()}
        if len(exts) > 1:
            raise FieldError("predictions", f"'{root}' mixes {' and '.join(sorted(exts))} files")
        self.ext = exts.pop() if exts else "npy"
        for scene, frame in needed:
            if (scene, frame) not in found:
                path = self.root / prediction_name(scene, frame, self.ext)
                raise FieldError("predictions", f"missing '{path}' (scene {scene}, frame {frame})")
            self._check(self.path(scene, frame), size)
        self.size = size

    def path(self, scene: int, frame: int) -> Path:
        return self.root / prediction_name(scene, frame, self.ext)

    def _scan(self, frames: dict[int, int]) -> dict[tuple[int, int], tuple[Path, str]]:
        """Every file under the folder, each a prediction of a frame of the split (lstat only:
        a symlink is refused, nothing is opened)."""
        found: dict[tuple[int, int], tuple[Path, str]] = {}
        for folder, dirs, files in os.walk(self.root):
            for name in sorted(dirs):
                if (Path(folder) / name).is_symlink():
                    raise FieldError("predictions", f"'{Path(folder) / name}' is a symlink")
            for name in sorted(files):
                path = Path(folder) / name
                rel = path.relative_to(self.root).as_posix()
                if _FLOW_NAME.fullmatch(rel) and not path.is_symlink():
                    continue  # a flow method's flow (--save-predictions): not depth
                match = _NAME.fullmatch(rel)
                if path.is_symlink():
                    raise FieldError("predictions", f"'{path}' is a symlink")
                if match is None:
                    raise FieldError(
                        "predictions",
                        f"'{path}' is not a prediction file (expected "
                        f"<chunk>/depth_<s>_<f>.npy or .png, as the dataset's depth files)",
                    )
                chunk, local, frame, ext = match.groups()
                scene = int(chunk) * layout.CHUNK_SIZE + int(local)
                if layout.chunk_name(scene) != chunk or frames.get(scene, 0) <= int(frame):
                    raise FieldError(
                        "predictions", f"'{path}' names no frame of a scene of the scored split"
                    )
                found[scene, int(frame)] = (path, ext)
        return found

    @staticmethod
    def _check(path: Path, size: tuple[int, int]) -> None:
        try:
            depth = read_prediction(path)
        except ValueError as e:
            raise FieldError("predictions", f"'{path}': {e}") from None
        if depth.shape != tuple(size):
            shape = "×".join(map(str, depth.shape))
            raise FieldError(
                "predictions", f"'{path}' is {shape}, the frames are {size[0]}×{size[1]}"
            )
        if not np.isfinite(depth).all():
            raise FieldError("predictions", f"'{path}' has non-finite values")

    def batch(self, scenes: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        """``(B, H, W)`` float32 metres: the prediction of frame ``frames[b]`` of scene
        ``scenes[b]``."""
        maps = [
            read_prediction(self.path(int(s), int(f)))
            for s, f in zip(scenes.tolist(), frames.tolist(), strict=True)
        ]
        return torch.from_numpy(np.stack(maps).astype(np.float32))
