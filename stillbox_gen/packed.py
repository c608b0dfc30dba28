"""The reader of a packed dataset (``stillbox-gen pack``; docs/FORMAT.md, "Packed shards"):
scenes streamed from the tar shards one shard at a time, nothing extracted to disk::

    from stillbox_gen.packed import PackedDataset

    for scene in PackedDataset("data/stillbox-64-wds").scenes("train"):
        rgb, depth = scene.load_rgb(0), scene.load_depth(0)  # (H, W, 3) uint8; (H, W) metres

Each scene is a :class:`PackedScene`, a :class:`stillbox_gen.dataset.Scene` whose frames are
decoded from the shard's bytes, with the same values, bit for bit, as the folder's files. Before
a shard is read, its size and SHA-256 are checked against index.json, so a corrupted or changed
shard is refused (DatasetError naming it) before any of its scenes is used. Only the standard
library's ``tarfile``, OpenCV and OpenEXR; no Blender, no torch (the torch dataset is
stillbox_gen.torch_dataset.StillBoxPackedPairs).

Member names (WebDataset's convention: the sample key is the name up to the first dot):
``<key>.json`` the scene's record, ``<key>.rgb_<f>.<png|jpg>`` and ``<key>.depth_<f>.exr`` frame
f's files, with ``<key>`` the global scene index in 7 digits; with --flow, also
``<key>.flow_<a>_<b>.<flo|png>``, ``<key>.valid_<a>_<b>.png`` and ``<key>.occluded_<a>_<b>.png``,
the files of the pair (a, b) (:meth:`PackedScene.load_flow`; packs of pack_version 1 have none).
"""

from __future__ import annotations

import io
import json
import os
import re
import tarfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path, PurePosixPath

import numpy as np

from . import formats, layout
from .dataset import Dataset, Scene, decode_flow_files
from .errors import DatasetError

PACK_FORMAT = "webdataset"
# 2: the --flow files are packed too (flow_member); a version-1 pack is read without them
PACK_VERSION = 2
READ_PACK_VERSIONS = (1, 2)
INDEX_JSON = "index.json"
SPLIT_ORDER = ("train", "val", "test")  # shards are numbered split by split in this order
KEY_DIGITS = 7  # LIMITS["scenes"] is 10 M: every key has the same width, names sort by scene
_SHARD = re.compile(r"shard-\d{6,}\.tar")
_MEMBER = re.compile(r"(\d+)\.([^/]+)")  # key, then WebDataset's "extension" (after 1st dot)


def shard_name(n: int) -> str:
    """``shard-<n>.tar``, n in 6 digits."""
    return f"shard-{n:06d}.tar"


def scene_key(index: int) -> str:
    """The WebDataset sample key of scene ``index``: its global index in KEY_DIGITS digits."""
    return f"{index:0{KEY_DIGITS}d}"


def record_member(index: int) -> str:
    """``<key>.json``: the scene's record (its metadata.json entry)."""
    return f"{scene_key(index)}.json"


def rgb_member(index: int, frame: int, name: str = "x.png") -> str:
    """``<key>.rgb_<f>.<ext>``: frame ``frame``'s RGB file, ``ext`` that of its file ``name``."""
    return f"{scene_key(index)}.rgb_{frame:02d}{PurePosixPath(name).suffix}"


def depth_member(index: int, frame: int) -> str:
    """``<key>.depth_<f>.exr``: frame ``frame``'s depth EXR."""
    return f"{scene_key(index)}.depth_{frame:02d}.exr"


def flow_member(index: int, entry: dict, key: str) -> str:
    """``<key>.<kind>_<a>_<b>.<ext>``: the file ``key`` (layout.FLOW_KEYS: flow, valid,
    occluded) of the record's flow entry ``entry`` (frames a to b), ``ext`` that of its file."""
    a, b = entry["from"], entry["to"]
    return f"{scene_key(index)}.{key}_{a:02d}_{b:02d}{PurePosixPath(entry[key]).suffix}"


def decode_rgb(data: bytes, where: str) -> np.ndarray:
    """An 8-bit PNG or JPEG file's bytes as (H, W, 3) uint8 RGB: the same decoder and values as
    stillbox_gen.formats.read_rgb. DatasetError naming ``where`` when it does not decode."""
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(f"cannot read image '{where}'")
    return img[..., ::-1].copy()


