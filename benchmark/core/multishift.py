"""Multi-range depth from a stabilised video: frame-shift choice and fusion (thesis §6.1–6.3).

A depth network trained for a nominal displacement ``d0`` (metres between its two frames) answers
for any pair once its output is scaled by the pair's real displacement ``d``:

- (6.1) ``depth = α·β·d`` with ``β = output / θ_max`` (1 at the largest training depth) and
  ``α = θ_max / d0``; i.e. ``depth = output · d / d0``.
- (6.2) the displacement that puts the scene's mean depth at ``β_mean`` is
  ``E(depth) / (α·β_mean)``; it is smoothed over frames with an exponential moving average,
  ``d_opt ← λ·d_opt + (1 − λ)·E(depth)/(α·β_mean)``, and the next pair uses the frame shift whose
  displacement is closest to ``d_opt``. ``E`` is a trimmed mean (extremes, especially the far
  sky, left out).
- (§6.3) with ``n`` pairs per frame, the ``n`` centroids of a 1-D k-means of the depth map replace
  the mean, giving ``n`` targets ``d_opt,i`` and ``n`` shifts; the ``n`` depth maps are fused per
  pixel by a weighted mean whose weights (6.3) favour ``β`` near ``β_mean``.

Pure maths (torch and numpy only): no file, no network. Units: depth and displacements in metres,
``β`` and weights dimensionless, shifts in frames (1 = the previous frame).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

#: β below which an estimate gets the weight EPSILON (too little motion for the depth, thesis §6.3)
BETA_MIN = 0.1
#: the β the shift choice aims for and where the weight is 1 (thesis: "e.g. 0.5")
BETA_MEAN = 0.5
#: β from which an estimate gets weight 0 (near the network's saturation θ_max)
BETA_MAX = 0.9
#: weight below BETA_MIN, so that a pixel with every β too small still gets a depth
EPSILON = 1e-3
#: λ of the moving average of the target displacement (eq. 6.2); the thesis calls it arbitrary:
#: 0.5 here (the target moves halfway towards each new frame's value)
EMA_LAMBDA = 0.5
#: quantiles of the depth map kept for the mean / the clustering: the nearest 5 % and the
#: farthest 10 % (sky, saturated far walls) are left out
TRIM = (0.05, 0.90)
#: most clusters, i.e. frame pairs per frame (thesis: "usually ranges from 1 to 4")
MAX_SHIFTS = 4
#: eval-multishift's largest frame shift (frames; 1.2 m at StillBox's 0.1 m per frame): frames
#: t >= it of each sequence are scored
MULTISHIFT_MAX_SHIFT = 12


@dataclass(frozen=True)
class DepthScale:
    """How a depth network's output becomes metres (eq. 6.1).

    ``theta_max``: depth (m) the network outputs at β = 1, the largest training depth (100 m for
    DepthNet, the upper clamp for a clamped network); ``d0``: nominal displacement (m) of its
    training pairs.
    """

    theta_max: float
    d0: float

    @property
    def alpha(self) -> float:
        """α = θ_max / d0 (dimensionless)."""
        return self.theta_max / self.d0

    def beta(self, output: torch.Tensor) -> torch.Tensor:
        """β = output / θ_max (dimensionless; 1 at the largest training depth)."""
        return output / self.theta_max

    def depth(self, output: torch.Tensor, d: float) -> torch.Tensor:
        """Depth (m) of a pair with displacement ``d`` (m): output · d / d0 = α·β·d."""
        return output * (d / self.d0)


def weight(beta: torch.Tensor, beta_mean: float = BETA_MEAN) -> torch.Tensor:
    """Fusion weight f(β) of eq. 6.3, elementwise: EPSILON below BETA_MIN, linear from EPSILON to 1
    on [BETA_MIN, beta_mean), linear from 1 to 0 on [beta_mean, BETA_MAX), 0 from BETA_MAX on."""
    if not BETA_MIN < beta_mean < BETA_MAX:
        raise ValueError(f"beta_mean must be in ({BETA_MIN}, {BETA_MAX}), got {beta_mean}")
    beta = torch.as_tensor(beta)
    rising = EPSILON + (beta - BETA_MIN) / (beta_mean - BETA_MIN) * (1.0 - EPSILON)
    falling = (BETA_MAX - beta) / (BETA_MAX - beta_mean)
    w = torch.where(beta < beta_mean, rising, falling)
    w = torch.where(beta < BETA_MIN, torch.full_like(w, EPSILON), w)
    return torch.where(beta >= BETA_MAX, torch.zeros_like(w), w)


def fuse(
    outputs: torch.Tensor,
    displacements: Sequence[float],
    scale: DepthScale,
    beta_mean: float = BETA_MEAN,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Fuse the depth maps of ``n`` pairs of one frame (thesis §6.3).

    ``outputs``: (n, H, W) network outputs (m, for the nominal displacement); ``displacements``:
    the n pairs' displacements (m). Returns ``(depth (H, W) m, saturated (H, W) bool)``: the
    per-pixel mean of the n estimates α·β_i·d_i weighted by f(β_i); where every weight is 0 (every
    β_i ≥ BETA_MAX, the thesis' ŵ = +∞ case) the plain mean of the estimates, and ``saturated``
    is True there (such pixels are left out of the clustering). With n = 1 the depth is the one
    estimate.
    """
    if outputs.ndim != 3 or outputs.shape[0] != len(displacements):
        raise ValueError(
            f"outputs must be (n, H, W) with n = {len(displacements)} displacements, "
            f"got {tuple(outputs.shape)}"
        )
    pairs = zip(outputs, displacements, strict=True)
    estimates = torch.stack([scale.depth(o, d) for o, d in pairs])
    w = weight(scale.beta(outputs), beta_mean)
    total = w.sum(dim=0)
    saturated = total <= 0
    weighted = (w * estimates).sum(dim=0) / torch.where(saturated, torch.ones_like(total), total)
    return torch.where(saturated, estimates.mean(dim=0), weighted), saturated


