"""Image pairs from a stillbox-gen dataset, read through stillbox_gen.dataset.Dataset.

Training pairs follow the original DepthNet sampling (its public loader): frame i1 uniform, shift =
round(2·nominal_shift·U) in {0..6}, i2 = min(last, i1 + shift), swapped with probability 0.5; the
target is depth(i2) · nominal_shift / |i2 − i1| (100 m when i1 == i2), clipped to the depth range
([0, 100] m; [10, 60] m for the clamped DepthNet of thesis 6.4);
random horizontal and vertical flips. Evaluation pairs are fixed forward pairs (i, i + shift) with
target depth(i + shift). Inputs are (x/255 − 0.5)/0.2 per channel, frames stacked to 6 channels.
Flow networks train on the same pairs with an optical-flow target (``target="flow"``): the exact
flow of the static scene at the second frame's pixels towards the first frame, from the second
frame's depth and the known translation (benchmark.core.flow).

On a rotating dataset (scenes whose camera turns) each pair's first frame, the reference, is
first stabilised to the second frame's orientation with the known rotation (the thesis' "D + O"
supervised DepthNet, §5.3): resampled through ``K·R·K⁻¹`` (``R``: the second frame's camera axes
→ the first's), its pixels the first frame does not see 0 in the normalised input (mid-grey), as
the unsupervised networks' stabilised references (benchmark.unsupervised.rotation); the pair's
translation is then expressed in the second frame's axes. Stabilised scenes are read as they are.

Every random draw comes from ``numpy.random.default_rng([seed, epoch, index])``: the same seed
gives the same batches whatever the worker count, and a resumed run continues the same sequence.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from stillbox_gen import layout
from stillbox_gen.camera import fov_from_focal
from stillbox_gen.conventions import MAX_DEPTH, NOMINAL_SHIFT
from stillbox_gen.dataset import Dataset, Scene
from stillbox_gen.errors import DatasetError
from stillbox_gen.packed import (
    PackedDataset,
    PackedScene,
    is_packed,
    open_dataset,
    record_member,
)

from .flow import flow_from_depth, warp_homography

STILL_TARGET = 100.0  # target for identical frames: "no motion => infinitely far", saturated
CACHE_LIMIT_BYTES = 8 * 1024**3

#: A dataset that cannot be used; the message names the file (stillbox_gen's DatasetError).
DataError = DatasetError


def read_dataset(root: str | os.PathLike) -> Dataset | PackedDataset:
    """The dataset ``root``, a folder or a pack of it (``stillbox-gen pack``: a folder holding
    index.json); stillbox_gen.packed.open_dataset decides, for every command's --data. DataError
    naming ``root`` when it is neither."""
    return open_dataset(root)


def read_scenes(root: str | os.PathLike, split: str, limit: int | None = None) -> list[Scene]:
    """The scenes of one split of the dataset or pack ``root`` (:func:`read_dataset`), in index
    order, the first ``limit`` only when given. A pack's scenes are read from its shards here,
    each shard's size and SHA-256 checked first (their frames stay in memory, encoded, as long
    as the scenes are referenced); a folder's are read from their files when used."""
    return list(read_dataset(root).scenes(split, limit=limit))


def check_packed_shards(root: str | os.PathLike) -> None:
    """When ``root`` is a pack: every shard's size and SHA-256 checked against its index.json
    (one read of the pack), DataError naming the first that differs; nothing for a folder."""
    ds = read_dataset(root)
    if isinstance(ds, PackedDataset):
        for shard in ds.shards:
            ds.verify(shard)


def load_scenes(root: str | os.PathLike, split: str, rotations: bool = False) -> list[Scene]:
    """Scenes of one split, in index order (:func:`read_scenes`: a dataset folder or its pack).
    Raises DataError naming the faulty file (or shard), or the record whose file name would
    lead outside ``root``, or, unless ``rotations``, a scene with camera rotations (the readers
    that stabilise them: PairDataset, depthnet-unsup*'s ``--pose``; the others need a stabilised
    dataset)."""
    scenes = read_scenes(root, split)
    for s in scenes:
        if not s.stabilised and not rotations:
            if isinstance(s, PackedScene):  # its record is a member of its shard
                meta = s.rgb[0].parent / record_member(s.index)
            else:
                meta = Path(root) / layout.chunk_name(s.index) / layout.METADATA_JSON
            raise DataError(
                f"{meta}: scene {s.index} has camera rotations; these baselines need a "
                "stabilised dataset (no --rotation-noise/--rotation-speed)"
            )
    return scenes


def camera_of(root: str | os.PathLike) -> dict:
    """The camera a dataset was rendered with: ``{"width", "height"}`` in pixels and
    ``"fov_deg"``, the horizontal field of view in degrees (from dataset.json). A network
    trained on it expects frames of that size and field of view. Only dataset.json is read (a
    pack holds it too): a checkpoint's training set needs no more of itself to be present."""
    info = PackedDataset(root).info if is_packed(root) else Dataset(root).info
    cam = info["config"]["camera"]
    focal = cam.get("focal_px")
    fov = cam["fov_deg"] if focal is None else fov_from_focal(focal, cam["width"])
    return {"width": int(cam["width"]), "height": int(cam["height"]), "fov_deg": float(fov)}