def decode_depth(data: bytes, where: str) -> np.ndarray:
    """A depth EXR file's bytes as (H, W) float32 metres: the same reader and values as
    stillbox_gen.formats.read_depth. DatasetError naming ``where`` when it does not decode."""
    import OpenEXR

    try:
        with OpenEXR.File(io.BytesIO(data)) as f:
            return np.array(f.channels()["Y"].pixels, dtype=np.float32)
    except Exception as e:  # noqa: BLE001 - any reader failure is the shard's member
        raise DatasetError(f"cannot read depth '{where}' ({e!r})") from None


@dataclass
class PackedScene(Scene):
    """A scene read from a shard: :class:`Scene`'s fields and methods, with ``rgb`` and
    ``depth`` naming the members (``<shard path>/<member>``, paths inside the tar, not files)
    and the frames decoded from the bytes held here (a scene's files stay in memory while the
    scene is referenced)."""

    rgb_data: list[bytes] = field(default_factory=list, repr=False)
    depth_data: list[bytes] = field(default_factory=list, repr=False)
    # --flow: {(a, b): {key of layout.FLOW_KEYS: bytes}}, named in ``flow_files`` (members)
    flow_data: dict[tuple[int, int], dict[str, bytes]] = field(default_factory=dict, repr=False)

    def load_rgb(self, frame: int) -> np.ndarray:
        """Frame ``frame`` as (H, W, 3) uint8, RGB order, 8-bit sRGB."""
        return decode_rgb(self.rgb_data[frame], str(self.rgb[frame]))

    def load_depth(self, frame: int) -> np.ndarray:
        """Planar depth of frame ``frame`` as (H, W) float32 metres (not clipped)."""
        return decode_depth(self.depth_data[frame], str(self.depth[frame]))

    def load_flow(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`Scene.load_flow` from the shard's members: ``(flow, valid, occluded)``, flow
        (H, W, 2) float32 pixels NaN where not valid, the same bits as the folder's."""
        files = self.flow_files.get((a, b))
        if files is None:
            raise DatasetError(f"scene {self.index}: no packed flow from frame {a} to frame {b}")
        return decode_flow_files(self.flow_data[a, b], {k: str(p) for k, p in files.items()})


@dataclass(frozen=True)
class Shard:
    """One shard as index.json lists it."""

    path: Path
    split: str
    scenes: tuple[int, ...]  # global scene indices, ascending
    frames: tuple[int, ...]  # frames of each scene
    size: int  # bytes
    sha256: str

    @property
    def name(self) -> str:
        return self.path.name


class PackedDataset:
    """A folder written by ``stillbox-gen pack --format webdataset``, read-only: index.json
    (:attr:`index`), dataset.json (:attr:`info`) and the shards, streamed on demand.

    Every error is a DatasetError (a ValueError) naming the file (or shard member)."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"'{root}' is not a folder")
        for name in (INDEX_JSON, layout.DATASET_JSON):  # before anything is opened
            formats.resolve_inside(self.root, name, f"'{root}'")
        self.shards = self._read_index()

    def __repr__(self) -> str:
        return f"PackedDataset('{self.root}')"

    @cached_property
    def index(self) -> dict:
        path = self.root / INDEX_JSON
        if not path.is_file():
            raise DatasetError(
                f"'{self.root}' has no {INDEX_JSON} (not a packed dataset, or an interrupted "
                "pack: delete it and pack again)"
            )
        try:
            return json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise DatasetError(f"cannot read '{path}' ({e})") from None

    @cached_property
    def info(self) -> dict:
        """dataset.json of the packed dataset (a copy)."""
        path = self.root / layout.DATASET_JSON
        try:
            return json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise DatasetError(f"cannot read '{path}' ({e})") from None

    def _read_index(self) -> list[Shard]:
        where = self.root / INDEX_JSON
        index = self.index
        if not isinstance(index, dict) or index.get("format") != PACK_FORMAT:
            raise DatasetError(f"{where}: not a '{PACK_FORMAT}' pack index")
        if index.get("pack_version") not in READ_PACK_VERSIONS:
            raise DatasetError(
                f"{where}: pack_version {index.get('pack_version')!r}, this reader reads "
                f"{' and '.join(map(str, READ_PACK_VERSIONS))}"
            )
        shards = []
        try:
            for n, s in enumerate(index["shards"]):
                if not isinstance(s["name"], str) or not _SHARD.fullmatch(s["name"]):
                    raise DatasetError(f"{where}: shard {n}: {s['name']!r} is not a shard name")
                path = formats.resolve_inside(self.root, s["name"], f"{where}: shard {n}")
                shard = Shard(
                    path=path,
                    split=str(s["split"]),
                    scenes=tuple(int(k) for k in s["scenes"]),
                    frames=tuple(int(f) for f in s["frames"]),
                    size=int(s["bytes"]),
                    sha256=str(s["sha256"]),
                )
                if len(shard.scenes) != len(shard.frames):
                    raise DatasetError(f"{where}: shard {n}: scenes and frames differ in length")
                shards.append(shard)
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, DatasetError):
                raise
            raise DatasetError(f"{where}: not a pack index ({e!r})") from None
        return shards

    @property
    def splits(self) -> dict[int, str]:
        """{scene index: split} of every packed scene, in index order."""
        return dict(sorted((k, s.split) for s in self.shards for k in s.scenes))

    def indices(self, split: str | None = None) -> list[int]:
        """Scene indices of ``split`` (every scene when None), ascending."""
        return [k for k, s in self.splits.items() if split is None or s == split]

    def shards_of(self, split: str | None = None) -> list[Shard]:
        """The shards holding ``split``'s scenes (all when None), in shard order."""
        return [s for s in self.shards if split is None or s.split == split]

    def scenes(
        self, split: str | None = None, verify: bool = True, limit: int | None = None
    ) -> Iterator[PackedScene]:
        """Stream the scenes of ``split`` (all when None), shard by shard; within a shard in
        index order (the shards of a split hold its scenes in index order). ``limit``: the
        first ``limit`` only (as :meth:`stillbox_gen.dataset.Dataset.scenes`'s; the shards
        after the last one are not read)."""
        if limit is not None and limit <= 0:
            return
        n = 0
        for shard in self.shards_of(split):
            for scene in self.read_shard(shard, verify):
                yield scene
                n += 1
                if n == limit:
                    return

    def verify(self, shard: Shard) -> None:
        """DatasetError naming the shard when its size or SHA-256 differs from index.json."""
        try:
            size = shard.path.stat().st_size
            digest = formats.file_sha256(shard.path) if size == shard.size else None
        except OSError as e:
            raise DatasetError(f"cannot read shard '{shard.path}' ({e.strerror})") from None
        if size != shard.size or digest != shard.sha256:
            what = "size" if size != shard.size else "SHA-256"
            raise DatasetError(
                f"shard '{shard.path}': {what} differs from {INDEX_JSON} (corrupted or changed "
                "since it was packed); pack the dataset again"
            )

    def read_shard(self, shard: Shard, verify: bool = True) -> Iterator[PackedScene]:
        """The scenes of one shard, streamed (tarfile's ``r|`` mode: one sequential read, no
        seek, nothing on disk). With ``verify`` (default), the whole shard's SHA-256 is checked
        first, so no scene of a corrupted shard is ever yielded (the shard is then read twice;
        the second read usually comes from the page cache)."""
        if verify:
            self.verify(shard)
        expected = iter(zip(shard.scenes, shard.frames, strict=True))
        key, members = None, {}
        try:
            with tarfile.open(shard.path, mode="r|") as tar:
                for m in tar:
                    match = _MEMBER.fullmatch(m.name)
                    if not m.isfile() or match is None:
                        raise DatasetError(f"shard '{shard.path}': unexpected member '{m.name}'")
                    if key is not None and match[1] != key:
                        yield self._scene(shard, key, members, expected)
                        members = {}
                    key = match[1]
                    if match[2] in members:
                        raise DatasetError(f"shard '{shard.path}': member '{m.name}' twice")
                    members[match[2]] = tar.extractfile(m).read()
                if key is not None:
                    yield self._scene(shard, key, members, expected)
        except (tarfile.TarError, OSError, EOFError) as e:
            raise DatasetError(f"cannot read shard '{shard.path}' ({e})") from None
        if next(expected, None) is not None:
            raise DatasetError(f"shard '{shard.path}': fewer scenes than {INDEX_JSON} lists")

    def _scene(
        self, shard: Shard, key: str, members: dict[str, bytes], expected: Iterator
    ) -> PackedScene:
        """The scene of one sample (its members by WebDataset extension)."""
        where = f"shard '{shard.path}': scene {key}"
        index, frames = next(expected, (None, None))
        if index is None or scene_key(index) != key:
            raise DatasetError(f"{where}: not the scene {INDEX_JSON} lists next ({index})")
        try:
            rec = json.loads(members.pop("json"))
            names = rec["rgb"]
            if rec["index"] != index or len(names) != frames or len(rec["depth_exr"]) != frames:
                raise DatasetError(f"{where}: its record disagrees with {INDEX_JSON}")
            rgb = [rgb_member(index, f, n).partition(".")[2] for f, n in enumerate(names)]
            depth = [depth_member(index, f).partition(".")[2] for f in range(frames)]
            # {(a, b): {file key: member extension}}; version 1 packed no flow
            entries = rec.get("flow", []) if self.index["pack_version"] >= 2 else []
            flow = {
                (e["from"], e["to"]): {
                    k: flow_member(index, e, k).partition(".")[2] for k in layout.FLOW_KEYS
                }
                for e in entries
            }
            wanted = {*rgb, *depth, *(m for f in flow.values() for m in f.values())}
            missing, extra = sorted(wanted - set(members)), sorted(set(members) - wanted)
            if missing or extra:
                raise DatasetError(f"{where}: missing members {missing}, unexpected {extra}")
            return PackedScene(
                index=index,
                split=shard.split,
                rgb=[shard.path / f"{key}.{m}" for m in rgb],
                depth=[shard.path / f"{key}.{m}" for m in depth],
                K=np.array(rec["K"], dtype=np.float64),
                cam2world=np.array(rec["cam2world"], dtype=np.float64),
                speed=np.array(rec["speed"], dtype=np.float64),
                time_step=float(rec["time_step"]),
                record=rec,
                rgb_data=[members[m] for m in rgb],
                depth_data=[members[m] for m in depth],
                flow_files={
                    pair: {k: shard.path / f"{key}.{m}" for k, m in f.items()}
                    for pair, f in flow.items()
                },
                flow_data={pair: {k: members[m] for k, m in f.items()} for pair, f in flow.items()},
            )
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, DatasetError):
                raise
            raise DatasetError(f"{where}: not a stillbox-gen record ({e!r})") from None