def trimmed(values: torch.Tensor) -> torch.Tensor:
    """The values (flattened) between the TRIM quantiles, bounds included; empty stays empty."""
    v = torch.as_tensor(values).reshape(-1).to(torch.float64)
    if v.numel() == 0:
        return v
    lo, hi = torch.quantile(v, torch.tensor(TRIM, dtype=torch.float64))
    return v[(v >= lo) & (v <= hi)]


def kmeans_1d(values: torch.Tensor, n: int, iters: int = 50) -> torch.Tensor:
    """Sorted centroids (≤ n,) of a 1-D k-means (Lloyd) of ``values`` (flattened, float64).

    Deterministic: the centroids start at the quantiles (k + 0.5)/n; a cluster left empty is
    moved to the value farthest from its own centroid. With fewer than ``n`` distinct values the
    distinct values themselves are returned (fewer centroids); empty input gives no centroid.
    """
    v = torch.as_tensor(values).reshape(-1).to(torch.float64)
    distinct = torch.unique(v)
    if distinct.numel() <= n:
        return distinct
    c = torch.quantile(v, (torch.arange(n, dtype=torch.float64) + 0.5) / n)
    for _ in range(iters):
        label = (v[:, None] - c[None, :]).abs().argmin(dim=1)
        new = c.clone()
        for k in range(n):
            members = v[label == k]
            if members.numel():
                new[k] = members.mean()
            else:  # empty cluster: take the worst-fitted value
                far = (v - new[label]).abs().argmax()
                new[k] = v[far]
                label[far] = k
        if torch.equal(new, c):
            break
        c = new
    return torch.unique(c)  # sorted, and merged if two ended equal


def displacements(positions: np.ndarray, t: int, max_shift: int) -> np.ndarray:
    """d(t, δ) = |p_t − p_{t−δ}| (m) for δ = 1..min(t, max_shift), ``positions`` (frames, 3) the
    camera path in metres."""
    n = min(t, max_shift)
    back = positions[t - np.arange(1, n + 1)]
    return np.linalg.norm(positions[t] - back, axis=1)


