"""``stillbox-gen pack D --format webdataset --out P``: a finished dataset as tar shards of whole
scenes (docs/FORMAT.md, "Packed shards"), for file systems and object stores where 1.6 M small
files (80,000 scenes) are slow to list and read. The reader is stillbox_gen.packed.

Each shard is written to a temporary name and renamed when complete (stillbox_gen.formats
atomic_write), and ``index.json``, which lists the shards with their SHA-256, is written last:
a folder without it is an interrupted pack. The bytes depend only on the dataset's files and
``--scenes-per-shard``: members in sorted order with a fixed mtime, owner and mode, so packing
the same dataset twice gives byte-identical shards. Only the standard library's ``tarfile``.
"""

from __future__ import annotations

import hashlib
import io
import json
import tarfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from . import formats, layout
from .dataset import Dataset, Scene
from .errors import ConfigError
from .layout import FLOW_KEYS
from .packed import (
    INDEX_JSON,
    PACK_FORMAT,
    PACK_VERSION,
    SPLIT_ORDER,
    depth_member,
    flow_member,
    record_member,
    rgb_member,
    shard_name,
)

DEFAULT_SCENES_PER_SHARD = 100  # about 200 MB at 256 px, 10 frames: WebDataset's advice
MEMBER_MODE = 0o644  # every member: a plain file, rw-r--r--, owner 0:0, mtime 0 (reproducible)


@dataclass(frozen=True)
class PackSummary:
    scenes: int
    shards: int
    bytes: int  # total size of the shards


class _HashingWriter:
    """A write-only file object that hashes (SHA-256) and counts what tarfile writes through it,
    so a shard's checksum costs no second read."""

    def __init__(self, f: BinaryIO) -> None:
        self.f, self.sha, self.size = f, hashlib.sha256(), 0

    def write(self, data: bytes) -> int:
        self.sha.update(data)
        self.size += len(data)
        return self.f.write(data)

    def tell(self) -> int:  # tarfile asks where the archive starts
        return self.size


