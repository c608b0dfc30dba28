"""Item 5 of ``stillbox-gen stats``, the same-pose flicker: scenes' poses re-rendered by
Blender (in a spawned worker process) with the dataset's own render settings, against the stored
frames."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .. import formats, layout
from ..dataset import Dataset, Scene
from ..errors import ConfigError, DatasetError
from ..record import spec_from_record
from ..scene import foreign_photos
from .common import PARTS, bgr, mean_or_none, open_dataset, parts
from .geometry import box_depth, wall_mask

if TYPE_CHECKING:
    from ..config import DatasetConfig, MaterialsConfig


def config_of(ds: Dataset) -> DatasetConfig:
    """The DatasetConfig of dataset.json (DatasetError naming it when it is not readable)."""
    from ..config import from_dict

    try:
        return from_dict(ds.info["config"])
    except Exception as e:  # noqa: BLE001 - any malformed config is the dataset's
        raise DatasetError(f"'{ds.root / 'dataset.json'}': config is not readable ({e})") from None


def check_photos(materials: MaterialsConfig, scenes: list, root: Path) -> None:
    """Every photo a scene names is one of the dataset's ``materials`` (config.MaterialsConfig:
    a plain name, opened inside its textures_dir or the bundled folder); DatasetError naming
    the record otherwise."""
    for scene in scenes:
        found = foreign_photos(scene.record, materials)
        if found:
            raise DatasetError(
                f"{root / layout.chunk_name(scene.index) / 'metadata.json'}: scene "
                f"{scene.index}: photo {found[0]!r} is not one of the dataset's photos "
                "(config.materials)"
            )


def _rerender(pool, spec: dict, out: Path, image_format: str) -> tuple[np.ndarray, np.ndarray]:
    """Render ``spec`` in ``pool`` into ``out``; its last frame (BGR, float32) and depth (m)."""
    from ..workers import render_scene

    pool.submit(render_scene, spec, str(out), image_format, False).result()
    local, last = layout.local_index(spec["index"]), len(spec["camera"]["cam2world"]) - 1
    img = bgr(formats.read_rgb(out / layout.rgb_name(local, last, image_format)))
    return img.astype(np.float32), formats.read_depth_exr(out / layout.depth_name(local, last))


def flicker_scene(pool, scene: Scene, tmp: Path, image_format: str, sums: dict, bar) -> float:
    """Re-render the pose of frame 0 of ``scene`` as frame 1 of its scene (same_pose) and with
    seed + 1 (other_seed), adding each one's absolute differences to the stored frame to
    ``sums`` (per kind and part: [sum, pixels]); returns the largest depth difference (m)."""
    rec = scene.record
    stored = bgr(scene.load_rgb(0)).astype(np.float32)
    depth = scene.load_depth(0).astype(np.float64)
    (w, h), box = rec["resolution"], rec["box"]
    box_d = box_depth(scene.K, scene.cam2world[0], box["center"], box["half_extents"], w, h)
    wall = wall_mask(depth, box_d)
    depth_diff = 0.0
    runs = (("same_pose", rec["seed"], [0, 0]), ("other_seed", rec["seed"] + 1, [0]))
    for key, seed, frames in runs:
        spec = {**spec_from_record(rec, frames=frames), "seed": seed}
        img, new_depth = _rerender(pool, spec, tmp / f"{rec['index']}-{key}", image_format)
        diff = np.abs(img - stored).mean(axis=-1)
        for p, m in parts(wall):
            sums[key][p][0] += float(diff[m].sum(dtype=np.float64))
            sums[key][p][1] += int(m.sum())
        depth_diff = max(depth_diff, float(np.abs(new_depth - depth).max()))
        bar.update(1)
    return depth_diff


def flicker_stats(
    root: Path | Dataset, count: int, progress: bool = False, threads: int = 0
) -> dict:
    """Re-render the pose of frame 0 of the first ``count`` scenes with the dataset's render
    settings: as frame 1 of its scene ("same_pose": what the generator gives when two frames
    share a pose, whatever its per-frame seeding), and as frame 0 with scene seed + 1
    ("other_seed": how much the sample placement alone moves pixels). Mean absolute difference
    against the stored frame, grey levels (0-255, mean over the 3 channels), on walls and on
    objects; also the largest depth difference (metres), a check of the pose."""
    from tqdm import tqdm

    from ..worker_setup import worker_setup
    from ..workers import process_pool

    ds = open_dataset(root)
    available = ds.indices()
    if not 1 <= count <= len(available):
        raise ConfigError(f"--flicker: must be between 0 and {len(available)} scenes, got {count}")
    scenes = ds.scenes(limit=count)
    cfg = config_of(ds)
    check_photos(cfg.materials, scenes, ds.root)
    sums = {k: {p: [0.0, 0] for p in PARTS} for k in ("same_pose", "other_seed")}
    depth_diff = 0.0
    with (
        tempfile.TemporaryDirectory(prefix="stillbox-stats-") as tmp,
        process_pool(1, worker_setup(cfg, threads)) as pool,
        tqdm(
            total=2 * count, desc="flicker", unit="render", disable=not progress, dynamic_ncols=True
        ) as bar,
    ):
        for scene in scenes:
            diff = flicker_scene(pool, scene, Path(tmp), cfg.render.image_format, sums, bar)
            depth_diff = max(depth_diff, diff)
    return {
        "units": "grey levels (0-255), mean absolute difference over the 3 channels",
        "frames": [[scene.record["index"], 0] for scene in scenes],
        **{k: {p: mean_or_none(*sums[k][p]) for p in PARTS} for k in sums},
        "depth_max_abs_diff_m": depth_diff,
        "rule": (
            "the pose of frame 0 of the first scenes re-rendered with the dataset's render "
            "settings (dataset.json config.render): same_pose as frame 1 of its scene (same-pose "
            "flicker), other_seed as frame 0 with scene seed + 1; against the stored frame 0"
        ),
    }