def is_packed(root: str | os.PathLike) -> bool:
    """True when ``root`` is (or claims to be) a packed dataset: it holds index.json. The one
    test of folder vs pack (:func:`open_dataset`)."""
    return (Path(root) / INDEX_JSON).exists()


def open_dataset(root: str | os.PathLike) -> Dataset | PackedDataset:
    """The dataset at ``root``, read-only: a :class:`PackedDataset` when it holds index.json
    (:func:`is_packed`; its index is read and checked here), else a folder
    (:class:`stillbox_gen.dataset.Dataset`). Both give the same scenes
    (``list(ds.scenes(split, limit=n))``) and ``info``. DatasetError naming ``root`` when it is
    neither a finished dataset (manifest.parquet) nor a complete pack, e.g. the shards of a
    pack interrupted before its index.json."""
    path = Path(root)
    if not path.is_dir():
        raise DatasetError(f"'{root}' is not a folder")
    if is_packed(path):
        return PackedDataset(path)
    if any(_SHARD.fullmatch(p.name) for p in path.glob("shard-*.tar")):
        raise DatasetError(
            f"'{root}' holds shards but no {INDEX_JSON}: an interrupted pack; delete it and "
            "pack again"
        )
    if not (path / layout.MANIFEST).is_file():
        raise DatasetError(
            f"'{root}' is not a finished stillbox-gen dataset (no {layout.MANIFEST}) nor a "
            f"packed one (no {INDEX_JSON})"
        )
    return Dataset(path)
