"""``stillbox-gen stats`` without the printing: check the flags, measure, write stats.json and
stats.png."""

from __future__ import annotations

import os
from pathlib import Path

from .. import formats
from ..arguments import check_out_folder
from ..conventions import MAX_DEPTH, NOMINAL_SHIFT
from ..dataset import Dataset
from ..errors import ConfigError
from ..lock import folder_lock
from ..worker_setup import require_blender
from .flicker import check_photos, config_of, flicker_stats
from .measure import check_numbers, dataset_stats
from .report import plot


def _check_out_folder(out: Path) -> None:
    """--out can be written: a folder, or a path whose nearest existing ancestor is a writable
    folder (created by its lock, before the measurements). ConfigError naming --out otherwise."""
    check_out_folder(out, inside_dataset=True)  # stats.json and stats.png may sit at its root
    existing = next(p for p in (out, *out.absolute().parents) if p.exists())
    check_out_folder(existing, inside_dataset=True)
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(f"--out: cannot create '{out}' ('{existing}' is not writable)")


def run(
    root: Path,
    scenes: int = 200,
    shift: int = NOMINAL_SHIFT,
    flicker: int = 0,
    out: Path | None = None,
    max_depth: float = MAX_DEPTH,
    progress: bool = True,
) -> dict:
    """Everything ``stillbox-gen stats`` does but printing: measure, then write stats.json and
    stats.png into ``out`` (default ``root``). Returns the stats dict."""
    ds = Dataset(root)
    info, available = ds.info, ds.indices()
    check_numbers(scenes, shift, int(info.get("frames_per_scene", 0)), max_depth, flicker)
    if flicker > min(scenes, len(available)):
        raise ConfigError(
            f"--flicker: at most the {min(scenes, len(available))} scenes used, got {flicker}"
        )
    out = Path(out) if out is not None else ds.root
    _check_out_folder(out)
    if flicker:
        # before measuring: they are re-rendered
        require_blender()
        check_photos(config_of(ds).materials, ds.scenes(limit=flicker), ds.root)
    # a second run writing into --out (or generate into the dataset, the default --out) is
    # refused; --out is made by the lock and removed again if a refusal leaves it empty
    with folder_lock(out, "--out"):
        stats = dataset_stats(ds, scenes, shift, max_depth, progress)
        stats["flicker"] = flicker_stats(ds, flicker, progress) if flicker else None
        formats.atomic_write_json(out / "stats.json", stats, indent=2)
        plot(stats, out / "stats.png")
    return stats
