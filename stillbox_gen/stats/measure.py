"""Items 1-4 of ``stillbox-gen stats`` over the first scenes of a dataset: depth bands and
histograms, wall and object pixels, true flow at the nominal shift, photometric residuals
(:func:`dataset_stats`, the ``stats.json`` without ``flicker``)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .. import formats
from ..conventions import MAX_DEPTH, NOMINAL_SHIFT
from ..dataset import Dataset, Scene
from ..errors import ConfigError
from .common import PARTS, bgr, mean_or_none, open_dataset, parts
from .geometry import (
    OCCLUSION_RTOL,
    WALL_ATOL,
    WALL_RTOL,
    box_depth,
    true_flow,
    wall_mask,
    warp_residuals,
)
from .histograms import (
    BAND_EDGES_M,
    BAND_LABELS,
    DEPTH_BIN_M,
    FLOW_BINS,
    FLOW_LOG_RANGE,
    PLOT_DEPTH_BINS,
    PLOT_FLOW_BINS,
    Histogram,
    band_counts,
    depth_histogram,
    flow_histogram,
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

RESIDUALS = ("unwarped", "unwarped_on_valid", "warped")


def check_numbers(scenes: int, shift: int, frames: int, max_depth: float, flicker: int) -> None:
    """ConfigError naming the flag of the first value out of its range (``frames``: the
    dataset's frames per scene, which bound ``shift``)."""
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


class Tally:
    """The running counts of :func:`dataset_stats`: pixels pooled over every frame (depth,
    walls) and every pair (flow, residuals) in the order they are added."""

    def __init__(self, max_depth: float) -> None:
        self.depth = depth_histogram()
        self.depth_part = {p: depth_histogram() for p in PARTS}
        self.bands = np.zeros(len(BAND_EDGES_M), dtype=np.int64)
        self.coarse_edges = np.linspace(0.0, max_depth, PLOT_DEPTH_BINS + 1)
        self.coarse = {p: Histogram(self.coarse_edges) for p in PARTS}
        self.flow = {p: flow_histogram() for p in PARTS}
        self.residual = {k: {p: [0.0, 0] for p in PARTS} for k in RESIDUALS}
        self.pixels = self.wall = self.beyond = self.miss = 0
        self.behind = self.flow_pixels = 0
        self.frames = self.pairs = 0

    def add_frame(self, depth: np.ndarray, wall: np.ndarray, wall_depth: np.ndarray) -> None:
        """One frame: its depth (metres), wall mask and box depth (metres)."""
        self.depth.add(depth)
        self.bands += band_counts(depth)
        self.pixels += depth.size
        self.frames += 1
        self.wall += int(wall.sum())
        self.beyond += int((~wall & (depth > wall_depth)).sum())
        self.miss += int((depth >= formats.NO_SURFACE_DEPTH).sum())
        for p, m in parts(wall):
            self.depth_part[p].add(depth[m])
            self.coarse[p].add(depth[m])

    def add_pair(self, flow: np.ndarray, residuals: tuple, wall: np.ndarray) -> None:
        """One pair (i, j): the true flow (pixels), :func:`warp_residuals` and frame i's walls."""
        unwarped, warped, valid = residuals
        mag = np.hypot(flow[..., 0], flow[..., 1])
        ok = np.isfinite(mag)
        self.behind += int((~ok).sum())
        self.flow_pixels += mag.size
        for p, m in parts(wall):
            self.flow[p].add(mag[m & ok])
            for key, values, mask in (
                ("unwarped", unwarped, m),
                ("unwarped_on_valid", unwarped, m & valid),
                ("warped", warped, m & valid),
            ):
                self.residual[key][p][0] += float(values[mask].sum(dtype=np.float64))
                self.residual[key][p][1] += int(mask.sum())
        self.pairs += 1


def measure_scene(tally: Tally, scene: Scene, shift: int) -> None:
    """Add every frame of ``scene`` and every pair (i, i + shift) of it to ``tally``."""
    w, h = scene.record["resolution"]
    K, poses, box = scene.K, list(scene.cam2world), scene.record["box"]
    depths, walls = [], []
    for f in range(len(poses)):
        d = scene.load_depth(f).astype(np.float64)
        wd = box_depth(K, poses[f], box["center"], box["half_extents"], w, h)
        walls.append(wall_mask(d, wd))
        depths.append(d)
        tally.add_frame(d, walls[-1], wd)
    imgs = [bgr(scene.load_rgb(f)) for f in range(scene.frames)]
    for i in range(len(poses) - shift):
        j = i + shift
        flow, z_j = true_flow(depths[i], K, poses[i], poses[j])
        tally.add_pair(flow, warp_residuals(imgs[i], imgs[j], depths[j], flow, z_j), walls[i])


def _averaging() -> str:
    return (
        "pixels pooled over all frames (depth, walls/objects) or all pairs (i, i + shift), "
        "i = 0 .. frames - 1 - shift (flow, residuals), of the chosen scenes (the first "
        "n_scenes of the manifest); every pixel weighs the same. Medians and percentiles "
        f"from histograms (depth: {DEPTH_BIN_M * 100:g} cm bins; flow: log bins "
        f"{(10 ** ((FLOW_LOG_RANGE[1] - FLOW_LOG_RANGE[0]) / FLOW_BINS) - 1) * 100:.2f} % "
        "wide), interpolated linearly inside the bin"
    )


def depth_section(t: Tally) -> dict:
    """stats.json's ``depth``: medians, band shares and the coarse histogram (shares of all
    pixels)."""
    n_pix = t.pixels
    below25 = int(t.bands[: BAND_EDGES_M.index(25.0)].sum())
    in5_25 = int(t.bands[BAND_EDGES_M.index(5.0) : BAND_EDGES_M.index(25.0)].sum())
    return {
        "units": "metres, planar depth as stored",
        "median_m": t.depth.quantile(0.5),
        "share_below_25m": below25 / n_pix,
        "share_5_25m": in5_25 / n_pix,
        "band_edges_m": list(BAND_EDGES_M),
        "band_shares": {k: float(c / n_pix) for k, c in zip(BAND_LABELS, t.bands, strict=True)},
        "miss_share": t.miss / n_pix,
        "histogram": {
            "edges_m": t.coarse_edges.tolist(),
            **{
                p: {
                    "shares": (t.coarse[p].counts[:-1] / n_pix).tolist(),
                    "share_above": float(t.coarse[p].counts[-1] / n_pix),
                }
                for p in PARTS
            },
            "note": "shares of all pixels (walls + objects sum to 1 with share_above)",
        },
    }


def walls_section(t: Tally) -> dict:
    """stats.json's ``walls_objects``: shares of pixels and median depths of each part."""
    return {
        "wall_share": t.wall / t.pixels,
        "object_share": (t.pixels - t.wall) / t.pixels,
        "beyond_box_share": t.beyond / t.pixels,
        "median_wall_depth_m": t.depth_part["walls"].quantile(0.5),
        "median_object_depth_m": t.depth_part["objects"].quantile(0.5),
        "wall_rule": (
            f"|depth - box exit depth| <= {WALL_RTOL:g} * box depth + {WALL_ATOL:g} m; "
            "objects: every other pixel (beyond_box_share: object pixels farther than the "
            "box, e.g. misses; 0 for a sound dataset)"
        ),
    }


def _flow_plot(h: Histogram) -> dict:
    """The fine flow histogram ``h`` in PLOT_FLOW_BINS coarse log bins (shares of its pixels)."""
    c, n = h.counts, max(h.total, 1)
    inner = c[1 : 1 + FLOW_BINS].reshape(PLOT_FLOW_BINS, FLOW_BINS // PLOT_FLOW_BINS).sum(axis=1)
    return {
        "shares": (inner / n).tolist(),
        "share_below": float(c[0] / n),
        "share_above": float(c[-1] / n),
    }


def flow_section(t: Tally) -> dict:
    """stats.json's ``flow``: median and 10/90 percentiles per part, and the histogram."""
    parts_out = {
        p: {
            "median_px": t.flow[p].quantile(0.5),
            "p10_px": t.flow[p].quantile(0.1),
            "p90_px": t.flow[p].quantile(0.9),
            "pixels": t.flow[p].total,
        }
        for p in PARTS
    }
    edges = np.logspace(*FLOW_LOG_RANGE, PLOT_FLOW_BINS + 1)
    return {
        "units": "pixels, frame i to frame i + shift",
        **parts_out,
        "behind_camera_share": mean_or_none(t.behind, t.flow_pixels),
        "histogram": {"edges_px": edges.tolist(), **{p: _flow_plot(t.flow[p]) for p in PARTS}},
    }


def residual_section(t: Tally) -> dict:
    """stats.json's ``residual``: mean residuals per kind and part, and the share of the pairs'
    pixels kept for the warped residual."""
    r = t.residual
    return {
        "units": "grey levels (0-255), mean absolute difference over the 3 channels",
        **{k: {p: mean_or_none(*r[k][p]) for p in PARTS} for k in r},
        "valid_share": {p: mean_or_none(r["warped"][p][1], r["unwarped"][p][1]) for p in PARTS},
        "rule": (
            "unwarped: |I_j - I_i| on every pixel; warped: |I_j(p + flow) - I_i(p)|, I_j "
            "bilinear, on pixels that land inside frame j, in front of it and not occluded "
            f"(bilinear depth_j within {OCCLUSION_RTOL:.0%} of the point's depth); "
            "unwarped_on_valid: |I_j - I_i| on those same pixels"
        ),
    }


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

    ds = open_dataset(root)
    info, available = ds.info, ds.indices()
    frames = int(info.get("frames_per_scene", 0))
    check_numbers(scenes, shift, frames, max_depth, 0)
    chosen = available[:scenes]
    if not chosen:
        raise ConfigError(f"DATASET: '{ds.root}' holds no scenes")
    scenes_used = ds.scenes(limit=scenes)  # every file name checked before measuring
    tally = Tally(max_depth)
    for scene in tqdm(
        scenes_used, desc="stats", unit="scene", disable=not progress, dynamic_ncols=True
    ):
        measure_scene(tally, scene, shift)
    return {
        "dataset": str(ds.root),
        "generator": info.get("versions", {}).get("stillbox-gen"),
        "resolution": scenes_used[0].record["resolution"] if scenes_used else None,
        "frames_per_scene": frames,
        "scenes_used": chosen,
        "n_scenes": len(chosen),
        "frames": tally.frames,
        "shift": shift,
        "pairs": tally.pairs,
        "averaging": _averaging(),
        "depth": depth_section(tally),
        "walls_objects": walls_section(tally),
        "flow": flow_section(tally),
        "residual": residual_section(tally),
        "max_depth_m": max_depth,
        "stillbox_reference": STILLBOX_REFERENCE,
    }
