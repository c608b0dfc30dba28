"""The writer's side of a stillbox-gen dataset (docs/FORMAT.md): its lifecycle.

Used by ``generate``, ``index`` and ``merge``: :func:`prepare_output` checks the
folder and marks it incomplete; :func:`commit_scene` moves a rendered scene into its chunk and
writes its record last (a scene is complete exactly when its record exists);
:func:`finalize` / :func:`index_dataset` write every metadata.json, manifest.parquet and a
complete dataset.json.

Reading is stillbox_gen.dataset; where each file lives is stillbox_gen.layout; file formats are
stillbox_gen.formats.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from importlib import metadata as importlib_metadata
from pathlib import Path

from . import config, formats, layout, manifest, photos
from .arguments import check_out_folder
from .config import CPU_DEVICE, DatasetConfig, denoise_quality
from .errors import ConfigError, DatasetError
from .flow import write_scene_flow
from .lock import folder_lock
from .phases import PhaseTimes, measure
from .record import scene_record

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
    check_out_folder(out, inside_dataset=True)  # out may be a dataset: it resumes or grows
    nested = layout.enclosing_dataset(out.parent)
    if nested is not None:
        raise ConfigError(f"--out: '{out}' is inside the dataset '{nested}'; write elsewhere")
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
    own = f".{layout.DATASET_JSON}{formats.TEMP_INFIX}"
    return path.name.startswith(own) or path.name == layout.LOCK_FILE


def pending_indices(out: Path, scenes: int, shard: tuple[int, int] = (0, 1)) -> list[int]:
    """Scene indices of shard (I, N) without a record (round-robin: k % N == I), ascending."""
    i, n = shard
    return [k for k in range(i, scenes, n) if not layout.record_path(out, k).is_file()]


def scene_checksums(folder: Path, record: dict) -> dict[str, str]:
    """{file name: SHA-256} of every file of a scene (layout.scene_files) found in ``folder``;
    stored in the record as ``sha256``."""
    return {name: formats.file_sha256(Path(folder) / name) for name in layout.scene_files(record)}


def commit_scene(
    out: Path, spec: dict, cfg: DatasetConfig, times: PhaseTimes | None = None
) -> dict:
    """Move a scene rendered into its temporary folder (layout.scene_tmp_name) into its chunk
    (with --flow, its flow files are first computed there: stillbox_gen.flow), then write its
    record (the completion mark) with the SHA-256 of every file of the scene. With ``times``,
    the flow is timed there as phase ``flow``, the hashing as ``hash``, the rest as ``commit``
    (stillbox_gen.phases)."""
    tmp = out / layout.scene_tmp_name(spec["index"])
    chunk_dir = tmp.parent
    with measure(times, "commit"):
        r = cfg.render
        record = scene_record(spec, r.image_format, r.legacy, r.flow, r.flow_format)
    if cfg.render.flow:
        with measure(times, "flow"):
            write_scene_flow(tmp, record)
    with measure(times, "hash"):
        record["sha256"] = scene_checksums(tmp, record)
    with measure(times, "commit"):
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
