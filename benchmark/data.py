"""Image pairs from a stillbox-gen dataset, read through stillbox_gen.dataset.Dataset.

Training pairs follow the original DepthNet sampling (REFERENCE §3): frame i1 uniform, shift =
round(2·nominal_shift·U) in {0..6}, i2 = min(last, i1 + shift), swapped with probability 0.5; the
target is depth(i2) · nominal_shift / |i2 − i1| (100 m when i1 == i2), clipped to the depth range
([0, 100] m; [10, 60] m for the clamped DepthNet of thesis 6.4);
random horizontal and vertical flips. Evaluation pairs are fixed forward pairs (i, i + shift) with
target depth(i + shift). Inputs are (x/255 − 0.5)/0.2 per channel, frames stacked to 6 channels.
Flow networks train on the same pairs with an optical-flow target (``target="flow"``): the exact
flow of the static scene at the second frame's pixels towards the first frame, from the second
frame's depth and the known translation (benchmark.flow).

Every random draw comes from ``numpy.random.default_rng([seed, epoch, index])``: the same seed
gives the same batches whatever the worker count, and a resumed run continues the same sequence.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")

from stillbox_gen import layout  # noqa: E402
from stillbox_gen.camera import fov_from_focal  # noqa: E402
from stillbox_gen.dataset import MAX_DEPTH, NOMINAL_SHIFT, Dataset, Scene  # noqa: E402
from stillbox_gen.formats import DatasetError, read_depth  # noqa: E402, F401 - runner uses it

from .flow import flow_from_depth  # noqa: E402

STILL_TARGET = 100.0  # target for identical frames: "no motion => infinitely far", saturated
CACHE_LIMIT_BYTES = 8 * 1024**3

#: A dataset that cannot be used; the message names the file (stillbox_gen's DatasetError).
DataError = DatasetError


def load_scenes(root: str | os.PathLike, split: str) -> list[Scene]:
    """Scenes of one split, in index order (stillbox_gen.dataset.Dataset.scenes). Raises
    DataError naming the faulty file, or the record whose file name would lead outside
    ``root``, or a scene with camera rotations (these baselines need a stabilised dataset)."""
    ds = Dataset(root)
    scenes = ds.scenes(split)
    for s in scenes:
        if not s.stabilised:
            meta = ds.root / layout.chunk_name(s.index) / layout.METADATA_JSON
            raise DataError(
                f"{meta}: scene {s.index} has camera rotations; these baselines need a "
                "stabilised dataset (no --rotation-noise/--rotation-speed)"
            )
    return scenes


def camera_of(root: str | os.PathLike) -> dict:
    """The camera a dataset was rendered with: ``{"width", "height"}`` in pixels and
    ``"fov_deg"``, the horizontal field of view in degrees (from dataset.json). A network
    trained on it expects frames of that size and field of view."""
    cam = Dataset(root).info["config"]["camera"]
    focal = cam.get("focal_px")
    fov = cam["fov_deg"] if focal is None else fov_from_focal(focal, cam["width"])
    return {"width": int(cam["width"]), "height": int(cam["height"]), "fov_deg": float(fov)}


class FrameStore:
    """Decoded frames and depth maps, all in memory when they fit (else read on demand)."""

    def __init__(self, scenes: list[Scene], cache: bool | None = None, progress: bool = True):
        self.scenes = scenes
        first = scenes[0].load_rgb(0) if scenes else np.zeros((1, 1, 3), np.uint8)
        self.height, self.width = first.shape[:2]
        frames = sum(len(s.rgb) for s in scenes)
        nbytes = frames * self.height * self.width * 7  # 3 bytes RGB + 4 bytes depth
        self.cached = nbytes <= CACHE_LIMIT_BYTES if cache is None else cache
        self.nbytes = nbytes if self.cached else 0
        if self.cached:
            n, length = len(scenes), max((len(s.rgb) for s in scenes), default=0)
            self._rgb = np.zeros((n, length, self.height, self.width, 3), np.uint8)
            self._depth = np.zeros((n, length, self.height, self.width), np.float32)
            for k, s in enumerate(
                tqdm(scenes, desc="caching frames", unit="scene", disable=not progress, leave=False)
            ):
                for f in range(len(s.rgb)):
                    self._rgb[k, f] = self._checked(s.load_rgb(f), s.rgb[f])
                    self._depth[k, f] = self._checked(s.load_depth(f), s.depth[f])

    def _checked(self, a: np.ndarray, path: Path) -> np.ndarray:
        if a.shape[:2] != (self.height, self.width):
            raise DataError(
                f"{path}: size {a.shape[1]}x{a.shape[0]}, expected {self.width}x{self.height}"
            )
        return a

    def rgb(self, k: int, f: int) -> np.ndarray:
        if self.cached:
            return self._rgb[k, f]
        return self._checked(self.scenes[k].load_rgb(f), self.scenes[k].rgb[f])

    def depth(self, k: int, f: int) -> np.ndarray:
        if self.cached:
            return self._depth[k, f]
        return self._checked(self.scenes[k].load_depth(f), self.scenes[k].depth[f])


def normalise(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 -> (3, H, W) float32, (x/255 - 0.5)/0.2."""
    return ((img.astype(np.float32) / 255.0 - 0.5) / 0.2).transpose(2, 0, 1)