def closest_shift(target_d: float, available: np.ndarray) -> int:
    """The frame shift (1-based) whose displacement is closest to ``target_d`` (m).

    ``available[k]``: displacement magnitude d(t, k + 1) (m) for shifts 1..len(available). Ties go
    to the smaller shift; shifts with a zero (or non-finite) displacement are never chosen
    (ValueError when every shift has one: no depth can be had from this frame).
    """
    a = np.asarray(available, dtype=np.float64)
    usable = np.isfinite(a) & (a > 0)
    if not usable.any():
        raise ValueError("no frame shift with a non-zero displacement")
    gap = np.where(usable, np.abs(a - target_d), np.inf)
    return int(np.argmin(gap)) + 1  # argmin: first of equal gaps, i.e. the smaller shift


class ShiftPlanner:
    """Chooses the frame shifts of the next frame's pairs (thesis §6.2–6.3).

    ``n``: clusters, i.e. pairs per frame (1..MAX_SHIFTS; 1 is the optimal single shift of §6.2);
    ``scale``: the network's DepthScale; ``ema``: λ of eq. 6.2 (0: no smoothing);
    ``fixed_shift``: always that shift (no adaptation); ``beta_mean``: the β the shifts aim at and
    the fusion favours (thesis: "e.g. 0.5"). ``d_opt`` (m, sorted, one per cluster) is None until
    the first :meth:`update`.
    """

    def __init__(
        self,
        n: int,
        scale: DepthScale,
        ema: float = EMA_LAMBDA,
        fixed_shift: int | None = None,
        beta_mean: float = BETA_MEAN,
    ):
        if not 1 <= n <= MAX_SHIFTS:
            raise ValueError(f"n must be in 1..{MAX_SHIFTS}, got {n}")
        if not 0 <= ema < 1:
            raise ValueError(f"ema must be in [0, 1), got {ema}")
        if fixed_shift is not None and fixed_shift < 1:
            raise ValueError(f"fixed_shift must be at least 1, got {fixed_shift}")
        if not BETA_MIN < beta_mean < BETA_MAX:
            raise ValueError(f"beta_mean must be in ({BETA_MIN}, {BETA_MAX}), got {beta_mean}")
        self.n, self.scale, self.ema, self.fixed_shift = n, scale, ema, fixed_shift
        self.beta_mean = beta_mean
        self.d_opt: np.ndarray | None = None

    def plan(self, available: np.ndarray) -> list[int]:
        """Unique sorted shifts (frames) for the next frame, given ``available[k]`` = d(t, k + 1)
        (m): the fixed shift (clipped to the available ones), else the shift closest to d0 before
        any depth is known, else the shift closest to each ``d_opt`` value."""
        if self.fixed_shift is not None:
            return [min(self.fixed_shift, len(available))]
        targets = [self.scale.d0] if self.d_opt is None else self.d_opt
        return sorted({closest_shift(float(d), available) for d in targets})

    def targets(self, depth: torch.Tensor, saturated: torch.Tensor) -> np.ndarray | None:
        """This frame's target displacements (m), sorted: the trimmed mean (n = 1) or the k-means
        centroids (n > 1) of the unsaturated depth, divided by α·β_mean. None without a value."""
        kept = trimmed(torch.as_tensor(depth)[~torch.as_tensor(saturated)])
        if kept.numel() == 0:
            return None
        centres = kept.mean().reshape(1) if self.n == 1 else kmeans_1d(kept, self.n)
        return centres.numpy() / (self.scale.alpha * self.beta_mean)

    def update(self, depth: torch.Tensor, saturated: torch.Tensor) -> None:
        """Move ``d_opt`` towards this frame's targets (eq. 6.2): λ·d_opt + (1 − λ)·targets; the
        first time, or when the number of centroids changes, ``d_opt`` restarts at the targets.
        A frame whose every pixel is saturated leaves ``d_opt`` as it was."""
        new = self.targets(depth, saturated)
        if new is None:
            return
        if self.d_opt is None or len(self.d_opt) != len(new):
            self.d_opt = new
        else:
            self.d_opt = self.ema * self.d_opt + (1.0 - self.ema) * new
