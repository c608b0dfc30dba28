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

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from stillbox_gen.conventions import MAX_DEPTH  # metres: predictions clamped, ground truth clipped

MIN_DEPTH = 0.1  # metres: predictions are clamped up to this before scoring (thesis 3.6.2)
#: bands [lo, hi) of ground-truth depth (metres) that reports break errors down by (a ground
#: truth clipped to exactly MAX_DEPTH, a sliver of sky, is in none)
DEPTH_BANDS = ((0.0, 10.0), (10.0, 25.0), (25.0, 50.0), (50.0, 100.0))
#: metres: the range within which depth becomes obstacles (the closed-loop flight's sensing range)
SENSING_RANGE = 15.0


@dataclass(frozen=True)
class Pixels:
    """The terms every metric of one batch is computed from: ``pred`` (clamped) and ``gt``
    (clipped; 1 m on invalid pixels) as ``(B, H, W)`` float64, ``valid`` the scored pixels,
    ``near`` the valid ones with ``gt <= sensing_range``, and their differences."""

    pred: torch.Tensor
    gt: torch.Tensor
    valid: torch.Tensor
    sensing_range: float

    @functools.cached_property
    def near(self) -> torch.Tensor:
        return self.valid & (self.gt <= self.sensing_range)

    @functools.cached_property
    def diff(self) -> torch.Tensor:
        return self.pred - self.gt

    @functools.cached_property
    def log_diff(self) -> torch.Tensor:
        return torch.log(self.pred) - torch.log(self.gt)

    @functools.cached_property
    def ratio(self) -> torch.Tensor:
        return torch.maximum(self.pred / self.gt, self.gt / self.pred)

    def mean(self, values: torch.Tensor, among: torch.Tensor | None = None) -> torch.Tensor:
        """(B,) mean of ``values`` over the pixels ``among`` (default: the valid ones) of each
        image; NaN for an image without such a pixel."""
        among = self.valid if among is None else among
        total = torch.where(among, values, torch.zeros_like(values)).sum(dim=(1, 2))
        return total / among.sum(dim=(1, 2)).to(torch.float64)  # 0/0 = NaN: no such pixel


@dataclass(frozen=True)
class Metric:
    """One per-image measure: ``label`` its name in the thesis' tables (Table 2.3), ``field``
    the name the monocular-depth literature reports it under (KITTI devkit, Monodepth2; "" when
    only the thesis uses it), ``unit`` ("m", or "" for none), ``formula`` in words and maths
    (θ̃ prediction, θ ground truth, E the mean over the scored pixels of one image), and
    ``compute``: its ``(B,)`` float64 values from a batch's :class:`Pixels`."""

    label: str
    field: str
    unit: str
    formula: str
    compute: Callable[[Pixels], torch.Tensor]


def _within(delta: float) -> Callable[[Pixels], torch.Tensor]:
    """P_delta: the share of pixels whose ratio to the truth is below ``delta``."""
    return lambda t: t.mean((t.ratio < delta).to(torch.float64))


def _silog(t: Pixels) -> torch.Tensor:
    # variance form of the KITTI devkit; clamped at 0 against rounding when e is constant
    spread = t.mean(t.log_diff.square()) - t.mean(t.log_diff).square()
    return 100 * spread.clamp(min=0).sqrt()


#: Every depth measure, in table order: the thesis' eight, the field's three others, then the
#: obstacle-avoidance pair. The one place metrics are defined (a new one is one entry): the
#: per-image scores, the reports and the CSVs derive from it.
METRIC_TABLE: dict[str, Metric] = {
    "mae": Metric(
        "MAE", "", "m", "MAE = E|θ̃ − θ|  (metres)", lambda t: t.mean(t.diff.abs())
    ),
    "mre": Metric(
        "MRE", "AbsRel", "", "MRE = AbsRel = E|θ̃ − θ| / θ", lambda t: t.mean(t.diff.abs() / t.gt)
    ),
    "mle": Metric(
        "MLE", "", "", "MLE = E|log θ̃ − log θ|  (natural log)",
        lambda t: t.mean(t.log_diff.abs()),
    ),
    "sae": Metric(
        "SAE", "RMSE", "m", "SAE = RMSE = sqrt(E(θ̃ − θ)²)  (metres)",
        lambda t: t.mean(t.diff.square()).sqrt(),
    ),
    "sle": Metric(
        "SLE", "RMSE log", "", "SLE = RMSE log = sqrt(E(log θ̃ − log θ)²)  (natural log)",
        lambda t: t.mean(t.log_diff.square()).sqrt(),
    ),
    "p1.25": Metric(
        "P1.25", "δ<1.25", "", "P_1.25 = δ<1.25 = E[max(θ̃/θ, θ/θ̃) < 1.25]", _within(1.25)
    ),
    "p1.25^2": Metric(
        "P1.25²", "δ<1.25²", "", "P_1.25² = E[max(θ̃/θ, θ/θ̃) < 1.25²]", _within(1.25**2)
    ),
    "p1.25^3": Metric(
        "P1.25³", "δ<1.25³", "", "P_1.25³ = E[max(θ̃/θ, θ/θ̃) < 1.25³]", _within(1.25**3)
    ),
    "sqrel": Metric(
        "SqRel", "SqRel", "m", "SqRel = E(θ̃ − θ)² / θ  (metres)",
        lambda t: t.mean(t.diff.square() / t.gt),
    ),
    "log10": Metric(
        "log10", "log10", "", "log10 = E|log10 θ̃ − log10 θ|",
        lambda t: t.mean(t.log_diff.abs()) / math.log(10),
    ),
    "silog": Metric(
        "SILog", "SILog", "",
        "SILog = 100 · sqrt(E e² − (E e)²), e = log θ̃ − log θ (natural log; KITTI devkit)",
        _silog,
    ),
    "missed_near": Metric(
        "missed", "", "",
        f"missed = share of the pixels with θ ≤ r estimated beyond r (r = {SENSING_RANGE:g} m: "
        "obstacles not seen); mean over the images that have such pixels",
        lambda t: t.mean((t.pred > t.sensing_range).to(torch.float64), t.near),
    ),
    "phantom_near": Metric(
        "phantom", "", "",
        f"phantom = share of the pixels with θ > r estimated within r (r = {SENSING_RANGE:g} m: "
        "obstacles that are not there); mean over the images that have such pixels",
        lambda t: t.mean((t.pred <= t.sensing_range).to(torch.float64), t.valid & ~t.near),
    ),
}  # fmt: skip

