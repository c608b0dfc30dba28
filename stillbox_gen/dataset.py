"""The one reader of a finished stillbox-gen dataset (docs/FORMAT.md), for ``preview``,
``stats``, the benchmark and your own code: :class:`Dataset` gives dataset.json and the scenes of
a split, each with its frame paths (checked to stay inside the dataset before anything is
opened), intrinsics, poses and loaders::

    from stillbox_gen.dataset import Dataset

    for scene in Dataset("data/stillbox-64").scenes("train"):
        rgb, depth = scene.load_rgb(0), scene.load_depth(0)  # (H, W, 3) uint8; (H, W) metres

Where each file lives is stillbox_gen.layout; file formats are stillbox_gen.formats; writing a
dataset is stillbox_gen.writer. This module needs neither Blender nor the generator's config.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from . import formats, layout, manifest
from .errors import DatasetError


@dataclass
class Scene:
    """One scene of a dataset: its frames' files and camera, in the conventions of
    docs/FORMAT.md (metres, seconds, pixels; OpenCV camera axes x right, y down, z forward)."""

    index: int  # global scene index
    split: str  # "train", "val" or "test"
    rgb: list[Path]  # frame files in frame order, checked to stay inside the dataset
    depth: list[Path]  # depth EXR files (planar depth in metres, float32, unclipped)
    K: np.ndarray  # (3, 3) intrinsics, pixels, pixel-centre convention
    cam2world: np.ndarray  # (frames, 4, 4) camera-to-world pose of each frame
    speed: np.ndarray  # (3,) m/s in the first frame's camera axes
    time_step: float  # seconds between frames
    record: dict = field(repr=False)  # the scene's metadata.json entry, every key
    # --flow: {(a, b): {"flow": .flo, "valid": PNG, "occluded": PNG}} of each stored frame pair
    flow_files: dict[tuple[int, int], dict[str, Path]] = field(default_factory=dict, repr=False)

    @property
    def frames(self) -> int:
        return len(self.rgb)

    @property
    def displacement(self) -> float:
        """Metres per frame."""
        return float(np.linalg.norm(self.speed) * self.time_step)

    @property
    def stabilised(self) -> bool:
        """True when every frame has the first frame's orientation."""
        return not self.record["orientation"]

    def translation(self, i1: int, i2: int) -> np.ndarray:
        """Camera displacement from frame i1 to frame i2, metres, in the first frame's camera
        axes (for a stabilised scene, every frame's axes)."""
        return (i2 - i1) * self.speed * self.time_step

    def relative_pose(self, i: int, j: int) -> np.ndarray:
        """(4, 4) map from frame i's camera coordinates to frame j's."""
        return np.linalg.inv(self.cam2world[j]) @ self.cam2world[i]

    def load_rgb(self, frame: int) -> np.ndarray:
        """Frame ``frame`` as (H, W, 3) uint8, RGB order, 8-bit sRGB."""
        return formats.read_rgb(self.rgb[frame])

    def load_depth(self, frame: int) -> np.ndarray:
        """Planar depth of frame ``frame`` as (H, W) float32 metres (not clipped)."""
        return formats.read_depth(self.depth[frame])

    def load_flow(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The stored optical flow from frame ``a`` to frame ``b`` (datasets made with --flow):
        ``(flow, valid, occluded)``: flow (H, W, 2) float32 pixels on frame a's grid, position
        in frame b minus position in frame a (x right, y down), NaN where not valid; the two
        (H, W) bool masks of stillbox_gen.flow.flow_masks. The flow file is Middlebury .flo or
        KITTI's 16-bit PNG (--flow-format kitti-png: 1/64 px steps, its valid channel equal to
        the valid mask). DatasetError when the dataset holds no flow for that pair or a file
        is missing, unreadable or disagrees with the others."""
        files = self.flow_files.get((a, b))
        if files is None:
            raise DatasetError(f"scene {self.index}: no stored flow from frame {a} to frame {b}")
        return decode_flow_files(self._flow_bytes(files), {k: str(p) for k, p in files.items()})

    def _flow_bytes(self, files: dict[str, Path]) -> dict[str, bytes]:
        """{key of layout.FLOW_KEYS: the bytes of that file} of one stored pair."""
        return {k: formats.read_file(files[k], k if k == "flow" else "mask") for k in files}


def decode_flow_files(
    data: dict[str, bytes], names: dict[str, str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:meth:`Scene.load_flow` of the bytes of a pair's files (``data`` and their ``names``, by
    key of layout.FLOW_KEYS), wherever they were read from (a folder or a packed shard)."""
    flow, channel = formats.decode_flow(data["flow"], names["flow"])
    valid = formats.decode_mask_png(data["valid"], names["valid"])
    occluded = formats.decode_mask_png(data["occluded"], names["occluded"])
    if valid.shape != flow.shape[:2] or occluded.shape != valid.shape:
        raise DatasetError(f"'{names['flow']}': its masks are not of the flow's size")
    if channel is not None and not np.array_equal(channel, valid):
        raise DatasetError(f"'{names['flow']}': its valid channel differs from '{names['valid']}'")
    flow[~valid] = np.nan
    return flow, valid, occluded


