"""Where each file of a stillbox-gen dataset lives (docs/FORMAT.md); what a scene's record holds
is stillbox_gen.record. Pure functions: nothing here reads or writes a file.

::

    DIR/
      dataset.json          DATASET_JSON: generator, parameters, counts; "complete" when done
      manifest.parquet      MANIFEST: one row per frame
      .stillbox.lock        LOCK_FILE: held by the run writing (stillbox_gen.lock), then deleted
      <chunk>/              chunk_name(k): scene k lives in chunk k // CHUNK_SIZE
        metadata.json       METADATA_JSON: {"args": {...}, "scenes": [record, ...]}
        RGB_<s>_<f>.png     rgb_name(s, f): frame f of scene s = local_index(k)
        depth_<s>_<f>.exr   depth_name(s, f)
        flow_<s>_<a>_<b>.flo      flow_name(s, a, b): optical flow from frame a to b (--flow;
                                  .png with --flow-format kitti-png)
        valid_<s>_<a>_<b>.png     flow_valid_name(s, a, b): where that flow lands in frame b
        occluded_<s>_<a>_<b>.png  flow_occluded_name(s, a, b): where it is hidden in frame b
        .records/<s>.json   record_name(k): the scene's record, written last (complete mark)
        .tmp-<s>/           scene_tmp_name(k): a scene being rendered
"""

from __future__ import annotations

from pathlib import Path

from .conventions import NOMINAL_SHIFT

CHUNK_SIZE = 200  # scenes per chunk folder (the original StillBox layout)
DATASET_JSON = "dataset.json"
MANIFEST = "manifest.parquet"
METADATA_JSON = "metadata.json"
RECORDS_DIR = ".records"
STATS_FILES = ("stats.json", "stats.png")  # what ``stillbox-gen stats`` may add to the root
# the lock of a run writing into the folder (stillbox_gen.lock); left behind only by a killed run
LOCK_FILE = ".stillbox.lock"


def enclosing_dataset(path: Path) -> Path | None:
    """The dataset folder (one holding DATASET_JSON) that ``path`` is or lies inside, after
    resolving links; None when there is none. Commands refuse to write there."""
    for folder in (path.resolve(), *path.resolve().parents):
        if (folder / DATASET_JSON).is_file():
            return folder
    return None


def chunk_name(index: int) -> str:
    """Folder name of the chunk holding scene ``index`` (global index, from 0)."""
    return str(index // CHUNK_SIZE)


def local_index(index: int) -> int:
    """Index of scene ``index`` inside its chunk (the ``<s>`` of its file names)."""
    return index % CHUNK_SIZE


def chunk_count(scenes: int) -> int:
    """Number of chunk folders of a dataset of ``scenes`` scenes."""
    return -(-scenes // CHUNK_SIZE)


def chunk_scenes(chunk: int, scenes: int) -> range:
    """Global indices of the scenes of chunk number ``chunk`` in a dataset of ``scenes`` scenes."""
    return range(chunk * CHUNK_SIZE, min(scenes, (chunk + 1) * CHUNK_SIZE))


def rgb_name(local: int, frame: int, ext: str = "png") -> str:
    """``RGB_<s>_<f>.<ext>``: frame ``frame`` of the scene with local index ``local``."""
    return f"RGB_{local:04d}_{frame:02d}.{ext}"


def depth_name(local: int, frame: int, ext: str = "exr") -> str:
    """``depth_<s>_<f>.<ext>``: the depth of that frame (``npy`` for --legacy copies)."""
    return f"depth_{local:04d}_{frame:02d}.{ext}"


#: --flow-format (config key render.flow_format): the flow file's format and its extension.
#: "flo": Middlebury .flo, float32; "kitti-png": KITTI's 16-bit PNG (u, v, valid), 1/64 px.
FLOW_EXTENSIONS = {"flo": "flo", "kitti-png": "png"}
FLOW_FORMATS = tuple(FLOW_EXTENSIONS)


def flow_name(local: int, a: int, b: int, flow_format: str = "flo") -> str:
    """``flow_<s>_<a>_<b>.flo`` (``.png`` for "kitti-png"): optical flow from frame ``a`` to
    frame ``b`` on ``a``'s grid."""
    return f"flow_{local:04d}_{a:02d}_{b:02d}.{FLOW_EXTENSIONS[flow_format]}"


def flow_valid_name(local: int, a: int, b: int) -> str:
    """``valid_<s>_<a>_<b>.png``: where the flow of :func:`flow_name` is valid."""
    return f"valid_{local:04d}_{a:02d}_{b:02d}.png"


def flow_occluded_name(local: int, a: int, b: int) -> str:
    """``occluded_<s>_<a>_<b>.png``: where the point of frame ``a`` is hidden in frame ``b``."""
    return f"occluded_{local:04d}_{a:02d}_{b:02d}.png"


#: Frame shifts s of the pairs written by --flow: (t, t + s) and (t + s, t) for every t; 1 is
#: the consecutive pair, NOMINAL_SHIFT the benchmark's pair (i, i + 3).
FLOW_SHIFTS = (1, NOMINAL_SHIFT)


def flow_pairs(frames: int, shifts: tuple[int, ...] = FLOW_SHIFTS) -> list[tuple[int, int]]:
    """Frame pairs ``(a, b)`` of a scene of ``frames`` frames that --flow writes: for each shift
    s < frames and each t, ``(t, t + s)`` then ``(t + s, t)``; ordered by shift, then t."""
    return [
        pair
        for s in dict.fromkeys(shifts)
        if 0 < s < frames
        for t in range(frames - s)
        for pair in ((t, t + s), (t + s, t))
    ]


def flow_entries(local: int, frames: int, flow_format: str = "flo") -> list[dict]:
    """The ``flow`` list of a scene record (docs/FORMAT.md): one entry per pair of
    :func:`flow_pairs`, ``{"from": a, "to": b, "flow": name, "valid": name, "occluded": name}``,
    the flow file in ``flow_format`` (FLOW_FORMATS)."""
    return [
        {
            "from": a,
            "to": b,
            "flow": flow_name(local, a, b, flow_format),
            "valid": flow_valid_name(local, a, b),
            "occluded": flow_occluded_name(local, a, b),
        }
        for a, b in flow_pairs(frames)
    ]


#: the file keys of an entry of a record's ``flow`` list (:func:`flow_entries`)
FLOW_KEYS = ("flow", "valid", "occluded")


def flow_files(record: dict) -> list[str]:
    """The flow, validity and occlusion files of a scene's record (none without --flow)."""
    return [p[k] for p in record.get("flow", []) for k in FLOW_KEYS]


def record_name(index: int) -> str:
    """``<chunk>/.records/<s>.json``, relative to the dataset root."""
    return f"{chunk_name(index)}/{RECORDS_DIR}/{local_index(index):04d}.json"


def record_path(root: Path, index: int) -> Path:
    """The record file of scene ``index`` under ``root`` (its presence: the scene is complete)."""
    return Path(root) / record_name(index)


def scene_tmp_name(index: int) -> str:
    """``<chunk>/.tmp-<s>``: the folder a scene is rendered into before it is committed."""
    return f"{chunk_name(index)}/.tmp-{local_index(index):04d}"


def scene_files(record: dict) -> list[str]:
    """Every file name of a scene in its chunk folder (frames, depth, legacy copies, flow),
    sorted."""
    names = [*record["rgb"], *record["depth_exr"], *record["imgs"], *record["depth"]]
    names += flow_files(record)
    return sorted(set(names))
