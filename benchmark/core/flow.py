"""Optical flow of a translating camera in a static scene, and depth back from flow (thesis 3.3.1).

Conventions (the dataset's, docs/FORMAT.md):

- OpenCV camera axes: x right, y down, z forward. Pixel coordinates ``(x, y)`` in pixels, the
  centre of the top-left pixel at ``(0, 0)``; ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (a
  skew term is ignored; stillbox-gen writes none).
- Depth is planar depth ``Z`` along the optical axis, metres.
- Two frames ``a`` and ``b`` of one camera with the same orientation (stabilised); the camera
  centre moves by ``T = (Tx, Ty, Tz)`` metres from ``a`` to ``b``, expressed in ``a``'s axes. A
  point at depth ``Z_a`` in frame ``a`` has depth ``Z_b = Z_a − Tz`` in frame ``b``.
- Flow lives on frame ``a``'s pixel grid: ``flow[:, y, x] = (position in frame b) − (x, y)``, in
  pixels, channel 0 horizontal (x), channel 1 vertical (y).

With ``A(p) = (fx·Tx − Tz·(x − cx), fy·Ty − Tz·(y − cy))`` the flow is ``F(p) = −A(p) / Z_b(p)``:
every vector lies on the line through its pixel and the focus of expansion (where ``A`` = 0), and
``Z_b = (A·A) / (−A·F)`` recovers depth from flow (the projection of ``F`` on that line; valid
for lateral motion too, ``Tz = 0``, where the FOE is at infinity). Near the FOE ``A`` → 0 and the
flow → 0: depth from flow is ill-conditioned there.

For the benchmark, frame ``a`` is the pair's *second* frame (whose depth is the target) and ``b``
the first: the flow networks predict, at each pixel of the second frame, where it was in the
first frame, and ``T`` is the translation from the second to the first frame (minus the pair's
translation).

All functions take torch tensors, batched ``(B, ...)`` or unbatched (no leading B); they compute
in the dtype of their input (pass float64 for exact geometry).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from stillbox_gen.conventions import MAX_DEPTH

from .metrics import MIN_DEPTH  # depth from flow is clamped to [MIN_DEPTH, MAX_DEPTH] metres


def _batched(x: torch.Tensor, ndim: int) -> tuple[torch.Tensor, bool]:
    """Add a batch axis when ``x`` has ``ndim − 1`` dimensions."""
    if x.ndim == ndim - 1:
        return x.unsqueeze(0), True
    if x.ndim != ndim:
        raise ValueError(f"expected a tensor with {ndim - 1} or {ndim} dimensions, got {x.shape}")
    return x, False


def _camera(K: torch.Tensor, t: torch.Tensor, batch: int, like: torch.Tensor):
    """(fx, fy, cx, cy, Tx, Ty, Tz), each (B, 1, 1) in ``like``'s dtype and device."""
    K = torch.as_tensor(K).to(like).reshape(-1, 3, 3).expand(batch, 3, 3)
    t = torch.as_tensor(t).to(like).reshape(-1, 3).expand(batch, 3)
    v = (K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], t[:, 0], t[:, 1], t[:, 2])
    return tuple(u.reshape(batch, 1, 1) for u in v)