class Dataset:
    """A finished stillbox-gen dataset, read-only. Files are read when first needed and kept:
    dataset.json (:attr:`info`), the manifest's scene list, each chunk's metadata.json.

    Every error is a DatasetError (a ValueError) naming the file, or the record whose file name
    would lead outside ``root``; a dataset.json or manifest.parquet that is a symlink leading
    outside it is refused on construction."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"'{root}' is not a folder")
        for name in (layout.DATASET_JSON, layout.MANIFEST):  # before anything is opened
            formats.resolve_inside(self.root, name, f"'{root}'")
        self._metadata: dict[str, dict[int, dict]] = {}

    def __repr__(self) -> str:
        return f"Dataset('{self.root}')"

    @cached_property
    def info(self) -> dict:
        """dataset.json: generator, versions, parameters (``config``), counts."""
        path = self.root / layout.DATASET_JSON  # checked by __init__
        if not path.is_file():
            raise DatasetError(f"'{self.root}' has no dataset.json (not a stillbox-gen dataset)")
        try:
            return json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise DatasetError(f"cannot read '{path}' ({e})") from None

    @cached_property
    def splits(self) -> dict[int, str]:
        """{scene index: split} of every scene of the manifest, in index order."""
        path = self.root / layout.MANIFEST  # checked by __init__
        if not path.is_file():
            raise DatasetError(f"'{self.root}' has no manifest.parquet (not a finished dataset)")
        try:
            table = manifest.read_manifest(path, columns=["scene", "split"])
            scenes, splits = table.column("scene").to_pylist(), table.column("split").to_pylist()
            rows = zip(scenes, splits, strict=True)
            return dict(sorted(set(rows)))
        except Exception as e:  # noqa: BLE001 - any reader failure is the user's file
            raise DatasetError(f"cannot read '{path}' ({e})") from None

    def indices(self, split: str | None = None) -> list[int]:
        """Scene indices of ``split`` (every scene when None), ascending."""
        return [k for k, s in self.splits.items() if split is None or s == split]

    def scenes(self, split: str | None = None, limit: int | None = None) -> list[Scene]:
        """The scenes of ``split`` (all when None) in index order, the first ``limit`` only when
        given; reads only the metadata.json of their chunks. Every file name of these scenes is
        checked to stay inside the dataset before this returns."""
        return [self.scene(k) for k in self.indices(split)[:limit]]

    def scene(self, index: int) -> Scene:
        """Scene ``index`` (DatasetError when the manifest or metadata.json lacks it)."""
        split = self.splits.get(index)
        if split is None:
            raise DatasetError(f"{self.root / layout.MANIFEST}: no scene {index}")
        meta_path = self._metadata_path(index)
        rec = self._chunk_records(index).get(index)
        if rec is None:
            raise DatasetError(f"{meta_path}: no scene {index}, which the manifest lists")
        where = f"{meta_path}: scene {index}"
        chunk = layout.chunk_name(index)
        try:
            return Scene(
                index=index,
                split=split,
                rgb=[formats.resolve_inside(self.root, n, where, chunk) for n in rec["rgb"]],
                depth=[
                    formats.resolve_inside(self.root, n, where, chunk) for n in rec["depth_exr"]
                ],
                K=np.array(rec["K"], dtype=np.float64),
                cam2world=np.array(rec["cam2world"], dtype=np.float64),
                speed=np.array(rec["speed"], dtype=np.float64),
                time_step=float(rec["time_step"]),
                record=rec,
                flow_files={
                    (e["from"], e["to"]): {
                        k: formats.resolve_inside(self.root, e[k], where, chunk)
                        for k in layout.FLOW_KEYS
                    }
                    for e in rec.get("flow", [])
                },
            )
        except (KeyError, TypeError) as e:
            raise DatasetError(f"{where}: not a stillbox-gen record ({e!r})") from None

    def _metadata_path(self, index: int) -> Path:
        where = f"{self.root / layout.MANIFEST}: scene {index}"
        return formats.resolve_inside(
            self.root, f"{layout.chunk_name(index)}/{layout.METADATA_JSON}", where
        )

    def _chunk_records(self, index: int) -> dict[int, dict]:
        """{scene index: record} of the chunk holding scene ``index`` (read once)."""
        chunk = layout.chunk_name(index)
        if chunk not in self._metadata:
            path = self._metadata_path(index)
            try:
                meta = json.loads(path.read_text())
                self._metadata[chunk] = {s["index"]: s for s in meta["scenes"]}
            except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
                raise DatasetError(f"cannot read '{path}' ({e})") from None
        return self._metadata[chunk]
