"""Exact optical flow of a static scene from rendered depth, intrinsics and camera poses, with
its validity and occlusion masks: what ``stillbox-gen --flow`` writes (docs/FORMAT.md). The one
implementation of flow from depth and full pose (rotation and translation) in the project; numpy
only (no Blender, no torch), so the generator, the reader and the benchmark share it.

Conventions (docs/FORMAT.md, stillbox_gen.camera):

- OpenCV camera axes (x right, y down, z forward), metres; pixel coordinates ``(x, y)`` with the
  centre of the top-left pixel at ``(0, 0)``; ``K`` in pixels.
- Depth is planar depth ``z`` along the optical axis, metres, sampled at pixel centres.
- ``pose_ab`` (4, 4) maps frame ``a``'s camera coordinates to frame ``b``'s:
  ``inv(cam2world[b]) @ cam2world[a]`` (``Scene.relative_pose(a, b)``).
- Flow lives on frame ``a``'s grid: ``flow[y, x] = (position in frame b) − (x, y)``, pixels,
  channel 0 horizontal (x, right), channel 1 vertical (y, down): forward flow for ``a → a + s``,
  backward flow for ``a + s → a``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import formats
from .camera import backproject, invert_pose

#: A valid point is occluded in frame b when its depth there exceeds frame b's rendered depth
#: by more than this share of it, both at the pixel it lands in and interpolated at the landing
#: point (flow_masks).
OCCLUSION_TOLERANCE = 0.01


@dataclass
class PairFlow:
    """Flow from frame ``a`` to frame ``b`` on ``a``'s grid and its masks, each (H, W)."""

    flow: np.ndarray  # (H, W, 2) float32 pixels; NaN where undefined (behind camera b)
    valid: np.ndarray  # bool: defined, in front of camera b and landing inside frame b
    occluded: np.ndarray  # bool: valid and hidden in frame b (false where not valid)


def relative_pose(cam2world_a: np.ndarray, cam2world_b: np.ndarray) -> np.ndarray:
    """(4, 4) map from frame a's camera coordinates to frame b's (OpenCV axes, metres)."""
    return invert_pose(cam2world_b) @ np.asarray(cam2world_a, dtype=np.float64)