def pixel_grid(height: int, width: int, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre coordinates ``(xs, ys)``, each ``(H, W)``."""
    ys = torch.arange(height, dtype=like.dtype, device=like.device)
    xs = torch.arange(width, dtype=like.dtype, device=like.device)
    return xs.view(1, -1).expand(height, width), ys.view(-1, 1).expand(height, width)


def epipolar_direction(
    K: torch.Tensor, translation: torch.Tensor, height: int, width: int, like: torch.Tensor
) -> torch.Tensor:
    """``A(p) = (fx·Tx − Tz·(x − cx), fy·Ty − Tz·(y − cy))`` per pixel, ``(B, 2, H, W)``.

    The flow of a static point at depth ``Z_b`` (frame b) is ``−A / Z_b``; ``A = 0`` at the FOE.
    ``K``: ``(B, 3, 3)`` or ``(3, 3)``; ``translation``: ``(B, 3)`` or ``(3,)``, a→b, metres;
    ``like``: a tensor giving dtype and device.
    """
    batch = max(
        torch.as_tensor(K).reshape(-1, 9).shape[0],
        torch.as_tensor(translation).reshape(-1, 3).shape[0],
    )
    fx, fy, cx, cy, tx, ty, tz = _camera(K, translation, batch, like)
    xs, ys = pixel_grid(height, width, like)
    return torch.stack((fx * tx - tz * (xs - cx), fy * ty - tz * (ys - cy)), dim=1)


def flow_from_depth(
    depth: torch.Tensor, K: torch.Tensor, translation: torch.Tensor
) -> torch.Tensor:
    """Exact optical flow of a static scene seen by a translating camera.

    Args:
        depth: ``(B, H, W)`` or ``(H, W)`` planar depth of frame a at its pixels, metres.
        K: ``(B, 3, 3)`` or ``(3, 3)`` intrinsics, pixels.
        translation: ``(B, 3)`` or ``(3,)`` camera displacement from frame a to frame b, metres,
            in frame a's OpenCV axes.

    Returns:
        ``(B, 2, H, W)`` (or ``(2, H, W)``) flow in pixels: position in frame b minus position in
        frame a, computed by back-projecting each pixel centre to 3-D and projecting it into b.
        NaN where the depth is not finite or ≤ 0, or where the point is not in front of camera b
        (``Z_a − Tz ≤ 0``). Depth "misses" (1e10 m) get a flow of ~0, as points at infinity.
    """
    depth, single = _batched(depth, 3)
    b, h, w = depth.shape
    fx, fy, cx, cy, tx, ty, tz = _camera(K, translation, b, depth)
    xs, ys = pixel_grid(h, w, depth)
    z_b = depth - tz
    x_b = (xs - cx) * depth / fx - tx  # frame-b camera coordinates (same orientation)
    y_b = (ys - cy) * depth / fy - ty
    flow = torch.stack((cx + fx * x_b / z_b - xs, cy + fy * y_b / z_b - ys), dim=1)
    valid = torch.isfinite(depth) & (depth > 0) & (z_b > 0)
    flow = torch.where(valid.unsqueeze(1), flow, torch.full_like(flow, float("nan")))
    return flow[0] if single else flow


def depth_from_flow(
    flow: torch.Tensor,
    K: torch.Tensor,
    translation: torch.Tensor,
    clamp: bool = True,
    min_depth: float = MIN_DEPTH,
    max_depth: float = MAX_DEPTH,
) -> torch.Tensor:
    """Depth of frame a from its flow towards frame b and the known translation (thesis 3.3.1).

    ``Z_b = (A·A) / (−A·F)`` (the flow projected on the line through the FOE), then
    ``Z_a = Z_b + Tz``. Works for forward, backward, lateral (``Tz`` = 0, FOE at infinity) and
    oblique motion, FOE inside or outside the image.

    Args:
        flow: ``(B, 2, H, W)`` or ``(2, H, W)`` flow at frame a's pixels, pixels (see module doc).
        K: ``(B, 3, 3)`` or ``(3, 3)`` intrinsics, pixels.
        translation: ``(B, 3)`` or ``(3,)`` camera displacement a→b in a's axes, metres.
        clamp: clamp to ``[min_depth, max_depth]`` (thesis 3.6.2: flow-based depth may be
            negative). Where the flow carries no parallax (``A·F = 0``: zero flow, or the exact
            FOE) or is NaN, depth is "at infinity" and becomes ``max_depth``; no pixel is dropped.
            With ``clamp=False`` the raw quotient is returned (± inf, NaN, negative values kept).

    Returns:
        ``(B, H, W)`` (or ``(H, W)``) planar depth of frame a, metres.
    """
    flow, single = _batched(flow, 4)
    b, _, h, w = flow.shape
    fx, fy, cx, cy, tx, ty, tz = _camera(K, translation, b, flow)
    xs, ys = pixel_grid(h, w, flow)
    a = torch.stack((fx * tx - tz * (xs - cx), fy * ty - tz * (ys - cy)), dim=1)
    den = -(a * flow).sum(1)
    den = torch.where(den == 0, torch.zeros_like(den), den)  # −0 -> +0: no parallax is +inf
    z_b = (a * a).sum(1) / den
    depth = z_b + tz
    if clamp:
        depth = torch.nan_to_num(depth, nan=max_depth).clamp(min_depth, max_depth)
    return depth[0] if single else depth


def stored_flow(scenes: dict, pairs: list[tuple[int, int, int]]) -> torch.Tensor | None:
    """The flow a dataset made with ``stillbox-gen --flow`` stores for ``pairs`` of (scene index,
    frame a, frame b), ``(B, 2, H, W)`` float64 pixels on frame a's grid towards frame b (this
    module's convention), NaN where the dataset's valid mask is false (the point leaves frame b
    or is behind it; occluded points are kept). ``scenes``: {scene index:
    stillbox_gen.dataset.Scene}. None when any pair has no stored flow. The stored flow uses the
    full poses (exact for rotating cameras too): stillbox_gen.flow."""
    if not pairs or any((a, b) not in scenes[k].flow_files for k, a, b in pairs):
        return None
    flows = [scenes[k].load_flow(a, b)[0] for k, a, b in pairs]
    return torch.from_numpy(np.stack(flows).transpose(0, 3, 1, 2).astype(np.float64))


def endpoint_error(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean end-point error ``E‖F̃ − F‖₂`` per image, pixels, float64.

    ``pred``, ``gt``: ``(B, 2, H, W)``. Pixels whose ground truth is NaN are left out; an image
    without any valid pixel gets NaN.
    """
    if pred.shape != gt.shape or pred.ndim != 4 or pred.shape[1] != 2:
        raise ValueError(f"expected two (B, 2, H, W) flows, got {pred.shape} and {gt.shape}")
    gt = gt.to(device=pred.device, dtype=torch.float64)
    valid = torch.isfinite(gt).all(1)
    err = (pred.to(torch.float64) - torch.nan_to_num(gt)).norm(dim=1)
    err = torch.where(valid, err, torch.zeros_like(err))
    return err.sum((1, 2)) / valid.sum((1, 2)).to(torch.float64)


#: KITTI 2015's outlier rule (Fl): an end-point error above both this many pixels and this share
#: of the true flow's length
FL_PIXELS, FL_SHARE = 3.0, 0.05
#: thresholds (pixels) of the plain outlier rates ``out1``, ``out3``, ``out5``
OUTLIER_PIXELS = (1, 3, 5)
FLOW_FORMULAS = {
    "fl_all": f"Fl-all = share of pixels with ‖F̃ − F‖ > {FL_PIXELS:g} px and > "
    f"{FL_SHARE:.0%} of ‖F‖ (KITTI 2015)",
    **{f"out{t}": f"out{t} = share of pixels with ‖F̃ − F‖ > {t} px" for t in OUTLIER_PIXELS},
}


def flow_errors(pred: torch.Tensor, gt: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per image ``(B,)`` float64: ``epe`` (:func:`endpoint_error`), ``fl_all`` and ``out1``,
    ``out3``, ``out5`` (:data:`FLOW_FORMULAS`), over the pixels whose ground truth is finite
    (NaN for an image without any). ``pred``, ``gt``: ``(B, 2, H, W)`` pixels."""
    out = {"epe": endpoint_error(pred, gt)}
    gt = gt.to(device=pred.device, dtype=torch.float64)
    valid = torch.isfinite(gt).all(1)
    n = valid.sum((1, 2)).to(torch.float64)
    truth = torch.nan_to_num(gt)
    err = (pred.to(torch.float64) - truth).norm(dim=1)

    def share(hit: torch.Tensor) -> torch.Tensor:
        return (hit & valid).sum((1, 2)).to(torch.float64) / n

    out["fl_all"] = share((err > FL_PIXELS) & (err > FL_SHARE * truth.norm(dim=1)))
    for t in OUTLIER_PIXELS:
        out[f"out{t}"] = share(err > t)
    return out


def warp_homography(
    image: torch.Tensor, homography: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``image`` ``(B, C, H, W)`` resampled through a homography of its pixels:
    ``out[:, :, p] = image[:, :, π(H·(x, y, 1))]``, ``homography`` ``(B, 3, 3)`` pixels → pixels
    (pass float64 for exact geometry). :func:`warp`'s bilinear sampling; its mask also drops the
    pixels whose ``H·p`` lies behind (third coordinate ≤ 0). With ``H = K·R·K⁻¹`` this is a frame
    seen from the same centre with another orientation (``R``: the new axes → the frame's)."""
    b, _, h, w = image.shape
    xs, ys = pixel_grid(h, w, homography)
    p = torch.stack((xs, ys, torch.ones_like(xs))).reshape(3, h * w)
    q = homography @ p  # (B, 3, H·W)
    z = torch.where(q[:, 2] > 0, q[:, 2], torch.full_like(q[:, 2], math.nan))
    moved = torch.stack((q[:, 0] / z - p[0], q[:, 1] / z - p[1]), 1)
    return warp(image, moved.reshape(b, 2, h, w).to(image.dtype))


def warp(image_b: torch.Tensor, flow: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Frame b resampled on frame a's grid: ``out[:, :, p] = image_b[:, :, p + flow(p)]``.

    Bilinear sampling at the flowed pixel-centre coordinates. ``image_b``: ``(B, C, H, W)``;
    ``flow``: ``(B, 2, H, W)`` a→b, pixels. Returns the warped image and a ``(B, H, W)`` bool
    mask of pixels whose flow is finite and lands inside frame b.
    """
    b, _, h, w = flow.shape
    xs, ys = pixel_grid(h, w, flow)
    x = xs + flow[:, 0]
    y = ys + flow[:, 1]
    inside = torch.isfinite(x) & torch.isfinite(y)
    inside &= (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    grid = torch.stack((2 * x / max(w - 1, 1) - 1, 2 * y / max(h - 1, 1) - 1), dim=-1)
    grid = torch.nan_to_num(grid, nan=-2.0).to(image_b.dtype)
    out = F.grid_sample(image_b, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out, inside
