"""Check a dataset folder against docs/FORMAT.md; every problem names the file it concerns."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import jsonschema
import numpy as np

from . import formats, manifest, schema
from .generate import DATASET_JSON, MANIFEST


def _schema_problems(obj, sch: dict, where: str, limit: int = 5) -> list[str]:
    validator = jsonschema.Draft202012Validator(sch)
    errors = sorted(validator.iter_errors(obj), key=lambda e: list(e.absolute_path))
    out = []
    for e in errors[:limit]:
        path = "/".join(str(p) for p in e.absolute_path) or "(root)"
        out.append(f"{where}: {path}: {e.message}")
    return out


def _check_frame(root: Path, chunk: str, rgb: str, depth: str, w: int, h: int) -> list[str]:
    problems = []
    img = cv2.imread(str(root / chunk / rgb), cv2.IMREAD_UNCHANGED)
    if img is None:
        problems.append(f"{chunk}/{rgb}: missing or unreadable image")
    elif img.shape != (h, w, 3) or img.dtype != np.uint8:
        problems.append(f"{chunk}/{rgb}: expected {h}x{w}x3 uint8, got {img.shape} {img.dtype}")
    try:
        d = formats.read_depth_exr(root / chunk / depth)
    except Exception as e:  # noqa: BLE001 - any reader failure is a problem to report
        return [*problems, f"{chunk}/{depth}: unreadable depth EXR ({e})"]
    if d.shape != (h, w):
        problems.append(f"{chunk}/{depth}: expected {h}x{w}, got {d.shape}")
    elif not np.all(np.isfinite(d)) or not np.all(d > 0):
        bad = int(np.sum(~np.isfinite(d) | (d <= 0)))
        problems.append(f"{chunk}/{depth}: {bad} pixels not finite and positive")
    return problems


def validate_dataset(root: Path, check_pixels: bool = True) -> tuple[list[str], dict]:
    """Return (problems, stats). No problems means the dataset matches the documented format."""
    problems: list[str] = []
    stats = {"scenes": 0, "frames": 0, "rows": 0}
    info_path = root / DATASET_JSON
    try:
        info = json.loads(info_path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        return [f"{info_path}: missing or not JSON ({e})"], stats
    problems += _schema_problems(info, schema.DATASET, DATASET_JSON)
    if problems:
        return problems, stats
    n_scenes, n_frames = info["scenes"], info["frames_per_scene"]
    n_chunks = -(-n_scenes // formats.CHUNK_SIZE)
    expected_dirs = {str(c) for c in range(n_chunks)}
    dirs = {p.name for p in root.iterdir() if p.is_dir()}
    for extra in sorted(dirs - expected_dirs):
        problems.append(f"{extra}/: unexpected folder (loaders read every sub-folder as a chunk)")

    records: list[dict] = []
    for c in range(n_chunks):
        meta_path = root / str(c) / "metadata.json"
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            problems.append(f"{c}/metadata.json: missing or not JSON ({e})")
            continue
        found = _schema_problems(meta, schema.METADATA, f"{c}/metadata.json")
        problems += found
        if found:
            continue
        want = list(range(c * formats.CHUNK_SIZE, min(n_scenes, (c + 1) * formats.CHUNK_SIZE)))
        got = [s["index"] for s in meta["scenes"]]
        if got != want:
            problems.append(f"{c}/metadata.json: scenes {got[:3]}... expected {want[:3]}...")
        for tmp in (root / str(c)).glob(".tmp-*"):
            problems.append(f"{c}/{tmp.name}: leftover temporary folder")
        for s in meta["scenes"]:
            w, h = s["resolution"]
            if s["length"] != n_frames or any(
                len(s[k]) != n_frames for k in ("imgs", "depth", "rgb", "depth_exr", "cam2world")
            ):
                problems.append(
                    f"{c}/metadata.json: scene {s['index']}: expected {n_frames} frames"
                )
                continue
            for name in s["imgs"] + s["depth"]:
                if not (root / str(c) / name).is_file():
                    problems.append(f"{c}/{name}: missing (listed in metadata.json)")
            if check_pixels:
                for rgb, depth in zip(s["rgb"], s["depth_exr"], strict=True):
                    problems += _check_frame(root, str(c), rgb, depth, w, h)
            records.append(s)
    stats["scenes"], stats["frames"] = len(records), len(records) * n_frames

    man_path = root / MANIFEST
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