def flow_from_depth(
    depth_a: np.ndarray, K: np.ndarray, pose_ab: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Flow of frame a's pixels towards frame b, and their depth in frame b.

    Each pixel centre is back-projected at its depth ``depth_a`` (metres; "no surface" values of
    1e10 m act as points far away), moved by ``pose_ab`` and projected with ``K`` (pixels).
    Returns ``(flow (H, W, 2) float64 pixels, z_b (H, W) float64 metres)``; the flow is NaN where
    the depth is not finite and positive or the point is not in front of camera b (``z_b ≤ 0``).
    """
    K = np.asarray(K, dtype=np.float64)
    pose = np.asarray(pose_ab, dtype=np.float64)
    h, w = depth_a.shape
    points = backproject(depth_a, K) @ pose[:3, :3].T + pose[:3, 3]
    z_b = points[..., 2]
    ahead = np.isfinite(depth_a) & (depth_a > 0) & (z_b > 0)
    proj = points @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        landing = proj[..., :2] / proj[..., 2:3]
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    flow = landing - np.stack([xs, ys], axis=-1)
    flow[~ahead] = np.nan
    return flow, z_b


def sample_bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``image`` (H, W) interpolated bilinearly at pixel coordinates ``x``, ``y`` (same shape),
    which must lie in ``[0, W − 1] × [0, H − 1]``."""
    h, w = image.shape
    x0 = np.clip(np.floor(x).astype(np.int64), 0, max(w - 2, 0))
    y0 = np.clip(np.floor(y).astype(np.int64), 0, max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    img = np.asarray(image, dtype=np.float64)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def flow_masks(
    flow: np.ndarray,
    z_b: np.ndarray,
    depth_b: np.ndarray,
    tolerance: float = OCCLUSION_TOLERANCE,
) -> tuple[np.ndarray, np.ndarray]:
    """``(valid, occluded)`` (H, W) bool masks of a flow from :func:`flow_from_depth`.

    Valid: the flow is defined (finite: the point is in front of camera b) and lands inside frame
    b, ``0 ≤ x ≤ W − 1`` and ``0 ≤ y ≤ H − 1`` (pixel centres, where frame b can be sampled).
    Occluded: valid, and the point's depth in frame b ``z_b`` (metres) exceeds frame b's
    rendered depth ``depth_b`` by more than ``tolerance`` times it both at the pixel it lands in
    (the nearest pixel centre: something nearer is seen there) and interpolated bilinearly at the
    landing point (so that a slanted surface, whose depth changes by more than ``tolerance``
    within half a pixel, is not taken for an occluder).
    """
    h, w = z_b.shape
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    x, y = xs + flow[..., 0], ys + flow[..., 1]
    finite = np.isfinite(x) & np.isfinite(y)
    x, y = np.where(finite, x, -1.0), np.where(finite, y, -1.0)
    valid = finite & (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    x, y = np.where(valid, x, 0.0), np.where(valid, y, 0.0)
    nearest = np.asarray(depth_b, dtype=np.float64)[np.rint(y).astype(int), np.rint(x).astype(int)]
    limit = (1.0 + tolerance) * np.maximum(nearest, sample_bilinear(depth_b, x, y))
    occluded = valid & (z_b > limit)
    return valid, occluded


def pair_flow(
    depth_a: np.ndarray,
    depth_b: np.ndarray,
    K: np.ndarray,
    cam2world_a: np.ndarray,
    cam2world_b: np.ndarray,
) -> PairFlow:
    """Flow from frame a to frame b (depth maps in metres, ``K`` pixels, OpenCV cam2world poses)
    and its masks, as --flow writes them (:class:`PairFlow`)."""
    flow, z_b = flow_from_depth(depth_a, K, relative_pose(cam2world_a, cam2world_b))
    valid, occluded = flow_masks(flow, z_b, depth_b)
    return PairFlow(flow.astype(np.float32), valid, occluded)


def write_scene_flow(folder: Path, record: dict) -> None:
    """Write the flow and mask files of every entry of ``record["flow"]`` into ``folder``, from
    the scene's depth files there (``record["depth_exr"]``), its ``K`` and ``cam2world``: .flo
    (float32; Middlebury's unknown value, 1e10, where the flow is undefined) or, for a ``.png``
    flow file (--flow-format kitti-png), KITTI's 16-bit PNG, and 8-bit PNG masks (255 where
    true), each written atomically. In KITTI's format a valid flow beyond its range (about
    ±512 px) cannot be stored: such pixels are not valid (nor occluded) there, in both the
    PNG's valid channel and the valid mask, which stay equal."""
    folder = Path(folder)
    depth: dict[int, np.ndarray] = {}

    def load(frame: int) -> np.ndarray:
        if frame not in depth:
            depth[frame] = formats.read_depth(folder / record["depth_exr"][frame])
        return depth[frame]

    K, poses = np.asarray(record["K"]), np.asarray(record["cam2world"])
    for entry in record["flow"]:
        a, b = entry["from"], entry["to"]
        pair = pair_flow(load(a), load(b), K, poses[a], poses[b])
        if entry["flow"].endswith(".png"):
            pair.valid &= formats.kitti_representable(pair.flow)
            pair.occluded &= pair.valid
            formats.write_kitti_flow(folder / entry["flow"], pair.flow, pair.valid)
        else:
            formats.write_flo(folder / entry["flow"], pair.flow)
        formats.write_mask_png(folder / entry["valid"], pair.valid)
        formats.write_mask_png(folder / entry["occluded"], pair.occluded)