THESIS_METRICS = ("mae", "mre", "mle", "sae", "sle", "p1.25", "p1.25^2", "p1.25^3")
#: measures over a subset of an image's pixels: NaN for an image without any, which
#: :func:`aggregate` leaves out of their mean
RANGE_METRICS = ("missed_near", "phantom_near")
#: every measure :func:`image_metrics` returns (besides ``valid_pixels``)
METRICS = tuple(METRIC_TABLE)
DEPTH_METRICS = tuple(m for m in METRICS if m not in RANGE_METRICS)


FORMULAS: dict[str, str] = {name: m.formula for name, m in METRIC_TABLE.items()}
"""Each metric in words/maths, by name."""


def header(name: str) -> str:
    """Metric ``name``'s table header: the thesis' label, then the field's name and the unit,
    e.g. "MAE (m)", "MRE (AbsRel)", "SAE (RMSE, m)"."""
    m = METRIC_TABLE[name]
    extra = [x for x in (m.field if m.field != m.label else "", m.unit) if x]
    return f"{m.label} ({', '.join(extra)})" if extra else m.label


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
    sensing_range: float = SENSING_RANGE,
) -> dict[str, torch.Tensor]:
    """Per-image metrics of a batch of depth maps.

    Args:
        pred: ``(B, H, W)`` predicted depth, metres (any float dtype).
        gt: ``(B, H, W)`` ground-truth depth, metres; pixels that are not finite or ≤ 0 are invalid.
        max_depth: predictions are clamped to ``[min_depth, max_depth]`` and ground truth is
            clipped to ``max_depth`` before scoring.
        min_depth: lower clamp of the predictions (keeps log and ratios finite).
        sensing_range: metres, the ``r`` of ``missed_near`` and ``phantom_near``.

    Returns:
        ``{name: (B,) float64 tensor}`` for every name in :data:`METRICS` (NaN for an image with
        no valid pixel; :data:`RANGE_METRICS` also for an image without pixels on that side of
        ``sensing_range``), plus ``"valid_pixels"``: ``(B,) int64`` count of valid pixels.
        Tensors are on ``pred``'s device. A NaN prediction on a valid pixel makes that image's
        metrics NaN.
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

    pixels = Pixels(pred, gt, valid, sensing_range)
    out = {name: m.compute(pixels) for name, m in METRIC_TABLE.items()}
    out["valid_pixels"] = valid.sum(dim=(1, 2)).to(torch.int64)
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
            measures such as an ``original_depth_error`` column are averaged the same way);
            :data:`RANGE_METRICS` over the images where they are not NaN.
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
        kept = values[has_valid]
        if name in RANGE_METRICS:  # images without pixels on that side of the range: left out
            kept = kept[~np.isnan(kept)]
        summary[name] = float(kept.mean()) if len(kept) else math.nan
    summary["images"] = int(has_valid.sum())
    summary["images_without_valid_pixels"] = int(n_images - has_valid.sum())
    return summary


def median_scale(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """``(B,)`` float64: per image, median(gt) / median(pred) over ``gt``'s valid pixels
    (``pred``, ``gt``: ``(B, H, W)``; ground truth clipped to MAX_DEPTH as it is scored); NaN for
    an image without one. Medians interpolate between the two middle values for an even count
    (``torch.quantile``, as numpy.median). The "median scaling" of monocular-depth papers
    (Zhou et al. 2017; Monodepth2's ``--eval_mono``)."""
    valid = valid_mask(gt)
    out = torch.full((len(gt),), float("nan"), dtype=torch.float64, device=gt.device)
    for b in range(len(gt)):
        if valid[b].any():
            g = gt[b][valid[b]].double().clamp(max=MAX_DEPTH).quantile(0.5)
            out[b] = g / pred[b][valid[b]].double().quantile(0.5)
    return out


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
