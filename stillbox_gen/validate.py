"""Check a dataset folder against docs/FORMAT.md; every problem names the file it concerns.

Besides the schemas and the manifest, it checks the integrity of the files: each scene's
``.records`` file equals its metadata.json entry, every file matches the SHA-256 in its record,
the folders hold no file that no record names, and dataset.json's seed and fingerprint agree with
its config and the scenes' seeds. What dataset.json's config determines is recomputed and
compared: each chunk's metadata.json ``args``, each record's K, frame size, time step and photo
names, and dataset.json's own frame and split counts and render settings. Paths from records
(and dataset.json, manifest.parquet, metadata.json themselves) never leave the dataset folder.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import cv2
import jsonschema
import numpy as np

from . import config, formats, layout, manifest, schema
from .errors import DatasetError
from .layout import DATASET_JSON, MANIFEST, flow_entries
from .scene import scene_seed


def _schema_problems(obj, sch: dict, where: str, limit: int = 5) -> list[str]:
    validator = jsonschema.Draft202012Validator(sch)
    errors = sorted(validator.iter_errors(obj), key=lambda e: list(e.absolute_path))
    out = []
    for e in errors[:limit]:
        path = "/".join(str(p) for p in e.absolute_path) or "(root)"
        out.append(f"{where}: {path}: {e.message}")
    return out


def _check_frame(root: Path, rgb: str, depth: str, w: int, h: int) -> list[str]:
    """Pixel checks of one frame; ``rgb`` and ``depth`` are checked paths relative to ``root``."""
    problems = []
    img = cv2.imread(str(root / rgb), cv2.IMREAD_UNCHANGED)
    if img is None:
        problems.append(f"{rgb}: missing or unreadable image")
    elif img.shape != (h, w, 3) or img.dtype != np.uint8:
        problems.append(f"{rgb}: expected {h}x{w}x3 uint8, got {img.shape} {img.dtype}")
    try:
        d = formats.read_depth_exr(root / depth)
    except Exception as e:  # noqa: BLE001 - any reader failure is a problem to report
        return [*problems, f"{depth}: unreadable depth EXR ({e})"]
    if d.shape != (h, w):
        problems.append(f"{depth}: expected {h}x{w}, got {d.shape}")
    elif not np.all(np.isfinite(d)) or not np.all(d > 0):
        bad = int(np.sum(~np.isfinite(d) | (d <= 0)))
        problems.append(f"{depth}: {bad} pixels not finite and positive")
    return problems


def _check_flow(root: Path, chunk: str, entry: dict, w: int, h: int) -> list[str]:
    """Pixel checks of one stored flow pair (--flow): sizes, masks, finite where valid; a KITTI
    PNG's valid channel equal to the valid mask."""
    name = f"{chunk}/{entry['flow']}"
    try:
        flow, channel = formats.decode_flow(formats.read_file(root / name, "flow"), name)
        valid = formats.read_mask_png(root / chunk / entry["valid"])
        occluded = formats.read_mask_png(root / chunk / entry["occluded"])
    except DatasetError as e:
        return [str(e)]
    if flow.shape != (h, w, 2) or valid.shape != (h, w) or occluded.shape != (h, w):
        return [f"{name}: expected {h}x{w} flow and masks, got {flow.shape[:2]}, {valid.shape}"]
    problems = []
    if np.any(occluded & ~valid):
        problems.append(f"{chunk}/{entry['occluded']}: occluded pixels outside the valid mask")
    if not np.all(np.abs(flow[valid]) < formats.FLO_UNKNOWN / 10):
        problems.append(f"{name}: flow not finite at valid pixels")
    if channel is not None and not np.array_equal(channel, valid):
        problems.append(f"{name}: its valid channel differs from {chunk}/{entry['valid']}")
    return problems