def nominal_displacement(scenes: list[Scene], shift: int) -> float:
    """Metres a depth network trained on ``scenes`` answers for: ``shift`` frames of the median
    displacement per frame (its depth targets are rescaled to that)."""
    return float(shift * np.median([s.displacement for s in scenes]))


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


#: the networks' input normalisation of 8-bit colour x, (x / 255 - NORM_MEAN) / NORM_STD, as the
#: original DepthNet code (core.contract)
NORM_MEAN, NORM_STD = 0.5, 0.2


def normalise(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 -> (3, H, W) float32, (x/255 - NORM_MEAN)/NORM_STD."""
    return ((img.astype(np.float32) / 255.0 - NORM_MEAN) / NORM_STD).transpose(2, 0, 1)


def eval_firsts(scene: Scene, shift: int) -> range:
    """First frames i of a scene's evaluation pairs (i, i + ``shift``): every frame that has a
    frame ``shift`` later."""
    return range(len(scene.rgb) - shift)


class PairDataset(torch.utils.data.Dataset):
    """Pairs of one split. ``mode='train'``: one random pair per frame index (original sampling);
    ``mode='eval'``: every fixed forward pair (i, i + shift).

    Items are dicts: ``input`` (6, H, W) float32, ``target`` (H, W) float32 metres (depth of the
    second frame, rescaled and clipped to ``depth_range`` in train mode, raw in eval mode),
    ``translation`` (3,) float32 metres (camera motion from first to second frame, in the second
    frame's camera axes, after flips), ``K`` (3, 3) (of the flipped images: a flip mirrors the
    principal point), ``scene``, ``frames`` (i1, i2), ``flips`` (horizontal, vertical).

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
                self.items += [(k, f) for f in eval_firsts(s, shift)]

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.items)

    def _draw(self, i: int, epoch: int) -> tuple[int, int, int, bool, bool]:
        """Pair ``i`` of ``epoch``: (scene position k, i1, i2, flip_h, flip_v)."""
        k, f = self.items[i]
        if self.mode == "eval":
            return k, f, f + self.shift, False, False
        rng = np.random.default_rng([self.seed, epoch, i])
        last = len(self.store.scenes[k].rgb) - 1
        i1 = int(rng.integers(0, last + 1))
        # four uniforms in one call: the same numbers as four rng.uniform() calls
        u_shift, u_swap, u_flip_h, u_flip_v = rng.random(4).tolist()
        i2 = min(last, i1 + round(2 * self.shift * u_shift))
        if u_swap > 0.5:
            i1, i2 = i2, i1
        return k, i1, i2, u_flip_h < 0.5, u_flip_v < 0.5

    def _target(self, k: int, i1: int, i2: int) -> np.ndarray:
        """(H, W) target of a pair before flips: the raw depth of i2 in eval mode and for flow
        targets, else rescaled to the nominal shift and clipped (may be a view of the store)."""
        if self.mode == "eval" or self.target == "flow":
            return self.store.depth(k, i2)
        if i1 == i2:
            target = np.full_like(self.store.depth(k, i2), STILL_TARGET)
        else:
            target = self.store.depth(k, i2) * (self.shift / abs(i2 - i1))
        return np.clip(target, *self.depth_range)

    def _camera(
        self, k: int, i1: int, i2: int, flip_h: bool, flip_v: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Translation (3,) and K (3, 3) of the (flipped) pair, and the homography (3, 3) that
        stabilises its (flipped) reference (None: a stabilised scene, or i1 == i2), float64."""
        scene = self.store.scenes[k]
        K = scene.K.copy()
        homography = None
        if scene.stabilised:
            translation = scene.translation(i1, i2)
        else:  # module doc: the reference turned to the target's axes
            translation = -scene.relative_pose(i1, i2)[:3, 3]
            if i1 != i2:
                turn = scene.relative_pose(i2, i1)[:3, :3]  # target axes -> reference axes
                homography = K @ turn @ np.linalg.inv(K)
        h, w = self.store.height, self.store.width
        for axis, size, flip in ((0, w, flip_h), (1, h, flip_v)):
            if not flip:
                continue
            translation = translation * np.where(np.arange(3) == axis, -1.0, 1.0)
            K[axis, 2] = size - 1 - K[axis, 2]
            if homography is not None:  # the same map between the mirrored pixels
                mirror = np.eye(3)
                mirror[axis, axis], mirror[axis, 2] = -1.0, size - 1
                homography = mirror @ homography @ mirror
        return translation, K, homography

    @staticmethod
    def _stabilise(pairs: np.ndarray, homographies: list[np.ndarray | None]) -> None:
        """In place: the reference (channels 0-2) of each normalised pair of ``pairs`` (N, 6, H,
        W) float32 with a homography, turned to its target's orientation (module doc)."""
        for j, homography in enumerate(homographies):
            if homography is None:
                continue
            reference = torch.from_numpy(pairs[j : j + 1, :3])
            turned, seen = warp_homography(reference, torch.from_numpy(homography)[None])
            pairs[j, :3] = torch.where(seen[:, None], turned, 0.0)[0].numpy()

    def __getitem__(self, i: int) -> dict:
        k, i1, i2, flip_h, flip_v = self._draw(i, self.epoch)
        scene = self.store.scenes[k]
        target = self._target(k, i1, i2)
        if self.mode == "eval":
            target = target.copy()
        img1, img2 = self.store.rgb(k, i1), self.store.rgb(k, i2)
        translation, K, homography = self._camera(k, i1, i2, flip_h, flip_v)
        if flip_h:
            img1, img2, target = img1[:, ::-1], img2[:, ::-1], target[:, ::-1]
        if flip_v:
            img1, img2, target = img1[::-1], img2[::-1], target[::-1]
        if self.target == "flow":
            depth = torch.from_numpy(np.ascontiguousarray(target, dtype=np.float64))
            target = flow_from_depth(depth, torch.from_numpy(K), torch.from_numpy(-translation))
            target = target.numpy()
        x = np.concatenate([normalise(img1), normalise(img2)], axis=0)
        self._stabilise(x[None], [homography])
        return {
            "input": torch.from_numpy(np.ascontiguousarray(x)),
            "target": torch.from_numpy(np.ascontiguousarray(target, dtype=np.float32)),
            "translation": torch.from_numpy(translation.astype(np.float32)),
            "K": torch.from_numpy(K.astype(np.float32)),
            "scene": scene.index,
            "frames": torch.tensor([i1, i2]),
            "flips": torch.tensor([flip_h, flip_v]),
        }

    def batch(self, indices: list[int], epoch: int | None = None) -> dict:
        """Items ``indices`` of ``epoch`` (default: the current one) as one batch: the same
        tensors as ``default_collate([self[i] for i in indices])``, bit for bit (same pairs,
        flips and values), with one normalisation of the whole batch's uint8 frames instead of
        one per frame, and no per-item tensors to collate."""
        epoch = self.epoch if epoch is None else epoch
        draws = [self._draw(i, epoch) for i in indices]
        n, h, w = len(draws), self.store.height, self.store.width
        frames = np.empty((n, 2, 3, h, w), np.uint8)
        target = np.empty((n, h, w), np.float32)
        translation, K = np.empty((n, 3)), np.empty((n, 3, 3))
        homographies = []
        for j, (k, i1, i2, flip_h, flip_v) in enumerate(draws):
            view = (slice(None, None, -1 if flip_v else 1), slice(None, None, -1 if flip_h else 1))
            frames[j, 0] = self.store.rgb(k, i1)[view].transpose(2, 0, 1)
            frames[j, 1] = self.store.rgb(k, i2)[view].transpose(2, 0, 1)
            target[j] = self._target(k, i1, i2)[view]
            translation[j], K[j], homography = self._camera(k, i1, i2, flip_h, flip_v)
            homographies.append(homography)
        if self.target == "flow":  # per pair, as __getitem__ (one call is not faster here)
            depth = torch.from_numpy(target.astype(np.float64))
            flows = [
                flow_from_depth(depth[j], torch.from_numpy(K[j]), torch.from_numpy(-translation[j]))
                for j in range(n)
            ]
            target = torch.stack(flows).numpy().astype(np.float32)
        x = frames.astype(np.float32)  # normalise's operations, in place on the whole batch
        x /= 255.0
        x -= 0.5
        x /= 0.2
        x = x.reshape(n, 6, h, w)
        self._stabilise(x, homographies)
        return {
            "input": torch.from_numpy(x),
            "target": torch.from_numpy(target),
            "translation": torch.from_numpy(translation.astype(np.float32)),
            "K": torch.from_numpy(K.astype(np.float32)),
            "scene": torch.tensor([self.store.scenes[d[0]].index for d in draws]),
            "frames": torch.tensor([d[1:3] for d in draws]),
            "flips": torch.tensor([d[3:5] for d in draws]),
        }


class PairBatches(torch.utils.data.Dataset):
    """A PairDataset read a batch at a time: item ``(epoch, indices)`` is
    ``pairs.batch(indices, epoch)``. The epoch travels with each batch, so DataLoader workers
    (persistent ones too) draw the same pairs as the training process would."""

    def __init__(self, pairs: PairDataset):
        self.pairs = pairs

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, key: tuple[int, list[int]]) -> dict:
        epoch, indices = key
        return self.pairs.batch(indices, epoch)


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


class EpochBatches(torch.utils.data.Sampler):
    """The full batches of an EpochSampler's current epoch as ``(epoch, indices)`` keys for
    PairBatches (the last, incomplete batch is dropped)."""

    def __init__(self, sampler: EpochSampler, batch_size: int):
        self.sampler, self.batch_size = sampler, batch_size

    def __iter__(self):
        order, epoch, b = list(self.sampler), self.sampler.epoch, self.batch_size
        for j in range(0, len(order) - b + 1, b):
            yield epoch, order[j : j + b]

    def __len__(self) -> int:
        return len(self.sampler) // self.batch_size
