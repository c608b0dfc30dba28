"""``stillbox-gen stats DIR``: data-quality figures of a generated dataset beside StillBox's.

Over the first N scenes it measures:

1. the pixel-depth distribution (planar depth as stored, metres; every frame of every scene):
   shares in fixed bands, median, share below 25 m and between 5 and 25 m;
2. wall and object pixels: a pixel is *wall* when its depth equals, within
   ``WALL_RTOL`` relative + ``WALL_ATOL`` metres, the planar depth at which its ray leaves the
   scene's axis-aligned box of walls (the camera is inside it); every other pixel is *object*;
3. the true optical flow at the nominal shift S: frame i's pixels moved into frame j = i + S by
   back-projecting depth_i, applying ``inv(cam2world_j) @ cam2world_i`` and projecting with K
   (pixels; median and 10/90 percentiles of its magnitude on walls and on objects);
4. the photometric residual (grey levels on 0-255, mean absolute difference over the three
   channels): ``|I_j - I_i|`` without warp, and after warping I_j back to frame i with the true
   flow (bilinear), on pixels that stay in frame j and are not occluded there;
5. optionally (``--flicker K``), the same-pose flicker: the pose of frame 0 of the first K scenes
   re-rendered by Blender with the dataset's own render settings as another frame of its scene,
   against the stored frame; and as frame 0 with another scene seed (sample placement only).

Averaging rule: pixels are pooled over all frames (depth, walls/objects) or all pairs
(i, i + S), i = 0 .. frames - 1 - S (flow, residuals) of the chosen scenes, every pixel weighing
the same. Medians and percentiles come from fine histograms (depth: 1 cm bins up to 250 m;
flow: log-spaced bins 0.46 % wide from 1e-3 to 1e3 px), linearly interpolated inside the bin.

This module never imports ``bpy``; ``--flicker`` renders through the generator's worker entry
points in a spawned process.
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import numpy as np

from . import formats, layout
from .conventions import MAX_DEPTH, NOMINAL_SHIFT
from .dataset import Dataset
from .errors import ConfigError, DatasetError
from .record import spec_from_record
from .scene import foreign_photos

#: Pixel-depth bands in metres: [0, 5), [5, 10), ..., [75, 100), then [100, inf) ("> 100", which
#: also holds pixels whose ray met no surface, stored as formats.NO_SURFACE_DEPTH).
BAND_EDGES_M = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 50.0, 75.0, 100.0)
BAND_LABELS = tuple(
    [f"{lo:g}-{hi:g}" for lo, hi in zip(BAND_EDGES_M[:-1], BAND_EDGES_M[1:], strict=True)]
    + [f">{BAND_EDGES_M[-1]:g}"]
)

#: StillBox's figures, decoded from the sample frames of the GIF in the README of the original
#: DepthNet repository (5 scenes, 47 frames, 256 px) through its rainbow colour map over
#: 0-100 m. Shares of pixels; "share_5_25m" is the sum of the 5-25 m bands.
STILLBOX_REFERENCE: dict = {
    "source": "sample GIF of the original DepthNet repository's README (5 scenes, 47 frames, "
    "256 px), decoded through its rainbow colour map over 0-100 m",
    "median_depth_m": 19.2,
    "share_below_25m": 0.58,
    "share_5_25m": 0.43,
    "band_shares": dict(
        zip(BAND_LABELS, (0.15, 0.24, 0.03, 0.09, 0.07, 0.03, 0.12, 0.25, 0.02, 0.00), strict=True)
    ),
}

WALL_RTOL = 1e-3  # wall test: |depth - box depth| <= WALL_RTOL * box depth + WALL_ATOL
WALL_ATOL = 1e-3  # metres
OCCLUSION_RTOL = 0.02  # visible in frame j: |depth_j(p') - z_j| <= OCCLUSION_RTOL * z_j

DEPTH_BIN_M = 0.01  # fine depth histogram: 1 cm bins from 0 to DEPTH_HIST_TOP_M, then overflow
DEPTH_HIST_TOP_M = 250.0
FLOW_LOG_RANGE = (-3.0, 3.0)  # fine flow histogram: log10 px bounds, FLOW_BINS log bins between
FLOW_BINS = 3000  # (plus [0, 1e-3) below and [1e3, inf) above)
PLOT_FLOW_BINS = 60  # coarse log bins of the flow histogram in stats.png / stats.json
PLOT_DEPTH_BINS = 100  # bins of the 0..--max-depth depth histogram in stats.png / stats.json
PARTS = ("walls", "objects")


# ---------------------------------------------------------------- histograms


class Histogram:
    """Counts of values in fixed bins ``edges[b] <= x < edges[b + 1]``, the last bin open."""

    def __init__(self, edges: np.ndarray) -> None:
        self.edges = np.asarray(edges, dtype=np.float64)  # last bin: [edges[-1], inf)
        self.counts = np.zeros(len(self.edges), dtype=np.int64)

    def add(self, values: np.ndarray) -> None:
        """Count finite or infinite values (NaN is ignored); values below edges[0] go in bin 0."""
        v = np.asarray(values, dtype=np.float64).ravel()
        v = v[~np.isnan(v)]
        b = np.clip(np.searchsorted(self.edges, v, side="right") - 1, 0, len(self.edges) - 1)
        self.counts += np.bincount(b, minlength=len(self.edges))

    @property
    def total(self) -> int:
        return int(self.counts.sum())

    def quantile(self, q: float) -> float | None:
        """Value below which a share ``q`` of the counts lies, interpolated linearly inside its
        bin; None when empty or when it falls in the open last bin."""
        n = self.total
        if n == 0:
            return None
        cum = np.cumsum(self.counts)
        target = q * n
        b = int(np.searchsorted(cum, target, side="left"))
        b = min(b, len(self.counts) - 1)
        if b == len(self.edges) - 1:
            return None
        before = cum[b] - self.counts[b]
        frac = (target - before) / self.counts[b] if self.counts[b] else 0.0
        lo, hi = self.edges[b], self.edges[b + 1]
        return float(lo + frac * (hi - lo))


def depth_histogram() -> Histogram:
    """Fine depth histogram: 1 cm bins from 0 to 250 m, then [250 m, inf)."""
    n = int(round(DEPTH_HIST_TOP_M / DEPTH_BIN_M))
    return Histogram(np.arange(n + 1) * DEPTH_BIN_M)


def flow_histogram() -> Histogram:
    """Fine flow-magnitude histogram (pixels): [0, 1e-3), log bins up to 1e3, [1e3, inf)."""
    return Histogram(np.concatenate([[0.0], np.logspace(*FLOW_LOG_RANGE, FLOW_BINS + 1)]))


# ---------------------------------------------------------------- geometry


def band_shares(depths: np.ndarray) -> dict[str, float]:
    """Share of the pixels of ``depths`` (metres, any shape) in each band of BAND_EDGES_M.

    Bands are half-open, [lo, hi); the last, ``">100"``, is [100 m, inf) and also holds misses
    (formats.NO_SURFACE_DEPTH) and infinities. NaN pixels are ignored. Shares sum to 1 (all 0
    for an empty array).
    """
    counts = band_counts(depths)
    n = counts.sum()
    return {k: float(c / n) if n else 0.0 for k, c in zip(BAND_LABELS, counts, strict=True)}


def band_counts(depths: np.ndarray) -> np.ndarray:
    """Pixel counts per band of BAND_EDGES_M (see :func:`band_shares`)."""
    d = np.asarray(depths, dtype=np.float64).ravel()
    d = d[~np.isnan(d)]
    b = np.clip(np.searchsorted(BAND_EDGES_M, d, side="right") - 1, 0, len(BAND_EDGES_M) - 1)
    return np.bincount(b, minlength=len(BAND_EDGES_M)).astype(np.int64)


def pixel_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Camera-frame ray directions (H, W, 3) ``K^-1 [u, v, 1]`` of the pixel centres (z = 1)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)
    return pix @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T


def box_depth(
    K: np.ndarray,
    cam2world: np.ndarray,
    center: np.ndarray,
    half_extents: np.ndarray,
    width: int,
    height: int,
) -> np.ndarray:
    """Planar depth (H, W), metres, at which each pixel's ray leaves an axis-aligned box.

    ``cam2world`` is the OpenCV camera-to-world 4x4 pose, ``center`` and ``half_extents`` the
    box in world metres. The camera is assumed inside the box, so the ray's exit distance is
    ``t = min over axes of (face - origin) / direction``; with the direction ``K^-1 [u, v, 1]``
    (z = 1 in camera axes), t is also the planar depth.
    """
    m = np.asarray(cam2world, dtype=np.float64)
    c, h = np.asarray(center, dtype=np.float64), np.asarray(half_extents, dtype=np.float64)
    d = pixel_rays(K, width, height) @ m[:3, :3].T  # world directions, (H, W, 3)
    o = m[:3, 3]
    face = np.where(d > 0, c + h, c - h)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d != 0, (face - o) / d, np.inf)
    return t.min(axis=-1)


def wall_mask(depth: np.ndarray, wall_depth: np.ndarray) -> np.ndarray:
    """Boolean (H, W): pixels whose depth (metres) is the box's, within WALL_RTOL + WALL_ATOL."""
    return np.abs(depth - wall_depth) <= WALL_RTOL * np.abs(wall_depth) + WALL_ATOL