def _info_problems(info: dict) -> list[str]:
    """dataset.json's seed and fingerprint against its own config."""
    problems = []
    if not isinstance(info["config"], dict):
        return [f"{DATASET_JSON}: config is not an object"]
    if info["seed"] != info["config"].get("seed"):
        problems.append(
            f"{DATASET_JSON}: seed {info['seed']} differs from config.seed "
            f"{info['config'].get('seed')}"
        )
    try:
        fingerprint = config.from_dict(info["config"]).fingerprint()
    except Exception as e:  # noqa: BLE001 - a malformed config is a problem to report
        return [*problems, f"{DATASET_JSON}: config is not a stillbox-gen config ({e})"]
    if fingerprint != info["fingerprint"]:
        problems.append(
            f"{DATASET_JSON}: fingerprint {info['fingerprint']} does not match its config "
            f"({fingerprint}): the config was edited"
        )
    return problems


def _config_of(info: dict) -> config.DatasetConfig | None:
    """dataset.json's config when it is a stillbox-gen config matching its fingerprint (the
    other cases are reported by _info_problems), else None."""
    try:
        cfg = config.from_dict(info["config"])
        return cfg if cfg.fingerprint() == info["fingerprint"] else None
    except Exception:  # noqa: BLE001 - reported by _info_problems
        return None


def _first_difference(got, want, path: str) -> tuple[str, object, object] | None:
    """(path, got, want) of the first value that differs between two JSON values (floats
    within 1e-12 relative: datasets written before stillbox_gen.portable derived their field of
    view with the machine's libm, which may round the last bit otherwise)."""
    if isinstance(got, dict) and isinstance(want, dict):
        for key in sorted({*got, *want}, key=str):
            if key not in got or key not in want:
                return f"{path}.{key}", got.get(key, "(missing)"), want.get(key, "(missing)")
            found = _first_difference(got[key], want[key], f"{path}.{key}")
            if found:
                return found
        return None
    if isinstance(got, list) and isinstance(want, list) and len(got) == len(want):
        for i, (a, b) in enumerate(zip(got, want, strict=True)):
            found = _first_difference(a, b, f"{path}[{i}]")
            if found:
                return found
        return None
    numbers = all(isinstance(v, int | float) and not isinstance(v, bool) for v in (got, want))
    if numbers and math.isclose(got, want, rel_tol=1e-12):
        return None
    return None if got == want and type(got) is type(want) else (path, got, want)


# dataset.json's render settings that its config determines (the others describe conventions)
RENDER_FROM_CONFIG = (
    "shading",
    "samples",
    "max_bounces",
    "rgb",
    "denoiser",
    "noise_seed",
    "photos",
)
RENDER_REQUIRED = RENDER_FROM_CONFIG[:4]


def _derived_problems(info: dict, cfg: config.DatasetConfig) -> list[str]:
    """dataset.json's fields that its config determines (render settings, frames, splits,
    versions' shape), recomputed from the config and compared."""
    from .writer import dataset_info

    problems = []
    render = info["render"] if isinstance(info["render"], dict) else {}
    device = render.get("device") or config.CPU_DEVICE  # not derived from the config
    want = dataset_info(cfg, info["scenes"], complete=True, device=device)
    for key in ("format_version", "preset", "frames_per_scene", "chunk_size"):
        if key in info and info[key] != want[key]:
            problems.append(
                f"{DATASET_JSON}: {key} is {info[key]!r}, but its config gives {want[key]!r}"
            )
    for key in RENDER_FROM_CONFIG:  # older datasets may lack the last ones
        if (key in render or key in RENDER_REQUIRED) and render.get(key) != want["render"][key]:
            problems.append(
                f"{DATASET_JSON}: render.{key} is {render.get(key, '(missing)')!r}, but its "
                f"config gives {want['render'][key]!r}"
            )
    if info["frames"] != info["scenes"] * cfg.camera.frames:
        problems.append(
            f"{DATASET_JSON}: frames {info['frames']!r} is not scenes x config.camera.frames "
            f"({info['scenes']} x {cfg.camera.frames})"
        )
    splits = [manifest.split_of(cfg.seed, k, cfg.split) for k in range(info["scenes"])]
    counts = {s: splits.count(s) for s in manifest.SPLITS}
    if info["split_scenes"] != counts:
        problems.append(
            f"{DATASET_JSON}: split_scenes {info['split_scenes']!r} differs from the scenes' "
            f"splits, which (seed, config.split) give ({counts})"
        )
    v = info["versions"]
    if not (isinstance(v, dict) and all(isinstance(x, str) for x in v.values())):
        problems.append(f"{DATASET_JSON}: versions is not a {{package: version}} object")
    elif sorted(v) != _versions_keys():
        problems.append(f"{DATASET_JSON}: versions names {sorted(v)}, expected {_versions_keys()}")
    bad = [n for n in cfg.materials.texture_files if not config.is_plain_name(n)]
    if bad:
        problems.append(
            f"{DATASET_JSON}: config.materials.texture_files names {bad[0]!r}, which is no plain "
            "file name (it would lead outside textures_dir)"
        )
    return problems


