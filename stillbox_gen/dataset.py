"""A stillbox-gen dataset on disk (docs/FORMAT.md): its lifecycle and the one reader.

Lifecycle, used by ``generate``, ``index`` and ``merge``: :func:`prepare_output` checks the
folder and marks it incomplete; :func:`commit_scene` moves a rendered scene into its chunk and
writes its record last (a scene is complete exactly when its record exists);
:func:`finalize` / :func:`index_dataset` write every metadata.json, manifest.parquet and a
complete dataset.json.

Reading, for ``preview``, ``stats``, the benchmark and your own code: :class:`Dataset` gives
dataset.json and the scenes of a split, each with its frame paths (checked to stay inside the
dataset before anything is opened), intrinsics, poses and loaders::

    from stillbox_gen.dataset import Dataset

    for scene in Dataset("data/stillbox-64").scenes("train"):
        rgb, depth = scene.load_rgb(0), scene.load_depth(0)  # (H, W, 3) uint8; (H, W) metres

Where each file lives is stillbox_gen.layout; file formats are stillbox_gen.formats.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from functools import cached_property
from importlib import metadata as importlib_metadata
from pathlib import Path

import numpy as np

from . import config, formats, layout, manifest, photos
from .config import CPU_DEVICE, ConfigError, DatasetConfig, denoise_quality
from .formats import DatasetError
from .lock import folder_lock

#: Frames between the two images of a nominal StillBox pair (i, i + 3): the benchmark's fixed
#: evaluation pairs, the displacement its depth targets are expressed for (3 frames of 0.1 m, as
#: in the thesis), and the shift of ``stillbox-gen stats``.
NOMINAL_SHIFT = 3

#: Metres. Depth is clipped to [0, MAX_DEPTH] for training and scoring (files hold it unclipped).
MAX_DEPTH = 100.0


def default_root(width: int, height: int) -> Path:
    """The generator's default ``--out`` for frames of width x height pixels:
    ``data/stillbox-<W>`` when square, ``data/stillbox-<W>x<H>`` otherwise (relative path)."""
    res = f"{width}" if width == height else f"{width}x{height}"
    return Path("data") / f"stillbox-{res}"


# ---------------------------------------------------------------- what dataset.json says


def versions() -> dict:
    """Installed versions of stillbox-gen, bpy and numpy ("unknown" when not installed)."""

    def v(name: str) -> str:
        try:
            return importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            return "unknown"

    return {"stillbox-gen": v("stillbox-gen"), "blender (bpy)": v("bpy"), "numpy": v("numpy")}


def generator_name() -> str:
    return f"stillbox-gen {versions()['stillbox-gen']}"


def dataset_info(
    cfg: DatasetConfig, scenes: int, complete: bool, device: str = CPU_DEVICE, **extra
) -> dict:
    """dataset.json: versions, parameters and render settings (``device``: the Cycles devices
    that rendered it, see :func:`join_devices`); ``extra`` keys come last."""
    r, w, h = cfg.render, cfg.camera.width, cfg.camera.height
    return {
        "format_version": formats.FORMAT_VERSION,
        "complete": complete,
        "versions": versions(),
        "preset": cfg.preset,
        "seed": cfg.seed,
        "fingerprint": cfg.fingerprint(),
        "scenes": scenes,
        "frames_per_scene": cfg.camera.frames,
        "chunk_size": layout.CHUNK_SIZE,
        "render": {
            "engine": "CYCLES",
            "device": device,
            "shading": r.shading,
            "samples": r.samples,
            "denoiser": (
                f"OPENIMAGEDENOISE ({denoise_quality(r.denoise_quality, w, h)})"
                if r.denoise
                else None
            ),
            "max_bounces": r.max_bounces,
            "view_transform": "Standard",
            "rgb": f"8-bit sRGB {r.image_format}",
            "depth": formats.DEPTH_CONVENTION,
            "pixel_filter": "box, 1 pixel wide (samples integrate the pixel's area)",
            "noise_seed": (
                "per frame, derived from the scene seed"
                if r.shading == "path"
                else "one per scene (the scene seed): fixed sample placement in every frame"
            ),
            "photos": photo_source(cfg),
        },
        "config": cfg.to_dict(),
        **extra,
    }


def photo_source(cfg: DatasetConfig) -> str | None:
    """Where the photo textures come from, for dataset.json."""
    m = cfg.materials
    if m.texture_files:
        return f"--textures ({len(m.texture_files)} images of config.materials.textures_dir)"
    return photos.BUNDLED_SOURCE if m.photos == "bundled" else None


def chunk_args(cfg_dict: dict, generator: str) -> dict:
    """The ``args`` block of every metadata.json: original keys plus every generator parameter."""
    from .camera import fov_from_focal

    cam = cfg_dict["camera"]
    focal = cam["focal_px"]
    fov = cam["fov_deg"] if focal is None else fov_from_focal(focal, cam["width"])
    return {
        "fov": fov,
        "resolution": [cam["width"], cam["height"]],
        "frames": cam["frames"],
        "displacement": cam["displacement"],
        "max_distance": cfg_dict["render"]["max_distance"],
        "depth_convention": formats.DEPTH_CONVENTION,
        "generator": generator,
        "format_version": formats.FORMAT_VERSION,
        "config": cfg_dict,
    }


def join_devices(*values: str | None) -> str:
    """dataset.json's ``render.device`` of a dataset rendered on several Cycles devices (e.g.
    resumed with another --device, or merged): each once, in order, joined by " + "."""
    names = [n for v in values if v for n in v.split(" + ")]
    return " + ".join(dict.fromkeys(names)) or CPU_DEVICE


# ---------------------------------------------------------------- lifecycle


def prepare_output(out: Path, cfg: DatasetConfig, scenes: int, device: str = CPU_DEVICE) -> str:
    """Check --out, mark the dataset incomplete; ConfigError (nothing written) on conflicts.
    Returns its ``render.device``: ``device`` after those recorded there (join_devices)."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out: '{out}' exists and is a file, not a folder")
    existing = out / layout.DATASET_JSON
    recorded = None  # the devices of earlier runs into it
    try:
        formats.resolve_inside(out, layout.DATASET_JSON, f"--out: '{out}'")
    except DatasetError as e:
        raise ConfigError(str(e)) from None
    if existing.is_file():
        try:
            old = json.loads(existing.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise ConfigError(f"--out: cannot read '{existing}' ({e})") from None
        if old.get("fingerprint") != cfg.fingerprint():
            raise ConfigError(
                f"--out: '{out}' holds a dataset made with other parameters "
                f"(preset {old.get('preset')!r}, seed {old.get('seed')}); "
                "use the same parameters to resume or extend it, or another --out"
            )
        if old.get("scenes", 0) > scenes:
            raise ConfigError(
                f"--scenes: {scenes} is fewer than the {old['scenes']} scenes already in '{out}'"
            )
        recorded = old.get("render", {}).get("device")
    elif out.is_dir() and any(not _is_own_temporary(p) for p in out.iterdir()):
        if existing.is_file():  # another shard's dataset.json appeared meanwhile: check it
            return prepare_output(out, cfg, scenes, device)
        raise ConfigError(
            f"--out: '{out}' is a non-empty folder that is not a stillbox-gen dataset"
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"--out: cannot create '{out}' ({e.strerror})") from None
    if not os.access(out, os.W_OK):
        raise ConfigError(f"--out: '{out}' is not writable")
    device = join_devices(recorded, device)
    state = dataset_info(cfg, scenes, complete=False, device=device)
    formats.atomic_write_json(existing, state, indent=2)
    (out / layout.MANIFEST).unlink(missing_ok=True)
    return device


def _is_own_temporary(path: Path) -> bool:
    """A dataset.json being written by another shard that started into the same new folder, or
    the lock file of a run (stillbox_gen.lock; left behind by a run killed before it wrote)."""
    return path.name.startswith(f".{layout.DATASET_JSON}.tmp-") or path.name == layout.LOCK_FILE


def pending_indices(out: Path, scenes: int, shard: tuple[int, int] = (0, 1)) -> list[int]:
    """Scene indices of shard (I, N) without a record (round-robin: k % N == I), ascending."""
    i, n = shard
    return [k for k in range(i, scenes, n) if not layout.record_path(out, k).is_file()]


def scene_checksums(folder: Path, record: dict) -> dict[str, str]:
    """{file name: SHA-256} of every file of a scene (layout.scene_files) found in ``folder``;
    stored in the record as ``sha256``."""
    return {name: formats.file_sha256(Path(folder) / name) for name in layout.scene_files(record)}


def commit_scene(out: Path, spec: dict, cfg: DatasetConfig) -> dict:
    """Move a scene rendered into its temporary folder (layout.scene_tmp_name) into its chunk,
    then write its record (the completion mark) with the SHA-256 of every file of the scene."""
    tmp = out / layout.scene_tmp_name(spec["index"])
    chunk_dir = tmp.parent
    record = layout.scene_record(spec, cfg.render.image_format, cfg.render.legacy)
    record["sha256"] = scene_checksums(tmp, record)
    for f in sorted(tmp.iterdir()):
        os.replace(f, chunk_dir / f.name)
    rec_path = layout.record_path(out, spec["index"])
    rec_path.parent.mkdir(exist_ok=True)
    formats.atomic_write_json(rec_path, record)
    formats.remove_tree(tmp)
    return record


@dataclass
class Totals:
    """What an indexed dataset holds: scenes, frames, rejected layouts, scenes per split."""

    scenes: int
    frames: int
    rejected: int
    split_counts: dict


def finalize(
    out: Path, cfg: DatasetConfig, scenes: int, run_info: dict, device: str = CPU_DEVICE
) -> Totals:
    """Write every chunk's metadata.json, the manifest and a complete dataset.json (with
    ``run_info`` as its ``run`` block and ``device`` as ``render.device``) from the scenes'
    records."""
    records = [json.loads(layout.record_path(out, k).read_text()) for k in range(scenes)]
    args = chunk_args(cfg.to_dict(), generator_name())
    for start in range(0, scenes, layout.CHUNK_SIZE):
        meta = {"args": args, "scenes": records[start : start + layout.CHUNK_SIZE]}
        formats.atomic_write_json(out / layout.chunk_name(start) / layout.METADATA_JSON, meta)
    table = manifest.write_manifest(out / layout.MANIFEST, records, cfg.seed, cfg.split)
    splits = table.column("split").to_pylist()
    frames = cfg.camera.frames
    totals = Totals(
        scenes=scenes,
        frames=scenes * frames,
        rejected=sum(r["rejected"] for r in records),
        split_counts={s: splits.count(s) // frames for s in manifest.SPLITS},
    )
    info = dataset_info(
        cfg,
        scenes,
        complete=True,
        device=device,
        frames=totals.frames,
        rejected_scenes=totals.rejected,
        split_scenes=totals.split_counts,
        run=run_info,
    )
    formats.atomic_write_json(out / layout.DATASET_JSON, info, indent=2)
    return totals


def index_dataset(out: Path, run_info: dict | None = None) -> Totals:
    """Write metadata, manifest and a complete dataset.json for a folder filled by shards;
    ``run_info`` replaces dataset.json's ``run`` block when given."""
    try:
        info_path = formats.resolve_inside(out, layout.DATASET_JSON, f"DATASET: '{out}'")
    except DatasetError as e:
        raise ConfigError(str(e)) from None
    if not info_path.is_file():
        raise ConfigError(
            f"DATASET: '{out}' has no {layout.DATASET_JSON} (not a stillbox-gen dataset)"
        )
    with folder_lock(out, "DATASET"):  # refused while a run writes into it
        return _index(out, run_info)


def _index(out: Path, run_info: dict | None) -> Totals:
    """:func:`index_dataset` once the folder's lock is held."""
    info_path = out / layout.DATASET_JSON
    info = json.loads(info_path.read_text())
    cfg = config.from_dict(info["config"])
    if cfg.fingerprint() != info["fingerprint"]:
        raise ConfigError(f"DATASET: '{info_path}' config does not match its fingerprint")
    missing = pending_indices(out, info["scenes"])
    if missing:
        shown = ", ".join(map(str, missing[:10])) + (" ..." if len(missing) > 10 else "")
        raise ConfigError(
            f"DATASET: '{out}' lacks {len(missing)} of {info['scenes']} scenes ({shown}); "
            "run the missing shards first"
        )
    run_info = run_info or info.get("run", {"indexed_from": "shards"})
    device = join_devices(info.get("render", {}).get("device"))
    return finalize(out, cfg, info["scenes"], run_info, device)


# ---------------------------------------------------------------- the reader


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
