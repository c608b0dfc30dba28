"""``stillbox-gen merge OUT SRC...``: join datasets rendered by ``--shard I/N`` into separate
folders (one per job, e.g. on machines without a shared file system) into one indexed dataset.

Every source must hold the same parameters (same ``fingerprint`` and ``scenes``). Each complete
scene of each source (its ``.records`` file exists) is linked, or copied across file systems, into
OUT under a temporary name and renamed; its record is written last, as in a generation run, so an
interrupted merge resumes. OUT is then indexed: the result equals a single run with the same seed.
Records are copied as they are, with their checksums. A file name in a record that would lead
outside its source or OUT (absolute, ``..``, a symlink) stops the merge before anything of that
scene is written.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from . import config, formats, layout
from .dataset import Dataset
from .errors import ConfigError, DatasetError
from .lock import folder_lock
from .writer import (
    Totals,
    index_dataset,
    join_devices,
    pending_indices,
    prepare_output,
)


def _info(folder: Path) -> dict:
    """dataset.json of a source (ConfigError naming SOURCES when it has none)."""
    try:
        return Dataset(folder).info
    except DatasetError as e:
        raise ConfigError(f"SOURCES: {e}") from None


def _place(src: Path, dst: Path) -> None:
    """Hard-link (same file system) or copy ``src`` to a temporary name, then rename to ``dst``."""
    tmp = formats.temp_path(dst)
    tmp.unlink(missing_ok=True)
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def _plan(out: Path, sources: list[Path], scenes: int) -> list[tuple[int, Path, Path, list]]:
    """(scene, source, its record, its file names) of every scene OUT lacks, from the first
    source holding it; every record read and every name checked to stay inside its source.
    ConfigError naming SOURCES when a record is unreadable or no source holds some scenes."""
    plan, missing = [], []
    for k in pending_indices(out, scenes):
        src = next((s for s in sources if layout.record_path(s, k).is_file()), None)
        if src is None:
            missing.append(k)
            continue
        where = f"SOURCES: scene {k} in '{src}'"
        rec_src = formats.resolve_inside(src, layout.record_name(k), where)
        try:
            names = layout.scene_files(json.loads(rec_src.read_text()))
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
            raise ConfigError(f"{where} is unreadable ({e})") from None
        where = f"SOURCES: {rec_src}: scene {k}"
        for name in names:
            formats.resolve_inside(src, name, where, folder=layout.chunk_name(k))
        plan.append((k, src, rec_src, names))
    if missing:
        shown = ", ".join(map(str, missing[:10])) + (" ..." if len(missing) > 10 else "")
        raise ConfigError(
            f"SOURCES: the merge lacks {len(missing)} of {scenes} scenes ({shown}), which no "
            "folder holds; run the missing shards first"
        )
    return plan


def merge_datasets(out: Path, sources: list[Path]) -> tuple[int, Totals]:
    """Copy the complete scenes of ``sources`` into ``out`` and index it.

    Returns (scenes copied now, what the indexed dataset holds). Raises ConfigError (naming the
    folder) when the sources disagree, OUT holds another dataset, or scenes are missing from
    every source, FolderInUse when another run writes into ``out`` (stillbox_gen.lock).
    """
    if not sources:
        raise ConfigError("SOURCES: give at least one dataset folder to merge")
    with folder_lock(out, "OUT"):  # refused while another run writes into OUT
        return _merge(out, sources)


def _merge(out: Path, sources: list[Path]) -> tuple[int, Totals]:
    """:func:`merge_datasets` once OUT's lock is held."""
    infos = [_info(s) for s in sources]
    first = infos[0]
    for src, info in zip(sources, infos, strict=True):
        if info.get("fingerprint") != first.get("fingerprint"):
            raise ConfigError(
                f"SOURCES: '{src}' was made with other parameters than '{sources[0]}' "
                f"(seed {info.get('seed')} vs {first.get('seed')}, preset {info.get('preset')!r})"
            )
        if info.get("scenes") != first.get("scenes"):
            raise ConfigError(
                f"SOURCES: '{src}' has --scenes {info.get('scenes')}, "
                f"'{sources[0]}' has {first.get('scenes')}"
            )
    plan = _plan(out, sources, first["scenes"])  # every refusal before OUT is created
    # the same checks of OUT, and the same "incomplete" mark, as a generation run
    devices = join_devices(*(info.get("render", {}).get("device") for info in infos))
    prepare_output(out, config.from_dict(first["config"]), first["scenes"], devices)

    for k, src, rec_src, names in plan:
        chunk = layout.chunk_name(k)
        where = f"SOURCES: scene {k} in '{src}'"
        rec_dst = formats.resolve_inside(out, layout.record_name(k), where)
        where = f"SOURCES: {rec_src}: scene {k}"
        pairs = [
            (
                formats.resolve_inside(src, name, where, folder=chunk),
                formats.resolve_inside(out, name, where, folder=chunk),
            )
            for name in names
        ]
        try:
            (out / chunk).mkdir(exist_ok=True)
            for a, b in pairs:
                _place(a, b)
            rec_dst.parent.mkdir(exist_ok=True)
            _place(rec_src, rec_dst)
        except OSError as e:
            raise ConfigError(f"SOURCES: scene {k} in '{src}' is unreadable ({e})") from None
    return len(plan), index_dataset(out, {"merged_from": [str(s) for s in sources]})