def check_out(out: Path) -> None:
    """``--out`` must be a new or empty folder outside every dataset (ConfigError naming the
    flag); nothing is written here."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out: '{out}' is a file; give a new or empty folder")
    if out.is_dir() and any(out.iterdir()):
        raise ConfigError(f"--out: '{out}' is not empty; give a new or empty folder")
    dataset = layout.enclosing_dataset(out)
    if dataset is not None:  # `validate` would report the shards as stray files
        raise ConfigError(f"--out: '{out}' is inside the dataset '{dataset}'; write elsewhere")


def check_source(dataset: Path) -> None:
    """``DATASET`` must be a folder that ``stillbox-gen validate --quick`` accepts (ConfigError
    with validate's first problem). Files are checked against their records' SHA-256 while they
    are packed (:func:`_scene_files`), so they are read once."""
    from .validate import validate_dataset

    if not dataset.is_dir():
        raise ConfigError(f"DATASET: '{dataset}' is not a folder")
    problems, _ = validate_dataset(dataset, check_pixels=False)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise ConfigError(
            f"DATASET: '{dataset}': {len(problems)} problem(s): {problems[0]}{more}; "
            f"`stillbox-gen validate {dataset}` lists them"
        )


def _scene_files(root: Path, scene: Scene) -> dict[str, bytes]:
    """{member name: bytes} of a scene: its record, RGB and depth files and, with --flow, its
    flow and mask files (the --legacy copies are left out: they repeat the same frames). Each
    file is checked against the SHA-256 of its record when the record has them (ConfigError in
    ``validate``'s words)."""
    rec, chunk = scene.record, layout.chunk_name(scene.index)
    sums = rec.get("sha256") or {}
    members = {record_member(scene.index): (json.dumps(rec, allow_nan=False) + "\n").encode()}
    files = [
        (name, path, member)
        for f in range(scene.frames)
        for name, path, member in (
            (rec["rgb"][f], scene.rgb[f], rgb_member(scene.index, f, rec["rgb"][f])),
            (rec["depth_exr"][f], scene.depth[f], depth_member(scene.index, f)),
        )
    ]
    for entry in rec.get("flow", []):
        paths = scene.flow_files[entry["from"], entry["to"]]
        files += [(entry[k], paths[k], flow_member(scene.index, entry, k)) for k in FLOW_KEYS]
    for name, path, member in files:
        data = path.read_bytes()
        if name in sums and hashlib.sha256(data).hexdigest() != sums[name]:
            raise ConfigError(
                f"DATASET: '{root}': {chunk}/{name}: SHA-256 differs from the record of "
                f"scene {scene.index} (the file was changed, replaced or swapped)"
            )
        members[member] = data
    return members


def _write_shard(f: BinaryIO, scenes: Iterable[dict[str, bytes]]) -> tuple[str, int]:
    """The tar of ``scenes`` (each {member: bytes}) into ``f``; returns (SHA-256 hex, bytes)."""
    out = _HashingWriter(f)
    with tarfile.open(fileobj=out, mode="w", format=tarfile.USTAR_FORMAT) as tar:
        for members in scenes:
            for name in sorted(members):  # keys sort in scene order, so the whole tar is sorted
                data = members[name]
                info = tarfile.TarInfo(name)
                info.size, info.mtime, info.mode = len(data), 0, MEMBER_MODE
                info.uid = info.gid = 0
                info.uname = info.gname = ""
                tar.addfile(info, io.BytesIO(data))
    return out.sha.hexdigest(), out.size


def pack_webdataset(
    dataset: Path,
    out: Path,
    scenes_per_shard: int = DEFAULT_SCENES_PER_SHARD,
    progress: Callable[[str], None] | None = None,
) -> PackSummary:
    """Pack the finished dataset ``dataset`` into ``out`` (docs/FORMAT.md, "Packed shards").

    Every split's scenes in index order, ``scenes_per_shard`` whole scenes per shard (the last
    shard of a split may hold fewer); then dataset.json and manifest.parquet copied, and
    index.json. User mistakes raise ConfigError (``--out``, ``--scenes-per-shard``) or
    DatasetError / ConfigError naming the dataset's file, before anything is written except
    for a file found changed while packing; on any failure the files written so far are
    deleted, so ``out`` is left as it was.
    """
    dataset, out = Path(dataset), Path(out)
    if scenes_per_shard < 1:
        raise ConfigError(f"--scenes-per-shard: must be at least 1, got {scenes_per_shard}")
    check_out(out)
    check_source(dataset)
    ds = Dataset(dataset)
    info = ds.info
    by_split: dict[str, list[int]] = {}
    for k, split in ds.splits.items():
        by_split.setdefault(split, []).append(k)
    order = [s for s in SPLIT_ORDER if s in by_split] + sorted(set(by_split) - set(SPLIT_ORDER))
    scenes_of_shards = [
        (split, ks[i : i + scenes_per_shard])
        for split in order
        for ks in [by_split[split]]
        for i in range(0, len(ks), scenes_per_shard)
    ]

    created = not out.exists()
    written: list[Path] = []
    try:
        out.mkdir(parents=True, exist_ok=True)
        shards = []
        for n, (split, ks) in enumerate(scenes_of_shards):
            scenes = [ds.scene(k) for k in ks]
            # one scene's files in memory at a time: the tar is written as they are read
            members = (_scene_files(dataset, s) for s in scenes)
            path = out / shard_name(n)
            result: dict = {}

            def write(f: BinaryIO, members=members, result=result) -> None:
                result["sha256"], result["bytes"] = _write_shard(f, members)

            formats.atomic_write(path, write)
            written.append(path)
            shards.append(
                {
                    "name": path.name,
                    "split": split,
                    "scenes": ks,
                    "frames": [s.frames for s in scenes],
                    "bytes": result["bytes"],
                    "sha256": result["sha256"],
                }
            )
            if progress:
                progress(f"{path.name}: {len(ks)} {split} scenes, {result['bytes']:,} bytes")
        for name in (layout.DATASET_JSON, layout.MANIFEST):  # checked inside by Dataset
            data = (dataset / name).read_bytes()
            formats.atomic_write_bytes(out / name, data)
            written.append(out / name)
        index = {
            "format": PACK_FORMAT,
            "pack_version": PACK_VERSION,
            "format_version": info.get("format_version"),
            "seed": info.get("seed"),
            "fingerprint": info.get("fingerprint"),
            "scenes": sum(len(ks) for _, ks in scenes_of_shards),
            "scenes_per_shard": scenes_per_shard,
            "shards": shards,
        }
        formats.atomic_write_json(out / INDEX_JSON, index)  # last: the pack is complete
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise
    return PackSummary(index["scenes"], len(shards), sum(s["bytes"] for s in shards))
