"""manifest.parquet: one row per frame, with the deterministic train/val/test split by scene."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from . import formats, layout

SPLITS = ("train", "val", "test")


def _f(name: str, type_: pa.DataType, doc: str) -> pa.Field:
    return pa.field(name, type_, nullable=False, metadata={"doc": doc})


MANIFEST_SCHEMA = pa.schema(
    [
        _f("scene", pa.int64(), f"global scene index (chunk = scene // {layout.CHUNK_SIZE})"),
        _f("chunk", pa.string(), "chunk folder name"),
        _f("scene_in_chunk", pa.int32(), "scene index inside the chunk (in file names)"),
        _f("frame", pa.int32(), "frame index in the scene, from 0"),
        _f("split", pa.string(), "train | val | test, fixed per scene"),
        _f("rgb", pa.string(), "RGB frame path relative to the dataset root"),
        _f("depth", pa.string(), "depth EXR path relative to the dataset root"),
        _f("width", pa.int32(), "image width, pixels"),
        _f("height", pa.int32(), "image height, pixels"),
        _f("fx", pa.float64(), "focal length, pixels"),
        _f("fy", pa.float64(), "focal length, pixels"),
        _f("cx", pa.float64(), "principal point x, pixels, pixel-centre convention"),
        _f("cy", pa.float64(), "principal point y, pixels, pixel-centre convention"),
        _f("displacement", pa.float64(), "camera displacement between frames, metres"),
        _f("time_step", pa.float64(), "seconds between frames"),
        _f("speed", pa.list_(pa.float64(), 3), "m/s in the first frame's OpenCV camera axes"),
        _f("position", pa.list_(pa.float64(), 3), "camera centre, metres, first-frame axes"),
        _f(
            "orientation",
            pa.list_(pa.float64(), 4),
            "[w,x,y,z] of R_cam0<-cam_i (identity if none)",
        ),
        _f("cam2world", pa.list_(pa.float64(), 16), "OpenCV camera-to-world 4x4, row-major"),
        _f("scene_seed", pa.int64(), "per-scene seed"),
    ],
    metadata={"format": f"stillbox-gen manifest v{formats.FORMAT_VERSION}"},
)


def split_of(seed: int, index: int, shares: tuple[float, float, float]) -> str:
    """Split of a scene: depends only on (seed, index), so adding scenes never moves old ones."""
    u = np.random.default_rng(np.random.SeedSequence([seed, index, 0x5E1])).random()
    cumulative = np.cumsum(shares)
    return SPLITS[min(int(np.searchsorted(cumulative, u, side="right")), 2)]


def manifest_rows(record: dict, seed: int, shares: tuple[float, float, float]) -> list[dict]:
    index, chunk = record["index"], layout.chunk_name(record["index"])
    K = np.array(record["K"])
    split = split_of(seed, index, shares)
    speed, dt = record["speed"], record["time_step"]
    rows = []
    for f in range(record["length"]):
        q = record["orientation"][f] if record["orientation"] else [1.0, 0.0, 0.0, 0.0]
        rows.append(
            {
                "scene": index,
                "chunk": chunk,
                "scene_in_chunk": record["scene_in_chunk"],
                "frame": f,
                "split": split,
                "rgb": f"{chunk}/{record['rgb'][f]}",
                "depth": f"{chunk}/{record['depth_exr'][f]}",
                "width": record["resolution"][0],
                "height": record["resolution"][1],
                "fx": K[0, 0],
                "fy": K[1, 1],
                "cx": K[0, 2],
                "cy": K[1, 2],
                "displacement": record["displacement"],
                "time_step": dt,
                "speed": speed,
                "position": [f * s * dt for s in speed],
                "orientation": q,
                "cam2world": np.array(record["cam2world"][f]).reshape(-1).tolist(),
                "scene_seed": record["seed"],
            }
        )
    return rows


def write_manifest(path: Path, records: list[dict], seed: int, shares) -> pa.Table:
    """Write the manifest of ``records`` (scene order) via a temporary name of this process (two
    shards finishing together may index at once), then rename; returns the table."""
    rows = [row for r in records for row in manifest_rows(r, seed, shares)]
    table = pa.Table.from_pylist(rows, schema=MANIFEST_SCHEMA)
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    formats.atomic_write_bytes(path, sink.getvalue().to_pybytes())
    return table


def read_manifest(path: Path, columns: list[str] | None = None) -> pa.Table:
    """The manifest table (only ``columns`` when given)."""
    return pq.read_table(path, columns=columns)