def _versions_keys() -> list[str]:
    """The packages dataset.json's ``versions`` names (writer.versions)."""
    from .writer import versions

    return sorted(versions())


def _args_problems(info: dict, args: dict, where: str) -> list[str]:
    """A chunk's metadata.json ``args`` against what dataset.json's config and version give."""
    from .writer import chunk_args

    version = info["versions"].get("stillbox-gen") if isinstance(info["versions"], dict) else None
    want = chunk_args(info["config"], f"stillbox-gen {version}")
    render = info["render"] if isinstance(info["render"], dict) else {}
    want["depth_convention"] = render.get("depth", want["depth_convention"])  # its own version's
    found = _first_difference(args, want, "args")
    if found is None:
        return []
    path, got, expected = found
    return [f"{where}: {path} is {got!r}, but dataset.json gives {expected!r}"]


def _scene_config_problems(s: dict, cfg: config.DatasetConfig, where: str) -> list[str]:
    """A record's intrinsics, frame size, time step and photos against dataset.json's config."""
    from .scene import foreign_photos

    where = f"{where}: scene {s['index']}"
    c = cfg.camera
    problems = []
    if s["resolution"] != [c.width, c.height]:
        problems.append(
            f"{where}: resolution {s['resolution']} differs from dataset.json's config "
            f"({c.width}x{c.height})"
        )
    try:
        K = np.asarray(s["K"], dtype=float)
    except ValueError:  # rows of unequal lengths
        K = np.zeros(0)
    if K.shape != (3, 3) or not np.allclose(K, c.K(), rtol=1e-9, atol=1e-9):
        problems.append(
            f"{where}: K {s['K']} differs from the K of dataset.json's config ({c.K().tolist()})"
        )
    if not math.isclose(s["time_step"], c.time_step, rel_tol=1e-12):
        problems.append(
            f"{where}: time_step {s['time_step']} differs from dataset.json's config "
            f"({c.time_step})"
        )
    r = cfg.render
    want = flow_entries(s["scene_in_chunk"], s["length"], r.flow_format) if r.flow else None
    if s.get("flow") != want:
        said = "its flow files" if cfg.render.flow else "no flow files (made without --flow)"
        problems.append(f"{where}: flow entries differ from dataset.json's config ({said})")
    found = foreign_photos(s, cfg.materials)
    if found:
        problems.append(
            f"{where}: photo {found[0]!r} is not one of the dataset's photos (config.materials)"
        )
    return problems


