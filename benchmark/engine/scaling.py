"""Scales of a depth known up to a factor (the SFMLearner baseline; thesis Tables 5.1-5.3).

A network trained without pose normalisation (``sfmlearner``: benchmark.core.dispnet) gives
depth and PoseNet translations in one arbitrary unit; its depth is put in metres two ways:

- "P" (:func:`pose_scale`): per pair (i1, i2), the measured displacement over PoseNet's,
  ``‖t(i1 → i2)‖ / (ε + ‖τ_i1 − τ_i2‖)``, τ PoseNet's positions relative to the last frame of a
  window of N consecutive frames (N its sequence length) holding both: the window ends at i2, or
  is the scene's first N frames when i2 < N − 1 (pairs are closer than N frames: training checks
  ``shift < N``). The same rule as depthnet-unsup's "P" (evaluate: × ‖t‖ / d0, where d0 is the
  displacement eq. 5.2 gave PoseNet), with PoseNet's own displacement for d0; no ground truth.
- "GT" (core.metrics.median_scale): per image, the median of the ground truth over the median of the
  prediction, both over the pixels that are scored (core.metrics.valid_mask; ground truth
  clipped to MAX_DEPTH as it is scored). Medians interpolate between the two middle values for
  an even count (``torch.quantile``, as numpy.median).

:func:`scale_free_depth` gives both (evaluate.predict's Scoring.SCALE_FREE): ``depth`` with "P"
(what eval's metrics and best.pt use) and ``depth_gt`` with "GT" (its metrics: ``gt_``-prefixed).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..core import metrics
from ..core.data import NORM_MEAN, NORM_STD, FrameStore
from ..core.metrics import median_scale
from ..core.posenet import EPSILON


def window(i2: int, frames: int, length: int) -> int:
    """First frame of the ``length``-frame window of a scene of ``frames`` frames that ends at
    frame ``i2``, or the scene's first window when ``i2 < length − 1``."""
    return max(0, min(i2 - length + 1, frames - length))


def pose_windows(store: FrameStore, batch: dict, length: int) -> tuple[torch.Tensor, torch.Tensor]:
    """PoseNet's input for a batch of eval pairs: ``(B, 3·N, H, W)`` normalised frames of each
    pair's window (:func:`window`) and ``(B, 2)`` the positions of i1, i2 in it."""
    position = {s.index: k for k, s in enumerate(store.scenes)}
    h, w = store.height, store.width
    raw = np.empty((len(batch["scene"]), length, 3, h, w), np.uint8)
    where = torch.empty(len(raw), 2, dtype=torch.int64)
    pairs = zip(batch["scene"].tolist(), batch["frames"].tolist(), strict=True)
    for j, (scene, (i1, i2)) in enumerate(pairs):
        k = position[scene]
        first = window(i2, len(store.scenes[k].rgb), length)
        for f in range(length):
            raw[j, f] = store.rgb(k, first + f).transpose(2, 0, 1)
        where[j] = torch.tensor([i1 - first, i2 - first])
    if not ((where >= 0) & (where < length)).all():
        raise ValueError(f"pose_windows: pairs more than {length - 1} frames apart")
    sequence = (torch.from_numpy(raw).float() / 255.0 - NORM_MEAN) / NORM_STD
    return sequence.reshape(len(raw), 3 * length, h, w), where


def pose_scale(poses: torch.Tensor, where: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """The "P" scale ``(B,)``: measured ``‖translation‖`` (metres, ``(B, 3)``) over
    ``ε + ‖τ_i1 − τ_i2‖``, ``poses`` ``(B, N, dof)`` PoseNet's (translation first), ``where``
    ``(B, 2)``: the positions of i1, i2 in the window."""
    rows = torch.arange(len(poses), device=poses.device)
    moved = poses[rows, where[:, 0], :3] - poses[rows, where[:, 1], :3]
    return translation.norm(dim=1) / (EPSILON + moved.norm(dim=1))


def scale_free_depth(model, batch: dict, store: FrameStore, device) -> dict[str, torch.Tensor]:
    """Scoring.SCALE_FREE's prediction of an eval batch by an SfmLearnerNet ``model``: ``depth``
    (B, H, W) with the "P" scale, ``depth_q`` (B, 1, H/4, W/4) its area-downsampled version,
    ``depth_gt`` (B, H, W) with the "GT" scale, ``scale_p`` and ``scale_gt`` (B,)."""
    gt = batch["target"].to(device)
    h, w = gt.shape[-2:]
    raw = metrics.upsample_to(model(batch["input"].to(device))[0].float(), h, w)
    sequence, where = pose_windows(store, batch, model.frames)
    poses = model.pose(sequence.to(device)).float()
    p = pose_scale(poses, where.to(device), batch["translation"].to(device))
    g = median_scale(raw, gt)
    depth = raw * p.view(-1, 1, 1)
    return {
        "depth": depth,
        "depth_q": F.adaptive_avg_pool2d(depth[:, None], (h // 4, w // 4)),
        "depth_gt": raw * g.to(raw.dtype).view(-1, 1, 1),
        "scale_p": p,
        "scale_gt": g,
    }
