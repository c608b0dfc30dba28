"""PyTorch datasets of a stillbox-gen dataset: frame pairs and frame sequences of one split.

Both are plain ``torch.utils.data.Dataset`` classes over :class:`stillbox_gen.dataset.Dataset`,
usable with a ``DataLoader`` and any number of worker processes (they hold file paths and
camera numbers only; frames are read in ``__getitem__``). They need torch (the ``bench`` extra).
:class:`StillBoxPackedPairs` gives the same pairs as a ``torch.utils.data.IterableDataset``
streamed from the tar shards of ``stillbox-gen pack`` (stillbox_gen.packed), the shards split
among the DataLoader's workers.

Conventions: images are float32 in [0, 1], channels first; depth is planar, in metres, clipped
to MAX_DEPTH (the sky and far walls beyond it read MAX_DEPTH); ``K`` is the 3×3 intrinsic
matrix in pixels; poses map one frame's camera coordinates to another's (OpenCV axes: x right,
y down, z forward), 4×4 float32.
"""

from __future__ import annotations

import os

import numpy as np

from .conventions import MAX_DEPTH, NOMINAL_SHIFT
from .dataset import Dataset, Scene
from .packed import PackedDataset

try:
    import torch
except ImportError:  # the reader works without torch; these classes do not
    raise ImportError(
        "stillbox_gen.torch_dataset needs PyTorch: pip install 'stillbox-gen[bench]'"
    ) from None


def _image(rgb: np.ndarray) -> torch.Tensor:
    """(H, W, 3) uint8 -> (3, H, W) float32 in [0, 1]."""
    return torch.from_numpy(rgb).permute(2, 0, 1).float() / 255


def _depth(depth: np.ndarray) -> torch.Tensor:
    """(H, W) metres, clipped to MAX_DEPTH."""
    return torch.from_numpy(np.clip(depth, 0, MAX_DEPTH))


class StillBoxPairs(torch.utils.data.Dataset):
    """Frame pairs (i, i + shift) of one split (None: every scene), in scene then frame order.

    Item: ``images`` (6, H, W) (frame i then frame i + shift), ``depth`` (H, W) of frame
    i + shift, ``K`` (3, 3), ``pose`` (4, 4) frame i's camera coordinates to frame i + shift's,
    ``scene`` (index) and ``frame`` (i). The benchmark scores the pairs of NOMINAL_SHIFT.
    """

    def __init__(
        self, root: str | os.PathLike, split: str | None = "train", shift: int = NOMINAL_SHIFT
    ):
        if shift < 1:
            raise ValueError(f"shift must be at least 1 frame, got {shift}")
        self.scenes = Dataset(root).scenes(split)
        self.shift = shift
        self.items = [(k, i) for k, s in enumerate(self.scenes) for i in range(s.frames - shift)]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, n: int) -> dict:
        k, i = self.items[n]
        return _pair(self.scenes[k], i, i + self.shift)


def _pair(scene: Scene, i: int, j: int) -> dict:
    """The item of StillBoxPairs and StillBoxPackedPairs for frames (i, j) of ``scene``."""
    rgb = np.concatenate([scene.load_rgb(i), scene.load_rgb(j)], axis=-1)
    return {
        "images": _image(rgb),
        "depth": _depth(scene.load_depth(j)),
        "K": torch.from_numpy(scene.K).float(),
        "pose": torch.from_numpy(scene.relative_pose(i, j)).float(),
        "scene": scene.index,
        "frame": i,
    }


class StillBoxSequences(torch.utils.data.Dataset):
    """Windows of ``length`` consecutive frames of one split (thesis chapter 5's sequences).

    Item: ``images`` (length, 3, H, W), ``depth`` (length, H, W), ``K`` (3, 3), ``poses``
    (length, 4, 4) the first frame's camera coordinates to each frame's, ``scene`` (index) and
    ``frame`` (the window's first frame). Windows start every ``stride`` frames.
    """

    def __init__(
        self, root: str | os.PathLike, split: str | None = "train", length: int = 5, stride: int = 1
    ):
        if length < 2 or stride < 1:
            raise ValueError(f"need length >= 2 and stride >= 1, got {length} and {stride}")
        self.scenes = Dataset(root).scenes(split)
        self.length = length
        self.items = [
            (k, i)
            for k, s in enumerate(self.scenes)
            for i in range(0, s.frames - length + 1, stride)
        ]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, n: int) -> dict:
        k, first = self.items[n]
        scene = self.scenes[k]
        frames = range(first, first + self.length)
        return {
            "images": torch.stack([_image(scene.load_rgb(f)) for f in frames]),
            "depth": torch.stack([_depth(scene.load_depth(f)) for f in frames]),
            "K": torch.from_numpy(scene.K).float(),
            "poses": torch.stack(
                [torch.from_numpy(scene.relative_pose(first, f)).float() for f in frames]
            ),
            "scene": scene.index,
            "frame": first,
        }


class StillBoxPackedPairs(torch.utils.data.IterableDataset):
    """StillBoxPairs' items, streamed from a packed dataset (``stillbox-gen pack``): the pairs
    (i, i + shift) of one split (None: every scene), shard by shard, each shard's SHA-256
    checked before it is read (stillbox_gen.packed).

    With a ``DataLoader`` of N workers, worker w reads the shards w, w + N, w + 2N, ... of the
    split (and with ``world_size`` > 1 processes, e.g. DDP, process ``rank`` reads every
    ``world_size``-th of those), so every pair is yielded exactly once per epoch, in an order
    that depends only on the shards and N. A worker reads one shard at a time; give at least as
    many shards as workers (``--scenes-per-shard``) or some workers idle. No shuffling: wrap it
    in a shuffle buffer (or shuffle the shard order) for training.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        split: str | None = "train",
        shift: int = NOMINAL_SHIFT,
        rank: int = 0,
        world_size: int = 1,
    ):
        if shift < 1:
            raise ValueError(f"shift must be at least 1 frame, got {shift}")
        if not 0 <= rank < world_size:
            raise ValueError(f"need 0 <= rank < world_size, got {rank} and {world_size}")
        self.packed = PackedDataset(root)
        self.shards = self.packed.shards_of(split)
        self.shift, self.rank, self.world_size = shift, rank, world_size

    def __len__(self) -> int:
        """Pairs of the split over every process (each process yields its share)."""
        return sum(max(0, f - self.shift) for s in self.shards for f in s.frames)

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        worker, workers = (info.id, info.num_workers) if info else (0, 1)
        step = workers * self.world_size
        for shard in self.shards[self.rank * workers + worker :: step]:
            for scene in self.packed.read_shard(shard):
                for i in range(scene.frames - self.shift):
                    yield _pair(scene, i, i + self.shift)