def _record_problems(root: Path, s: dict) -> list[str]:
    """The scene's ``.records`` file must exist and equal its metadata.json entry ``s``."""
    name = layout.record_name(s["index"])
    try:
        path = formats.resolve_inside(root, name, f"scene {s['index']}")
        on_disk = json.loads(path.read_text())
    except formats.UnsafePathError as e:
        return [str(e)]
    except FileNotFoundError:
        return [f"{name}: missing record of scene {s['index']} (listed in metadata.json)"]
    except (OSError, json.JSONDecodeError) as e:
        return [f"{name}: unreadable record of scene {s['index']} ({e})"]
    if not isinstance(on_disk, dict):
        return [f"{name}: record of scene {s['index']} is not a JSON object"]
    if on_disk != s:
        keys = sorted(k for k in {*on_disk, *s} if on_disk.get(k) != s.get(k))
        return [f"{name}: differs from scene {s['index']} in metadata.json on {keys[:5]}"]
    return []


def _file_problems(root: Path, chunk: str, s: dict, check: bool) -> tuple[list[str], bool]:
    """Every file of scene ``s`` inside the dataset and present; with ``check``, its SHA-256 as
    recorded and its pixels. Returns (problems, whether the record holds checksums)."""
    problems: list[str] = []
    where = f"{chunk}/metadata.json: scene {s['index']}"
    sums = s.get("sha256")
    if sums is not None and not isinstance(sums, dict):
        return [f"{where}: sha256 is not a {{file name: digest}} object"], True
    safe = set()
    for name in layout.scene_files(s):
        rel = f"{chunk}/{name}"
        try:
            path = formats.resolve_inside(root, name, where, folder=chunk)
        except formats.UnsafePathError as e:
            problems.append(str(e))
            continue
        if not path.is_file():
            problems.append(f"{rel}: missing (listed in metadata.json)")
            continue
        safe.add(name)
        if sums is None or not check:
            continue
        if name not in sums:
            problems.append(f"{rel}: no checksum in the record of scene {s['index']}")
        elif formats.file_sha256(path) != sums[name]:
            problems.append(
                f"{rel}: SHA-256 differs from the record of scene {s['index']} "
                "(the file was changed, replaced or swapped)"
            )
    if sums is not None:
        for name in sorted(set(sums) - set(layout.scene_files(s))):
            problems.append(f"{where}: sha256 names '{name}', which is no file of the scene")
    if check:
        w, h = s["resolution"]
        for rgb, depth in zip(s["rgb"], s["depth_exr"], strict=True):
            if rgb in safe and depth in safe:
                problems += _check_frame(root, f"{chunk}/{rgb}", f"{chunk}/{depth}", w, h)
        for entry in s.get("flow", []):
            if all(entry[k] in safe for k in layout.FLOW_KEYS):
                problems += _check_flow(root, chunk, entry, w, h)
    return problems, sums is not None


def _unsafe_names(root: Path, chunk: str, meta) -> list[str]:
    """Names of a metadata.json that failed its schema, but as they would be read, that lead
    outside the dataset (said plainly, beside the schema's pattern message)."""
    problems = []
    scenes = meta.get("scenes") if isinstance(meta, dict) else None
    for s in scenes if isinstance(scenes, list) else []:
        if not isinstance(s, dict):
            continue
        where = f"{chunk}/metadata.json: scene {s.get('index')}"
        lists = [s.get(k) for k in ("imgs", "depth", "rgb", "depth_exr")]
        names = [n for v in lists if isinstance(v, list) for n in v]
        flows = s.get("flow") if isinstance(s.get("flow"), list) else []
        names += [e.get(k) for e in flows if isinstance(e, dict) for k in layout.FLOW_KEYS]
        for name in dict.fromkeys(n for n in names if isinstance(n, str)):
            try:
                formats.resolve_inside(root, name, where, folder=chunk)
            except formats.UnsafePathError as e:
                problems.append(str(e))
    return problems


def _stray_files(root: Path, chunk: str, named: set[str], locals_: set[int]) -> list[str]:
    """Files of a chunk folder that no record names (leftover temporary folders aside)."""
    problems = []
    folder = root / chunk
    for p in sorted(folder.iterdir()):
        if p.name in named or p.name in (layout.METADATA_JSON, layout.RECORDS_DIR):
            continue
        if p.name.startswith(".tmp-") and p.is_dir():
            continue  # reported as a leftover temporary folder
        kind = "folder" if p.is_dir() else "file"
        problems.append(f"{chunk}/{p.name}: stray {kind} (no scene record names it)")
    records = folder / layout.RECORDS_DIR
    if records.is_dir():
        expected = {f"{k:04d}.json" for k in locals_}
        for p in sorted(records.iterdir()):
            if p.name not in expected:
                problems.append(f"{chunk}/{layout.RECORDS_DIR}/{p.name}: stray file (no scene)")
    return problems


