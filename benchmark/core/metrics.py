"""Depth-map error measures of the StillBox thesis (section 2.4, Table 2.3).

Conventions
-----------
- Depth maps are planar depth (distance along the optical axis) in metres.
- ``pred`` is the estimate θ̃, ``gt`` the ground truth θ; both are ``(B, H, W)`` float tensors at
  the same resolution (use :func:`upsample_to` on a network's ``(B, 1, h, w)`` output first).
- A pixel is *valid* when its ground truth is finite and > 0 (tested before any clipping).
- Before scoring, predictions are clamped to ``[min_depth, max_depth]`` (flow-based methods can
  output negative depth, thesis 3.6.2) and ground truth is clipped to ``max_depth``.
- Every metric is computed per image over its valid pixels (reductions in float64, so the result
  does not depend on how images are batched), then :func:`aggregate` averages images with equal
  weight. See :data:`AVERAGING_RULE`.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from stillbox_gen.conventions import MAX_DEPTH  # metres: predictions clamped, ground truth clipped

MIN_DEPTH = 0.1  # metres: predictions are clamped up to this before scoring (thesis 3.6.2)

METRICS = ("mae", "mre", "mle", "sae", "sle", "p1.25", "p1.25^2", "p1.25^3")

#: threshold δ of each precision metric P_δ
DELTAS = {"p1.25": 1.25, "p1.25^2": 1.25**2, "p1.25^3": 1.25**3}

FORMULAS: dict[str, str] = {
    "mae": "MAE = E|θ̃ − θ|  (metres)",
    "mre": "MRE = E|θ̃ − θ| / θ",
    "mle": "MLE = E|log θ̃ − log θ|  (natural log)",
    "sae": "SAE = sqrt(E(θ̃ − θ)²)  (metres)",
    "sle": "SLE = sqrt(E(log θ̃ − log θ)²)  (natural log)",
    "p1.25": "P_1.25 = E[max(θ̃/θ, θ/θ̃) < 1.25]",
    "p1.25^2": "P_1.25² = E[max(θ̃/θ, θ/θ̃) < 1.25²]",
    "p1.25^3": "P_1.25³ = E[max(θ̃/θ, θ/θ̃) < 1.25³]",
}
"""Each metric in words/maths: θ̃ prediction, θ ground truth, E the mean over the valid pixels of
one image."""

AVERAGING_RULE = (
    f"Metrics are computed per image over its valid pixels (finite ground truth > 0), then "
    f"averaged over images with equal weight; images with no valid pixel are excluded and counted. "
    f"Before scoring, predictions are clamped to [min_depth, max_depth] = [{MIN_DEPTH:g}, "
    f"{MAX_DEPTH:g}] m and ground truth is clipped to max_depth {MAX_DEPTH:g} m."
)


def valid_mask(gt: torch.Tensor) -> torch.Tensor:
    """The pixels that are scored: ground truth finite and > 0 (boolean, ``gt``'s shape)."""
    return torch.isfinite(gt) & (gt > 0)


def image_metrics(
    pred: torch.Tensor,
    gt: torch.Tensor,
    max_depth: float = MAX_DEPTH,
    min_depth: float = MIN_DEPTH,
) -> dict[str, torch.Tensor]:
    """Per-image metrics of a batch of depth maps.

    Args:
        pred: ``(B, H, W)`` predicted depth, metres (any float dtype).
        gt: ``(B, H, W)`` ground-truth depth, metres; pixels that are not finite or ≤ 0 are invalid.
        max_depth: predictions are clamped to ``[min_depth, max_depth]`` and ground truth is
            clipped to ``max_depth`` before scoring.
        min_depth: lower clamp of the predictions (keeps log and ratios finite).

    Returns:
        ``{name: (B,) float64 tensor}`` for every name in :data:`METRICS` (NaN for an image with
        no valid pixel), plus ``"valid_pixels"``: ``(B,) int64`` count of valid pixels. Tensors
        are on ``pred``'s device. A NaN prediction on a valid pixel makes that image's metrics NaN.
    """
    if pred.ndim != 3 or pred.shape != gt.shape:
        raise ValueError(
            f"pred and gt must both be (B, H, W) with the same shape, got {tuple(pred.shape)} and "
            f"{tuple(gt.shape)} (upsample a (B, 1, h, w) output with upsample_to first)"
        )
    if not 0 < min_depth <= max_depth:
        raise ValueError(f"need 0 < min_depth <= max_depth, got {min_depth}, {max_depth}")

    pred = pred.detach().to(torch.float64).clamp(min_depth, max_depth)
    gt = gt.detach().to(device=pred.device, dtype=torch.float64)
    valid = valid_mask(gt)
    # Invalid pixels get a harmless placeholder (1 m) so logs and ratios stay finite; they are
    # masked out of every mean below.
    gt = torch.where(valid, gt.clamp(max=max_depth), torch.ones_like(gt))

    count = valid.sum(dim=(1, 2))
    n = count.to(torch.float64)  # 0 for an all-invalid image -> 0/0 = NaN below

    def mean(values: torch.Tensor) -> torch.Tensor:
        return torch.where(valid, values, torch.zeros_like(values)).sum(dim=(1, 2)) / n

    diff = pred - gt
    log_diff = torch.log(pred) - torch.log(gt)
    ratio = torch.maximum(pred / gt, gt / pred)

    out = {
        "mae": mean(diff.abs()),
        "mre": mean(diff.abs() / gt),
        "mle": mean(log_diff.abs()),
        "sae": mean(diff.square()).sqrt(),
        "sle": mean(log_diff.square()).sqrt(),
    }
    for name, delta in DELTAS.items():
        out[name] = mean((ratio < delta).to(torch.float64))
    out["valid_pixels"] = count.to(torch.int64)
    return out


def _to_numpy(values: np.ndarray | torch.Tensor) -> np.ndarray:
    if isinstance(values, torch.Tensor):
        values = values.detach().cpu().numpy()
    return np.asarray(values).reshape(-1)


def aggregate(per_image: dict[str, np.ndarray | torch.Tensor]) -> dict[str, float]:
    """Equal-weight mean over images of per-image metrics (see :data:`AVERAGING_RULE`).

    Args:
        per_image: ``{name: (N,) values}``, typically :func:`image_metrics` outputs concatenated
            over batches. Every key except ``"valid_pixels"`` is averaged (so extra per-image
            measures such as an ``original_depth_error`` column are averaged the same way).
            An image counts as having valid pixels when ``valid_pixels > 0`` if that key is given,
            else when its first :data:`METRICS` value (or, without any, every value) is not NaN.

    Returns:
        ``{name: mean over images with valid pixels}`` (NaN when there is none), plus
        ``"images"``: number of images averaged, and ``"images_without_valid_pixels"``: number
        of images excluded.
    """
    arrays = {name: _to_numpy(values).astype(np.float64) for name, values in per_image.items()}
    lengths = {len(a) for a in arrays.values()}
    if len(lengths) > 1:
        raise ValueError(f"per-image arrays have different lengths: {sorted(lengths)}")
    n_images = lengths.pop() if lengths else 0

    if "valid_pixels" in arrays:
        has_valid = arrays["valid_pixels"] > 0
    else:
        keys = [name for name in METRICS if name in arrays][:1] or list(arrays)
        has_valid = np.ones(n_images, dtype=bool)
        for name in keys:
            has_valid &= ~np.isnan(arrays[name])

    summary: dict[str, float] = {}
    for name, values in arrays.items():
        if name == "valid_pixels":
            continue
        summary[name] = float(values[has_valid].mean()) if has_valid.any() else math.nan
    summary["images"] = int(has_valid.sum())
    summary["images_without_valid_pixels"] = int(n_images - has_valid.sum())
    return summary


def original_depth_error(
    pred_quarter: torch.Tensor, gt: torch.Tensor, max_depth: float = MAX_DEPTH
) -> torch.Tensor:
    """The public DepthNet code's "depth error", per image.

    Ground truth is clipped to ``[0, max_depth]``, area-downsampled (average pooling,
    ``adaptive_avg_pool2d``) to the prediction's size, then the mean absolute difference is taken
    over all pixels. As in the original code there is no validity mask and the prediction is not
    clamped.

    Args:
        pred_quarter: ``(B, 1, h, w)`` (or ``(B, h, w)``) network output at 1/4 resolution, metres.
        gt: ``(B, H, W)`` ground-truth depth, metres (finite).
        max_depth: ground-truth clip, metres.

    Returns:
        ``(B,)`` float64 tensor, metres.
    """
    if pred_quarter.ndim == 4:
        if pred_quarter.shape[1] != 1:
            raise ValueError(f"pred_quarter must have one channel, got {tuple(pred_quarter.shape)}")
        pred_quarter = pred_quarter[:, 0]
    if pred_quarter.ndim != 3 or gt.ndim != 3 or pred_quarter.shape[0] != gt.shape[0]:
        raise ValueError(
            f"expected pred_quarter (B, 1, h, w) and gt (B, H, W), got {tuple(pred_quarter.shape)} "
            f"and {tuple(gt.shape)}"
        )
    pred = pred_quarter.detach().to(torch.float64)
    target = gt.detach().to(device=pred.device, dtype=torch.float64).clamp(0.0, max_depth)
    target_small = F.adaptive_avg_pool2d(target[:, None], tuple(pred.shape[-2:]))[:, 0]
    return (pred - target_small).abs().mean(dim=(1, 2))


def upsample_to(pred: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Bilinear upsampling (``align_corners=False``) of ``(B, 1, h, w)`` to ``(B, H, W)``.

    Keeps the dtype and device; values (metres) are interpolated, not rescaled.
    """
    if pred.ndim != 4 or pred.shape[1] != 1:
        raise ValueError(f"pred must be (B, 1, h, w), got {tuple(pred.shape)}")
    out = F.interpolate(pred, size=(height, width), mode="bilinear", align_corners=False)
    return out[:, 0]
