"""Scoring a depth model on fixed forward pairs (i, i + shift) of a split.

Depth is scaled by the known displacement, never by the ground truth: the network answers for
its training set's nominal displacement (shift × metres per frame), so its output is multiplied
by |translation of the pair| / nominal displacement. Metrics: benchmark.metrics (per image at
full resolution, prediction upsampled bilinearly; then equal-weight mean over images), plus the
original DepthNet "depth error" at 1/4 resolution.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from . import geometry, metrics


@dataclass
class EvalResult:
    summary: dict
    per_sample: list[dict] = field(default_factory=list)
    pixels: dict[str, np.ndarray] = field(default_factory=dict)  # subsample for plots
    samples: list[dict] = field(default_factory=list)  # a few pairs for the sample grid


def _to_uint8(x: torch.Tensor) -> np.ndarray:
    """Inverse of the input normalisation, (3, H, W) -> (H, W, 3) uint8."""
    img = (x.numpy().transpose(1, 2, 0) * 0.2 + 0.5) * 255.0
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


@torch.no_grad()
def evaluate(
    model: torch.nn.Module,
    dataset,
    device: torch.device,
    batch_size: int,
    nominal_displacement: float,
    collect: bool = True,
    predictions_dir: Path | None = None,
    plot_pixels: int = 400_000,
    grid_samples: int = 6,
) -> EvalResult:
    """Score ``model`` on an eval-mode PairDataset; returns aggregated and per-pair metrics."""
    was_training = model.training
    model.eval()
    loader = torch.utils.data.DataLoader(dataset, batch_size=batch_size, shuffle=False)
    per_image: dict[str, list] = {}
    rows: list[dict] = []
    pix: dict[str, list] = {"gt": [], "pred": [], "abs_err": [], "foe_distance": []}
    samples: list[dict] = []
    per_pair = max(1, plot_pixels // max(1, len(dataset)))
    if predictions_dir is not None:
        predictions_dir.mkdir(parents=True, exist_ok=True)
    for batch in loader:
        x = batch["input"].to(device)
        gt = batch["target"].to(device)
        h, w = gt.shape[-2:]
        scale = batch["translation"].norm(dim=1).to(device) / nominal_displacement
        pred_q = model(x)[0] * scale.view(-1, 1, 1, 1)
        pred = metrics.upsample_to(pred_q, h, w)
        m = metrics.image_metrics(pred, gt)
        m["depth_error"] = metrics.original_depth_error(pred_q, gt)
        for k, v in m.items():
            per_image.setdefault(k, []).append(v.cpu())
        pred, gt = pred.cpu(), gt.cpu()
        for b in range(x.shape[0]):
            scene, (i1, i2) = int(batch["scene"][b]), batch["frames"][b].tolist()
            rows.append(
                {
                    "scene": scene,
                    "frame1": i1,
                    "frame2": i2,
                    **{k: float(v[b]) for k, v in m.items()},
                }
            )
            if predictions_dir is not None:
                np.save(
                    predictions_dir / f"{scene:06d}_{i1:02d}_{i2:02d}.npy",
                    pred[b].numpy().astype(np.float32),
                )
            if not collect:
                continue
            K, t = batch["K"][b].numpy().astype(np.float64), batch["translation"][b].numpy()
            p = pred[b].clamp(0.1, metrics.MAX_DEPTH).numpy()
            g = np.clip(gt[b].numpy(), 0, metrics.MAX_DEPTH)
            foe_dist = geometry.distance_to_foe(K, t.astype(np.float64), h, w)
            pick = np.random.default_rng(len(rows)).choice(h * w, min(per_pair, h * w), False)
            for name, arr in (
                ("gt", g),
                ("pred", p),
                ("abs_err", np.abs(p - g)),
                ("foe_distance", foe_dist),
            ):
                pix[name].append(arr.reshape(-1)[pick])
            if len(samples) < grid_samples and b == 0:
                xb = batch["input"][b]
                samples.append(
                    {
                        "img1": _to_uint8(xb[:3]),
                        "img2": _to_uint8(xb[3:]),
                        "gt": g,
                        "pred": p,
                        "foe": geometry.focus_of_expansion(K, t),
                    }
                )
    model.train(was_training)
    stacked = {k: torch.cat(v).numpy() for k, v in per_image.items()}
    summary = metrics.aggregate(stacked)  # valid_pixels decides which images count
    return EvalResult(
        summary=summary,
        per_sample=rows,
        pixels={k: np.concatenate(v) for k, v in pix.items() if v},
        samples=samples,
    )