def true_flow(
    depth_i: np.ndarray, K: np.ndarray, cam2world_i: np.ndarray, cam2world_j: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Where frame i's pixels land in frame j: (flow (H, W, 2) in pixels, z_j (H, W) in metres).

    Each pixel is back-projected with its planar depth (metres), moved into frame j's camera by
    ``inv(cam2world_j) @ cam2world_i`` and projected with K; ``flow[..., 0]`` is horizontal (x),
    ``flow[..., 1]`` vertical (y), and ``z_j`` the point's planar depth in frame j. Pixels whose
    point is not in front of camera j (z_j <= 0) get NaN flow.
    """
    K = np.asarray(K, dtype=np.float64)
    h, w = depth_i.shape
    pts = pixel_rays(K, w, h) * depth_i.astype(np.float64)[..., None]  # camera i, metres
    rel = np.linalg.inv(np.asarray(cam2world_j, dtype=np.float64)) @ np.asarray(
        cam2world_i, dtype=np.float64
    )
    pj = pts @ rel[:3, :3].T + rel[:3, 3]
    z = pj[..., 2]
    proj = pj @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = proj[..., :2] / proj[..., 2:3]
    xy[z <= 0] = np.nan
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    return xy - np.stack([u, v], axis=-1), z


def warp_residuals(
    img_i: np.ndarray,
    img_j: np.ndarray,
    depth_j: np.ndarray,
    flow: np.ndarray,
    z_j: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel photometric residuals of a pair, in grey levels (0-255), on frame i's grid.

    Returns ``(unwarped, warped, valid)``: ``|I_j - I_i|`` and ``|I_j(p + flow) - I_i(p)|``
    (I_j sampled bilinearly), each averaged over the channels, and the boolean mask where the
    warped value is meaningful: the point is in front of camera j, lands inside frame j
    (0 <= x <= W - 1, 0 <= y <= H - 1) and is not occluded there (depth_j, bilinearly
    sampled, within OCCLUSION_RTOL of z_j).
    """
    import cv2

    a = img_i.astype(np.float32)
    b = img_j.astype(np.float32)
    unwarped = np.abs(b - a).reshape(*a.shape[:2], -1).mean(axis=-1)
    h, w = depth_j.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    x, y = u + flow[..., 0], v + flow[..., 1]
    valid = np.isfinite(x) & np.isfinite(y) & (z_j > 0)
    valid &= (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    mx = np.where(valid, x, -1).astype(np.float32)
    my = np.where(valid, y, -1).astype(np.float32)
    sampled = cv2.remap(b, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    dj = cv2.remap(
        depth_j.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    valid &= np.abs(dj - z_j) <= OCCLUSION_RTOL * np.abs(z_j)
    warped = np.abs(sampled - a).reshape(*a.shape[:2], -1).mean(axis=-1)
    return unwarped, warped, valid


# ---------------------------------------------------------------- dataset access


def _open(root: Path | Dataset) -> Dataset:
    """The dataset at ``root`` (a Dataset is used as it is, so its files are read once)."""
    return root if isinstance(root, Dataset) else Dataset(root)


def _bgr(rgb: np.ndarray) -> np.ndarray:
    """A frame in BGR order: the figures sum channels in that order (another order could move
    the last digits of float sums)."""
    return rgb[..., ::-1]


def _check_numbers(scenes: int, shift: int, frames: int, max_depth: float, flicker: int) -> None:
    if scenes < 1:
        raise ConfigError(f"--scenes: must be at least 1, got {scenes}")
    if not 1 <= shift <= frames - 1:
        raise ConfigError(
            f"--shift: must be between 1 and frames - 1 = {frames - 1} for this dataset, "
            f"got {shift}"
        )
    if not (max_depth > 0 and math.isfinite(max_depth)):
        raise ConfigError(f"--max-depth: must be a positive number of metres, got {max_depth}")
    if flicker < 0:
        raise ConfigError(f"--flicker: must be >= 0, got {flicker}")


# ---------------------------------------------------------------- the measurements


def _mean(s: float, n: int) -> float | None:
    return float(s / n) if n else None


def _share(c: int, n: int) -> float | None:
    return float(c / n) if n else None


def dataset_stats(
    root: Path | Dataset,
    scenes: int = 200,
    shift: int = NOMINAL_SHIFT,
    max_depth: float = MAX_DEPTH,
    progress: bool = False,
) -> dict:
    """Depth, wall/object, flow and residual statistics of the first ``scenes`` scenes.

    Depths in metres, flow in pixels, residuals in grey levels (0-255), shares in [0, 1];
    ``shift`` is the frame shift of the pairs (i, i + shift); ``max_depth`` (metres) is the top of
    the coarse depth histogram. Returns the dict written to stats.json (without ``flicker``).
    Raises ConfigError (naming the flag or file) on bad input.
    """
    from tqdm import tqdm

    ds = _open(root)
    info, available = ds.info, ds.indices()
    frames = int(info.get("frames_per_scene", 0))
    _check_numbers(scenes, shift, frames, max_depth, 0)
    chosen = available[:scenes]
    if not chosen:
        raise ConfigError(f"DATASET: '{ds.root}' holds no scenes")
    scenes_used = ds.scenes(limit=scenes)  # every file name checked before measuring

    d_all, d_part = depth_histogram(), {p: depth_histogram() for p in PARTS}
    bands = np.zeros(len(BAND_EDGES_M), dtype=np.int64)
    n_pix = n_wall = n_beyond = n_miss = 0
    coarse_edges = np.linspace(0.0, max_depth, PLOT_DEPTH_BINS + 1)
    coarse = {p: Histogram(coarse_edges) for p in PARTS}
    flow_h = {p: flow_histogram() for p in PARTS}
    behind = n_flow_pix = 0
    res = {k: {p: [0.0, 0] for p in PARTS} for k in ("unwarped", "unwarped_on_valid", "warped")}
    n_pairs = n_frames = 0
    resolution = None

    bar = tqdm(scenes_used, desc="stats", unit="scene", disable=not progress, dynamic_ncols=True)
    for scene in bar:
        w, h = scene.record["resolution"]
        resolution = resolution or [w, h]
        K, poses, box = scene.K, list(scene.cam2world), scene.record["box"]
        depths, walls = [], []
        for f in range(len(poses)):
            d = scene.load_depth(f).astype(np.float64)
            wd = box_depth(K, poses[f], box["center"], box["half_extents"], w, h)
            wall = wall_mask(d, wd)
            depths.append(d)
            walls.append(wall)
            d_all.add(d)
            bands += band_counts(d)
            n_pix += d.size
            n_frames += 1
            n_wall += int(wall.sum())
            n_beyond += int((~wall & (d > wd)).sum())
            n_miss += int((d >= formats.NO_SURFACE_DEPTH).sum())
            for p, m in (("walls", wall), ("objects", ~wall)):
                d_part[p].add(d[m])
                coarse[p].add(d[m])
        imgs = [_bgr(scene.load_rgb(f)) for f in range(scene.frames)]
        for i in range(len(poses) - shift):
            j = i + shift
            flow, z_j = true_flow(depths[i], K, poses[i], poses[j])
            mag = np.hypot(flow[..., 0], flow[..., 1])
            ok = np.isfinite(mag)
            behind += int((~ok).sum())
            n_flow_pix += mag.size
            unwarped, warped, valid = warp_residuals(imgs[i], imgs[j], depths[j], flow, z_j)
            for p, m in (("walls", walls[i]), ("objects", ~walls[i])):
                flow_h[p].add(mag[m & ok])
                for key, values, mask in (
                    ("unwarped", unwarped, m),
                    ("unwarped_on_valid", unwarped, m & valid),
                    ("warped", warped, m & valid),
                ):
                    res[key][p][0] += float(values[mask].sum(dtype=np.float64))
                    res[key][p][1] += int(mask.sum())
            n_pairs += 1

    n_obj = n_pix - n_wall
    below25 = int(bands[: BAND_EDGES_M.index(25.0)].sum())
    in5_25 = int(bands[BAND_EDGES_M.index(5.0) : BAND_EDGES_M.index(25.0)].sum())
    shares = {k: float(c / n_pix) for k, c in zip(BAND_LABELS, bands, strict=True)}
    flow_pix = {p: flow_h[p].total for p in PARTS}
    flow_out = {
        p: {
            "median_px": flow_h[p].quantile(0.5),
            "p10_px": flow_h[p].quantile(0.1),
            "p90_px": flow_h[p].quantile(0.9),
            "pixels": flow_pix[p],
        }
        for p in PARTS
    }
    plot_edges = np.logspace(*FLOW_LOG_RANGE, PLOT_FLOW_BINS + 1)
    step = FLOW_BINS // PLOT_FLOW_BINS
    flow_plot = {}
    for p in PARTS:
        c = flow_h[p].counts
        inner = c[1 : 1 + FLOW_BINS].reshape(PLOT_FLOW_BINS, step).sum(axis=1)
        n = max(flow_pix[p], 1)
        flow_plot[p] = {
            "shares": (inner / n).tolist(),
            "share_below": float(c[0] / n),
            "share_above": float(c[-1] / n),
        }
    valid_share = {
        p: _share(res["warped"][p][1], res["unwarped"][p][1]) for p in PARTS
    }  # pixels of the pairs kept for the warped residual
    return {
        "dataset": str(ds.root),
        "generator": info.get("versions", {}).get("stillbox-gen"),
        "resolution": resolution,
        "frames_per_scene": frames,
        "scenes_used": chosen,
        "n_scenes": len(chosen),
        "frames": n_frames,
        "shift": shift,
        "pairs": n_pairs,
        "averaging": (
            "pixels pooled over all frames (depth, walls/objects) or all pairs (i, i + shift), "
            "i = 0 .. frames - 1 - shift (flow, residuals), of the chosen scenes (the first "
            "n_scenes of the manifest); every pixel weighs the same. Medians and percentiles "
            f"from histograms (depth: {DEPTH_BIN_M * 100:g} cm bins; flow: log bins "
            f"{(10 ** ((FLOW_LOG_RANGE[1] - FLOW_LOG_RANGE[0]) / FLOW_BINS) - 1) * 100:.2f} % "
            "wide), interpolated linearly inside the bin"
        ),
        "depth": {
            "units": "metres, planar depth as stored",
            "median_m": d_all.quantile(0.5),
            "share_below_25m": below25 / n_pix,
            "share_5_25m": in5_25 / n_pix,
            "band_edges_m": list(BAND_EDGES_M),
            "band_shares": shares,
            "miss_share": n_miss / n_pix,
            "histogram": {
                "edges_m": coarse_edges.tolist(),
                **{
                    p: {
                        "shares": (coarse[p].counts[:-1] / n_pix).tolist(),
                        "share_above": float(coarse[p].counts[-1] / n_pix),
                    }
                    for p in PARTS
                },
                "note": "shares of all pixels (walls + objects sum to 1 with share_above)",
            },
        },
        "walls_objects": {
            "wall_share": n_wall / n_pix,
            "object_share": n_obj / n_pix,
            "beyond_box_share": n_beyond / n_pix,
            "median_wall_depth_m": d_part["walls"].quantile(0.5),
            "median_object_depth_m": d_part["objects"].quantile(0.5),
            "wall_rule": (
                f"|depth - box exit depth| <= {WALL_RTOL:g} * box depth + {WALL_ATOL:g} m; "
                "objects: every other pixel (beyond_box_share: object pixels farther than the "
                "box, e.g. misses; 0 for a sound dataset)"
            ),
        },
        "flow": {
            "units": "pixels, frame i to frame i + shift",
            **flow_out,
            "behind_camera_share": _share(behind, n_flow_pix),
            "histogram": {"edges_px": plot_edges.tolist(), **flow_plot},
        },
        "residual": {
            "units": "grey levels (0-255), mean absolute difference over the 3 channels",
            **{k: {p: _mean(*res[k][p]) for p in PARTS} for k in res},
            "valid_share": valid_share,
            "rule": (
                "unwarped: |I_j - I_i| on every pixel; warped: |I_j(p + flow) - I_i(p)|, I_j "
                "bilinear, on pixels that land inside frame j, in front of it and not occluded "
                f"(bilinear depth_j within {OCCLUSION_RTOL:.0%} of the point's depth); "
                "unwarped_on_valid: |I_j - I_i| on those same pixels"
            ),
        },
        "max_depth_m": max_depth,
        "stillbox_reference": STILLBOX_REFERENCE,
    }


# ---------------------------------------------------------------- same-pose flicker


def _config_of(ds: Dataset):
    """The DatasetConfig of dataset.json (DatasetError naming it when it is not readable)."""
    from .config import from_dict

    try:
        return from_dict(ds.info["config"])
    except Exception as e:  # noqa: BLE001 - any malformed config is the dataset's
        raise DatasetError(f"'{ds.root / 'dataset.json'}': config is not readable ({e})") from None


def _check_photos(materials, scenes: list, root: Path) -> None:
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

    from .worker_setup import worker_setup
    from .workers import process_pool, render_scene

    ds = _open(root)
    available = ds.indices()
    if not 1 <= count <= len(available):
        raise ConfigError(f"--flicker: must be between 0 and {len(available)} scenes, got {count}")
    scenes = ds.scenes(limit=count)
    cfg = _config_of(ds)
    _check_photos(cfg.materials, scenes, ds.root)
    image_format = cfg.render.image_format
    sums = {k: {p: [0.0, 0] for p in PARTS} for k in ("same_pose", "other_seed")}
    depth_diff = 0.0
    used = []
    with (
        tempfile.TemporaryDirectory(prefix="stillbox-stats-") as tmp,
        process_pool(1, worker_setup(cfg, threads)) as pool,
        tqdm(
            total=2 * count, desc="flicker", unit="render", disable=not progress, dynamic_ncols=True
        ) as bar,
    ):
        for scene in scenes:
            rec = scene.record
            local = layout.local_index(rec["index"])
            stored = _bgr(scene.load_rgb(0)).astype(np.float32)
            depth = scene.load_depth(0).astype(np.float64)
            (w, h), box = rec["resolution"], rec["box"]
            box_d = box_depth(scene.K, scene.cam2world[0], box["center"], box["half_extents"], w, h)
            wall = wall_mask(depth, box_d)
            runs = (("same_pose", rec["seed"], [0, 0]), ("other_seed", rec["seed"] + 1, [0]))
            for key, seed, frames in runs:
                spec = spec_from_record(rec, frames=frames)
                spec["seed"] = seed
                out = Path(tmp) / f"{rec['index']}-{key}"
                pool.submit(render_scene, spec, str(out), image_format, False).result()
                last = len(frames) - 1
                name = layout.rgb_name(local, last, image_format)
                img = _bgr(formats.read_rgb(out / name)).astype(np.float32)
                diff = np.abs(img - stored).mean(axis=-1)
                for p, m in (("walls", wall), ("objects", ~wall)):
                    sums[key][p][0] += float(diff[m].sum(dtype=np.float64))
                    sums[key][p][1] += int(m.sum())
                new_depth = formats.read_depth_exr(out / layout.depth_name(local, last))
                depth_diff = max(depth_diff, float(np.abs(new_depth - depth).max()))
                bar.update(1)
            used.append([rec["index"], 0])
    return {
        "units": "grey levels (0-255), mean absolute difference over the 3 channels",
        "frames": used,
        **{k: {p: _mean(*sums[k][p]) for p in PARTS} for k in sums},
        "depth_max_abs_diff_m": depth_diff,
        "rule": (
            "the pose of frame 0 of the first scenes re-rendered with the dataset's render "
            "settings (dataset.json config.render): same_pose as frame 1 of its scene (same-pose "
            "flicker), other_seed as frame 0 with scene seed + 1; against the stored frame 0"
        ),
    }


# ---------------------------------------------------------------- report


def _fmt(v: float | None, kind: str) -> str:
    if v is None:
        return "-"
    if kind == "%":
        return f"{100 * v:.1f} %"
    if kind == "m":
        return f"{v:.1f} m"
    if kind == "px":
        return f"{v:.2f} px"
    return f"{v:.2f}"


def table(stats: dict) -> str:
    """The report as a plain-text table: our figure beside StillBox's ('-' when it has none)."""
    ref = stats["stillbox_reference"]
    d, wo, fl, rs = stats["depth"], stats["walls_objects"], stats["flow"], stats["residual"]
    rows: list[tuple[str, str, str]] = [
        ("median pixel depth", _fmt(d["median_m"], "m"), _fmt(ref["median_depth_m"], "m")),
        ("pixels below 25 m", _fmt(d["share_below_25m"], "%"), _fmt(ref["share_below_25m"], "%")),
        ("pixels in 5-25 m", _fmt(d["share_5_25m"], "%"), _fmt(ref["share_5_25m"], "%")),
    ]
    for k in BAND_LABELS:
        rows.append(
            (f"  depth {k} m", _fmt(d["band_shares"][k], "%"), _fmt(ref["band_shares"][k], "%"))
        )
    rows += [
        ("wall pixels", _fmt(wo["wall_share"], "%"), "-"),
        ("object pixels", _fmt(wo["object_share"], "%"), "-"),
        ("median wall depth", _fmt(wo["median_wall_depth_m"], "m"), "-"),
        ("median object depth", _fmt(wo["median_object_depth_m"], "m"), "-"),
    ]
    s = stats["shift"]
    for p in PARTS:
        f = fl[p]
        spread = f"{_fmt(f['median_px'], 'px')} ({_fmt(f['p10_px'], '')}-{_fmt(f['p90_px'], '')})"
        rows.append((f"flow at shift {s}, {p}: median (p10-p90)", spread, "-"))
    for key, label in (("unwarped", "no warp"), ("warped", "after true-flow warp")):
        for p in PARTS:
            rows.append((f"residual {label}, {p} (grey levels)", _fmt(rs[key][p], ""), "-"))
    for p in PARTS:
        rows.append((f"  pixels kept for the warp, {p}", _fmt(rs["valid_share"][p], "%"), "-"))
    fk = stats.get("flicker")
    if fk:
        for key, label in (("same_pose", "same-pose flicker"), ("other_seed", "other seed")):
            for p in PARTS:
                rows.append((f"{label}, {p} (grey levels)", _fmt(fk[key][p], ""), "-"))
    head = ("", "ours", "StillBox")
    widths = [max(len(r[c]) for r in [head, *rows]) for c in range(3)]
    lines = [
        f"{stats['dataset']}: {stats['n_scenes']} scenes, {stats['frames']} frames, "
        f"{stats['pairs']} pairs (i, i+{s}), {stats['resolution'][0]}x{stats['resolution'][1]} px",
        "  ".join(
            h.ljust(wd) if i == 0 else h.rjust(wd)
            for i, (h, wd) in enumerate(zip(head, widths, strict=True))
        ),
    ]
    for r in rows:
        lines.append(
            "  ".join(
                v.ljust(wd) if i == 0 else v.rjust(wd)
                for i, (v, wd) in enumerate(zip(r, widths, strict=True))
            )
        )
    return "\n".join(lines)


def plot(stats: dict, path: Path) -> None:
    """stats.png: depth bands ours vs StillBox, depth histogram to --max-depth (walls, objects),
    flow-magnitude histogram (walls, objects) on a log x-axis. Written via a temporary name."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d, fl = stats["depth"], stats["flow"]
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.2))
    x = np.arange(len(BAND_LABELS))
    ax = axes[0]
    ours = [100 * d["band_shares"][k] for k in BAND_LABELS]
    ref = [100 * stats["stillbox_reference"]["band_shares"][k] for k in BAND_LABELS]
    ax.bar(x - 0.2, ours, 0.4, label=f"ours ({stats['n_scenes']} scenes)")
    ax.bar(x + 0.2, ref, 0.4, label="StillBox (published samples)")
    ax.set_xticks(x, BAND_LABELS, rotation=45)
    ax.set_xlabel("pixel depth band (m)")
    ax.set_ylabel("share of pixels (%)")
    ax.set_title("pixel depth")
    ax.legend(fontsize=8)

    ax = axes[1]
    edges = np.asarray(d["histogram"]["edges_m"])
    bottom = np.zeros(len(edges) - 1)
    for p in PARTS:
        v = 100 * np.asarray(d["histogram"][p]["shares"])
        ax.bar(edges[:-1], v, np.diff(edges), bottom=bottom, align="edge", label=p)
        bottom += v
    ax.set_xlabel(f"pixel depth (m), up to --max-depth {stats['max_depth_m']:g}")
    ax.set_ylabel("share of pixels (%)")
    ax.set_title("pixel depth, walls and objects")
    ax.legend(fontsize=8)

    ax = axes[2]
    edges = np.asarray(fl["histogram"]["edges_px"])
    for p in PARTS:
        v = 100 * np.asarray(fl["histogram"][p]["shares"])
        ax.stairs(v, edges, label=f"{p} (median {_fmt(fl[p]['median_px'], 'px')})")
    ax.set_xscale("log")
    ax.set_xlabel(f"true flow magnitude (px), frames i to i+{stats['shift']}")
    ax.set_ylabel("share of the part's pixels (%)")
    ax.set_title("flow magnitude")
    ax.legend(fontsize=8)
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(path)


def _check_out_folder(out: Path) -> None:
    """--out can be written: a folder, or a path whose nearest existing ancestor is a writable
    folder (created after the measurements). ConfigError naming --out otherwise."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out: '{out}' is a file, not a folder")
    existing = next(p for p in (out, *out.absolute().parents) if p.exists())
    if not existing.is_dir():
        raise ConfigError(f"--out: '{existing}' is a file, not a folder")
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
    _check_numbers(scenes, shift, int(info.get("frames_per_scene", 0)), max_depth, flicker)
    if flicker > min(scenes, len(available)):
        raise ConfigError(
            f"--flicker: at most the {min(scenes, len(available))} scenes used, got {flicker}"
        )
    out = Path(out) if out is not None else ds.root
    _check_out_folder(out)
    if flicker:
        _check_photos(
            _config_of(ds).materials, ds.scenes(limit=flicker), ds.root
        )  # before measuring: they are re-rendered
    stats = dataset_stats(ds, scenes, shift, max_depth, progress)
    stats["flicker"] = flicker_stats(ds, flicker, progress) if flicker else None
    try:  # created only now: a refusal during the measurements leaves nothing behind
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"--out: cannot create '{out}' ({e.strerror})") from None
    formats.atomic_write_json(out / "stats.json", stats, indent=2)
    plot(stats, out / "stats.png")
    return stats