def validate_dataset(root: Path, check_pixels: bool = True) -> tuple[list[str], dict]:
    """Return (problems, stats). No problems means the dataset matches the documented format.

    ``check_pixels`` (off with ``validate --quick``) also reads every file: SHA-256 against the
    records, image sizes, depth values. ``stats["notes"]`` lists what could not be checked.
    """
    problems: list[str] = []
    stats: dict = {"scenes": 0, "frames": 0, "rows": 0, "notes": []}
    info_path = root / DATASET_JSON
    try:
        formats.resolve_inside(root, DATASET_JSON, DATASET_JSON)
        info = json.loads(info_path.read_text())
    except formats.UnsafePathError as e:
        return [str(e)], stats
    except (OSError, json.JSONDecodeError) as e:
        return [f"{info_path}: missing or not JSON ({e})"], stats
    problems += _schema_problems(info, schema.DATASET, DATASET_JSON)
    if problems:
        return problems, stats
    problems += _info_problems(info)
    if not isinstance(info["config"], dict):
        return problems, stats
    if problem := config.limit_problem("scenes", info["scenes"]):
        return [*problems, f"{DATASET_JSON}: scenes {problem}"], stats
    cfg = _config_of(info)
    if cfg is not None:
        problems += _derived_problems(info, cfg)
    n_scenes, n_frames = info["scenes"], info["frames_per_scene"]
    n_chunks = layout.chunk_count(n_scenes)
    expected_dirs = {str(c) for c in range(n_chunks)}
    root_files = {DATASET_JSON, MANIFEST, *layout.STATS_FILES, layout.LOCK_FILE}
    linked = set()  # entries that are links: named by lstat, never followed
    for p in sorted(root.iterdir()):
        if p.is_symlink():
            linked.add(p.name)
            suffix = "/" if p.name in expected_dirs else ""
            target = os.readlink(p)
            problems.append(
                f"{p.name}{suffix}: a symbolic link (to '{target}'); a dataset holds no links"
            )
        elif p.is_dir() and p.name not in expected_dirs:
            problems.append(
                f"{p.name}/: unexpected folder (loaders read every sub-folder as a chunk)"
            )
        elif not p.is_dir() and p.name not in root_files:
            problems.append(f"{p.name}: stray file at the dataset root (not part of the format)")

    records: list[dict] = []
    unchecked: list[int] = []  # scenes whose record holds no checksums (older datasets)
    for c in range(n_chunks):
        if str(c) in linked:
            continue
        try:
            meta_path = formats.resolve_inside(root, f"{c}/{layout.METADATA_JSON}", f"chunk {c}")
            meta = json.loads(meta_path.read_text())
        except formats.UnsafePathError as e:
            problems.append(str(e))
            continue
        except (OSError, json.JSONDecodeError) as e:
            problems.append(f"{c}/metadata.json: missing or not JSON ({e})")
            continue
        found = _schema_problems(meta, schema.METADATA, f"{c}/metadata.json")
        problems += found
        if found:
            problems += _unsafe_names(root, str(c), meta)
            continue
        if cfg is not None:
            problems += _args_problems(info, meta["args"], f"{c}/metadata.json")
        want = list(layout.chunk_scenes(c, n_scenes))
        got = [s["index"] for s in meta["scenes"]]
        if got != want:
            problems.append(f"{c}/metadata.json: scenes {got[:3]}... expected {want[:3]}...")
        for tmp in (root / str(c)).glob(".tmp-*"):
            problems.append(f"{c}/{tmp.name}: leftover temporary folder")
        named: set[str] = set()
        for s in meta["scenes"]:
            named.update(layout.scene_files(s))
            if s["length"] != n_frames or any(
                len(s[k]) != n_frames for k in ("imgs", "depth", "rgb", "depth_exr", "cam2world")
            ):
                problems.append(
                    f"{c}/metadata.json: scene {s['index']}: expected {n_frames} frames"
                )
                continue
            problems += _record_problems(root, s)
            if cfg is not None:
                problems += _scene_config_problems(s, cfg, f"{c}/metadata.json")
            found, has_sums = _file_problems(root, str(c), s, check_pixels)
            problems += found
            if not has_sums:
                unchecked.append(s["index"])
            records.append(s)
        problems += _stray_files(root, str(c), named, {s["scene_in_chunk"] for s in meta["scenes"]})
    stats["scenes"], stats["frames"] = len(records), len(records) * n_frames
    problems += _seed_problems(info["seed"], records)
    if len(records) == n_scenes and info["rejected_scenes"] != sum(r["rejected"] for r in records):
        problems.append(
            f"{DATASET_JSON}: rejected_scenes {info['rejected_scenes']!r} differs from the "
            f"records' sum ({sum(r['rejected'] for r in records)})"
        )
    if unchecked:
        stats["notes"].append(
            f"{len(unchecked)} of {len(records)} scenes (from {unchecked[0]}) have no checksums "
            "in their records (written before stillbox-gen recorded them): their files' contents "
            "cannot be checked"
        )
    if not check_pixels:
        stats["notes"].append("--quick: checksums and pixels not checked")

    man_path = root / MANIFEST
    try:
        formats.resolve_inside(root, MANIFEST, MANIFEST)
    except formats.UnsafePathError as e:
        problems.append(str(e))
        return problems, stats
    try:
        table = manifest.read_manifest(man_path)
    except Exception as e:  # noqa: BLE001
        problems.append(f"{MANIFEST}: missing or unreadable ({e})")
        return problems, stats
    stats["rows"] = table.num_rows
    if table.schema.remove_metadata() != manifest.MANIFEST_SCHEMA.remove_metadata():
        problems.append(f"{MANIFEST}: schema differs from the documented one")
        return problems, stats
    if table.num_rows != n_scenes * n_frames:
        problems.append(f"{MANIFEST}: {table.num_rows} rows, expected {n_scenes * n_frames}")
    seed, shares = info["seed"], tuple(info["config"]["split"])
    expected = [row for r in records for row in manifest.manifest_rows(r, seed, shares)]
    rows = table.to_pylist()
    if len(rows) == len(expected):
        for i, (a, b) in enumerate(zip(rows, expected, strict=True)):
            if a != b:
                keys = [k for k in a if a[k] != b[k]]
                problems.append(f"{MANIFEST}: row {i} disagrees with metadata.json on {keys}")
                break
    return problems, stats


def _seed_problems(seed: int, records: list[dict]) -> list[str]:
    """Scene k's seed is derived from (dataset seed, k): a mismatch in every scene means
    dataset.json's seed was edited, in some scenes that their records were."""
    try:
        bad = [(r, scene_seed(seed, r["index"])) for r in records]
    except (TypeError, ValueError):
        return [f"{DATASET_JSON}: seed {seed!r} is not a non-negative integer"]
    bad = [(r, want) for r, want in bad if r["seed"] != want]
    if bad and len(bad) == len(records):
        r, want = bad[0]
        return [
            f"{DATASET_JSON}: seed {seed} does not give the scenes' seeds (scene {r['index']}: "
            f"{r['seed']} in its record, {want} from seed {seed}): dataset.json was edited"
        ]
    return [
        f"{layout.chunk_name(r['index'])}/metadata.json: scene {r['index']}: seed {r['seed']} "
        f"is not the one derived from dataset seed {seed} ({want})"
        for r, want in bad
    ]
