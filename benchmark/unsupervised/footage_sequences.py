"""Training sequences from a user's footage for ``finetune`` (thesis §5.4.5): the frames ``infer``
would feed the network, as a store SequenceDataset reads (benchmark.unsupervised.sequences).

Frames are read, centre-cropped to the training field of view and resized to the network's input
exactly as ``infer`` does (benchmark.core.footage: ``prepare_frame`` with the Job's crop), and
kept in memory. Every ``stride``-th frame is kept (:func:`frame_stride`: consecutive kept frames
are about as far apart as consecutive frames of the training set), and the kept frames are cut
where the camera does not move between two of them: each moving stretch of at least a sequence's
length is one "scene" of :class:`FootageStore`. The camera positions (``--speed`` or ``--poses``)
serve only for the stride, the cuts and the ``translation`` logged beside the loss; the loss
never reads them (eq. 5.2 normalises PoseNet's translations to d0 whatever the speed).
"""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from ..core import footage
from ..core.data import CACHE_LIMIT_BYTES
from ..core.errors import FieldError


def frame_stride(positions: np.ndarray, d0: float, shift: int) -> int:
    """Frames between two kept frames: the displacement per training frame, ``d0 / shift``
    (metres; the checkpoint's nominal displacement over its frame shift), over the footage's
    median displacement per frame (metres, moving frames only), rounded, at least 1."""
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    steps = steps[steps > 0]
    if not len(steps):
        return 1
    return max(1, round(d0 / shift / float(np.median(steps))))


def moving_stretches(positions: np.ndarray, kept: list[int], length: int) -> list[list[int]]:
    """``kept`` frame indices cut where the camera does not move between two consecutive ones;
    the stretches of at least ``length`` frames."""
    stretches: list[list[int]] = [[kept[0]]] if kept else []
    for a, b in zip(kept, kept[1:], strict=False):
        if np.array_equal(positions[a], positions[b]):
            stretches.append([b])
        else:
            stretches[-1].append(b)
    return [s for s in stretches if len(s) >= length]


def prepared_K(size: tuple[int, int], crop: footage.Crop, f_video: float) -> np.ndarray:
    """(3, 3) intrinsics in pixels of the prepared frames (``size`` = (W, H)): the video's focal
    length ``f_video`` (pixels) times the resize of the crop in each axis, the principal point
    at the frame's centre (stillbox_gen.camera's convention: W/2 − 0.5)."""
    w, h = size
    return np.array(
        [
            [f_video * w / crop.width, 0.0, w / 2 - 0.5],
            [0.0, f_video * h / crop.height, h / 2 - 0.5],
            [0.0, 0.0, 1.0],
        ]
    )


class FootageScene:
    """One moving stretch of the footage: ``rgb`` its frame indices in the footage, ``K`` the
    prepared frames' intrinsics, ``index`` its position among the stretches."""

    #: fine-tuning reads stabilised footage (thesis §5.4.5): no rotation between frames
    stabilised = True

    def __init__(self, index: int, frames: list[int], K: np.ndarray, positions: np.ndarray):
        self.index, self.rgb, self.K, self._positions = index, frames, K, positions

    def translation(self, i: int, j: int) -> np.ndarray:
        """Camera displacement (m) from the stretch's frame i to its frame j, in the axes of the
        positions (``--poses``' own; ``--speed``: along x)."""
        return self._positions[self.rgb[j]] - self._positions[self.rgb[i]]


class FootageStore:
    """The moving stretches of the footage as FrameStore-like scenes over prepared frames held in
    memory (``frames`` (n, H, W, 3) uint8, ``rows`` footage frame index -> row of ``frames``)."""

    def __init__(self, scenes: list[FootageScene], frames: np.ndarray, rows: dict[int, int]):
        self.scenes, self._frames, self._rows = scenes, frames, rows
        self.height, self.width = frames.shape[1:3]

    def rgb(self, k: int, f: int) -> np.ndarray:
        return self._frames[self._rows[self.scenes[k].rgb[f]]]


def footage_store(job, length: int, stride: int, progress: bool = True) -> FootageStore:
    """Read ``job``'s footage (an ``infer`` Job: source, crop, size, positions, focals) into a
    FootageStore of the moving stretches of at least ``length`` frames, every ``stride``-th frame
    kept. FieldError on ``input`` when no stretch is long enough or the frames would not fit in
    memory (data.CACHE_LIMIT_BYTES)."""
    kept = list(range(0, job.source.count, stride))
    stretches = moving_stretches(job.positions, kept, length)
    if not stretches:
        raise FieldError(
            "input",
            f"no {length} moving frames in a row (of {job.source.count}, one in {stride} kept); "
            f"fine-tuning reads sequences of {length} frames",
        )
    w, h = job.size
    needed = {f for s in stretches for f in s}
    nbytes = len(needed) * w * h * 3
    if nbytes > CACHE_LIMIT_BYTES:
        raise FieldError(
            "input",
            f"{len(needed)} frames of {w}x{h} need {nbytes / 1024**3:.1f} GB in memory, more than "
            f"{CACHE_LIMIT_BYTES / 1024**3:.0f} GB; cut the footage",
        )
    frames = np.empty((len(needed), h, w, 3), np.uint8)
    rows: dict[int, int] = {}
    bar = tqdm(total=job.source.count, unit="frame", desc="reading footage", disable=not progress)
    with bar:
        for t, frame in enumerate(job.source):  # every frame decoded: a video cannot skip
            bar.update()
            if t in needed:
                rows[t] = len(rows)
                frames[rows[t]] = footage.prepare_frame(frame, job.crop, w, h)
    K = prepared_K(job.size, job.crop, job.focals["video_focal_px"])
    scenes = [FootageScene(i, s, K, job.positions) for i, s in enumerate(stretches)]
    return FootageStore(scenes, frames, rows)


def describe_stretches(store: FootageStore) -> str:
    """E.g. "2 moving stretches of 8-40 frames"."""
    sizes = [len(s.rgb) for s in store.scenes]
    span = f"{min(sizes)}" if min(sizes) == max(sizes) else f"{min(sizes)}-{max(sizes)}"
    word = "stretch" if len(sizes) == 1 else "stretches"
    return f"{len(sizes)} moving {word} of {span} frames"