class PairDataset(torch.utils.data.Dataset):
    """Pairs of one split. ``mode='train'``: one random pair per frame index (original sampling);
    ``mode='eval'``: every fixed forward pair (i, i + shift).

    Items are dicts: ``input`` (6, H, W) float32, ``target`` (H, W) float32 metres (depth of the
    second frame, rescaled and clipped to ``depth_range`` in train mode, raw in eval mode),
    ``translation`` (3,) float32 metres (camera motion from first to second frame, camera axes,
    after flips), ``K`` (3, 3) (of the flipped images: a flip mirrors the principal point),
    ``scene``, ``frames`` (i1, i2), ``flips`` (horizontal, vertical).

    ``target="flow"`` (train mode only): ``target`` is instead the (2, H, W) float32 flow in
    pixels at the second frame's pixels towards the first frame (position in frame i1 minus
    position in frame i2), computed from the raw depth of frame i2 and the translation i2 → i1
    (after flips); NaN where a point is not in front of the first camera. Zero for i1 == i2.
    """

    def __init__(
        self,
        store: FrameStore,
        mode: str,
        shift: int = NOMINAL_SHIFT,
        seed: int = 0,
        target: str = "depth",
        depth_range: tuple[float, float] = (0.0, MAX_DEPTH),
    ):
        if mode not in ("train", "eval"):
            raise ValueError(mode)
        if target not in ("depth", "flow") or (target == "flow" and mode != "train"):
            raise ValueError(f"target {target!r} with mode {mode!r}")
        self.target, self.depth_range = target, depth_range
        self.store, self.mode, self.shift, self.seed = store, mode, shift, seed
        self.epoch = 0
        self.items: list[tuple[int, int]] = []
        for k, s in enumerate(store.scenes):
            if mode == "train":
                self.items += [(k, f) for f in range(len(s.rgb))]
            else:
                self.items += [(k, f) for f in range(len(s.rgb) - shift)]

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        k, f = self.items[i]
        scene = self.store.scenes[k]
        if self.mode == "eval":
            i1, i2 = f, f + self.shift
            target = self.store.depth(k, i2).copy()
            flip_h = flip_v = False
        else:
            rng = np.random.default_rng([self.seed, self.epoch, i])
            last = len(scene.rgb) - 1
            i1 = int(rng.integers(0, last + 1))
            i2 = min(last, i1 + round(2 * self.shift * rng.uniform()))
            if rng.uniform() > 0.5:
                i1, i2 = i2, i1
            if self.target == "flow":
                target = self.store.depth(k, i2)  # raw: the flow uses the true translation
            elif i1 == i2:
                target = np.full_like(self.store.depth(k, i2), STILL_TARGET)
            else:
                target = self.store.depth(k, i2) * (self.shift / abs(i2 - i1))
            if self.target == "depth":
                target = np.clip(target, *self.depth_range)
            flip_h, flip_v = rng.uniform() < 0.5, rng.uniform() < 0.5
        img1, img2 = self.store.rgb(k, i1), self.store.rgb(k, i2)
        translation = scene.translation(i1, i2)
        K = scene.K.copy()
        h, w = target.shape
        if flip_h:
            img1, img2, target = img1[:, ::-1], img2[:, ::-1], target[:, ::-1]
            translation = translation * np.array([-1.0, 1.0, 1.0])
            K[0, 2] = w - 1 - K[0, 2]
        if flip_v:
            img1, img2, target = img1[::-1], img2[::-1], target[::-1]
            translation = translation * np.array([1.0, -1.0, 1.0])
            K[1, 2] = h - 1 - K[1, 2]
        if self.target == "flow":
            depth = torch.from_numpy(np.ascontiguousarray(target, dtype=np.float64))
            target = flow_from_depth(depth, torch.from_numpy(K), torch.from_numpy(-translation))
            target = target.numpy()
        x = np.concatenate([normalise(img1), normalise(img2)], axis=0)
        return {
            "input": torch.from_numpy(np.ascontiguousarray(x)),
            "target": torch.from_numpy(np.ascontiguousarray(target, dtype=np.float32)),
            "translation": torch.from_numpy(translation.astype(np.float32)),
            "K": torch.from_numpy(K.astype(np.float32)),
            "scene": scene.index,
            "frames": torch.tensor([i1, i2]),
            "flips": torch.tensor([flip_h, flip_v]),
        }


class EpochSampler(torch.utils.data.Sampler):
    """Permutation of the dataset drawn from (seed, epoch), split across ranks, skippable."""

    def __init__(self, size: int, seed: int, rank: int = 0, world: int = 1):
        self.size, self.seed, self.rank, self.world = size, seed, rank, world
        self.epoch, self.skip = 0, 0

    def set_epoch(self, epoch: int, skip: int = 0) -> None:
        """Next iteration yields the permutation of ``epoch`` minus its first ``skip`` items."""
        self.epoch, self.skip = epoch, skip

    def _indices(self) -> list[int]:
        order = np.random.default_rng([self.seed, self.epoch, 0x5A]).permutation(self.size)
        return order[self.rank :: self.world].tolist()

    def __iter__(self):
        return iter(self._indices()[self.skip :])

    def __len__(self) -> int:
        return len(self._indices()) - self.skip
