"""Scoring a method on fixed forward pairs (i, i + shift) of a split.

Depth is scaled by the known displacement, never by the ground truth: a depth network answers for
its training set's nominal displacement (shift × metres per frame), so its output is multiplied
by |translation of the pair| / nominal displacement. A flow network's 1/4-resolution flow is
upsampled bilinearly to full resolution (its values are already full-resolution pixels), turned
into depth with the pair's known translation (benchmark.core.flow.depth_from_flow, clamped to
[0.1, 100] m, every pixel kept, the FOE's neighbourhood included) and its end-point error (EPE)
against the exact flow is reported too. A depth known up to a scale (Scoring.SCALE_FREE:
``sfmlearner``) is scaled by PoseNet's displacement ("P", its metrics) and by the ground truth's
median ("GT", its metrics prefixed ``gt_``): benchmark.engine.scaling. ``oracle-flow``
feeds the exact flow to the same geometry; ``constant`` predicts one depth everywhere. Metrics:
benchmark.core.metrics (per image at full resolution; then equal-weight mean over images), plus
the original DepthNet "depth error" at 1/4 resolution (for methods without a 1/4-resolution
depth output: their full-resolution depth, area-downsampled by 4).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from stillbox_gen.conventions import MAX_DEPTH

from ..core import flow, geometry, metrics, runfolder
from ..core.contract import depth_output
from ..core.registry import DEPTH, Kind, Scoring
from .predictions import PredictionFiles
from .scaling import scale_free_depth


@dataclass
class Method:
    """How a registered method turns a batch of pairs into depth.

    ``kind``: the registry's :class:`benchmark.core.registry.Kind` (how depth is obtained);
    ``model``: the network (depth and flow methods); ``nominal_displacement``: metres the depth
    network answers for (depth methods); ``constant``: metres (constant method);
    ``flow_noise``: standard deviation (pixels) of Gaussian noise added to the exact flow of
    ``oracle-flow`` (seeded by scene and frames: the conditioning of the geometry near the FOE);
    ``depth_range``: metres, a depth network's outputs are clamped to it before the displacement
    scaling (its training range; None: not clamped); ``predictions``: the files of a method of
    kind PREDICTIONS (depth of the pair's second frame, as given).
    """

    kind: Kind
    model: torch.nn.Module | None = None
    nominal_displacement: float | None = None
    constant: float | None = None
    flow_noise: float = 0.0  # oracle-flow: Gaussian noise (px, per component) added to the flow
    depth_range: tuple[float, float] | None = None
    predictions: PredictionFiles | None = None  # Scoring.GIVEN: the files read


def predict(
    method: Method, batch: dict, device: torch.device, store=None
) -> dict[str, torch.Tensor]:
    """Depth (B, H, W) at full resolution, its 1/4-resolution version ``depth_q`` (B, 1, h, w)
    and, for flow-based methods, the flow ``flow`` (B, 2, H, W) and the exact ``gt_flow``; for
    Scoring.SCALE_FREE, ``depth_gt`` too (scaling.scale_free_depth, PoseNet reading the frames
    of ``store``, the batch's FrameStore)."""
    gt = batch["target"].to(device)
    b, h, w = gt.shape
    out: dict[str, torch.Tensor] = {}
    scoring = method.kind.scored_as
    if scoring is Scoring.SCALE_FREE:
        return scale_free_depth(method.model, batch, store, device)
    if scoring is Scoring.DEPTH:
        scale = batch["translation"].norm(dim=1).to(device) / method.nominal_displacement
        raw = depth_output(method.model(batch["input"].to(device)))
        if method.depth_range is not None:
            raw = raw.clamp(*method.depth_range)
        out["depth_q"] = raw * scale.view(-1, 1, 1, 1)
        out["depth"] = metrics.upsample_to(out["depth_q"], h, w)
        return out
    if scoring is Scoring.CONSTANT:
        out["depth"] = torch.full_like(gt, method.constant)
    elif scoring is Scoring.GIVEN:
        out["depth"] = method.predictions.batch(batch["scene"], batch["frames"][:, 1]).to(device)
    elif scoring in (Scoring.FLOW, Scoring.EXACT_FLOW):
        K = batch["K"].to(device, torch.float64)
        back = -batch["translation"].to(device, torch.float64)  # second frame -> first frame
        out["gt_flow"] = flow.flow_from_depth(gt.to(torch.float64), K, back)
        if scoring is Scoring.FLOW:
            f_q = method.model(batch["input"].to(device))[0]
            f = F.interpolate(f_q, size=(h, w), mode="bilinear", align_corners=False)
            out["flow"] = f
        else:
            out["flow"] = out["gt_flow"]
            if method.flow_noise > 0:
                noise = torch.stack(
                    [
                        torch.randn(
                            (2, h, w),
                            generator=torch.Generator().manual_seed(
                                int(scene) * 1000 + int(frames[0])
                            ),
                            dtype=torch.float64,
                        )
                        for scene, frames in zip(batch["scene"], batch["frames"], strict=True)
                    ]
                )
                out["flow"] = out["gt_flow"] + method.flow_noise * noise.to(device)
        out["depth"] = flow.depth_from_flow(out["flow"].to(torch.float64), K, back).to(gt.dtype)
    else:
        raise ValueError(f"unknown scoring {scoring!r}")
    out["depth_q"] = F.adaptive_avg_pool2d(out["depth"][:, None], (h // 4, w // 4))
    return out


@dataclass
class EvalResult:
    summary: dict
    per_sample: list[dict] = field(default_factory=list)
    pixels: dict[str, np.ndarray] = field(default_factory=dict)  # subsample for plots
    samples: list[dict] = field(default_factory=list)  # a few pairs for the sample grid
    # flow methods: what their EPE was measured against, "stored" (the dataset's --flow files),
    # "computed" (flow.flow_from_depth) or "stored, computed" (some pairs each); else None
    flow_truth: str | None = None


def _to_uint8(x: torch.Tensor) -> np.ndarray:
    """Inverse of the input normalisation, (3, H, W) -> (H, W, 3) uint8."""
    img = (x.numpy().transpose(1, 2, 0) * 0.2 + 0.5) * 255.0
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _flow_truth(scenes: dict, batch: dict) -> torch.Tensor | None:
    """The dataset's stored flow of the batch's pairs (second frame -> first frame, what the
    flow networks predict), None when the dataset does not hold it (flow.stored_flow)."""
    pairs = [
        (int(k), int(f[1]), int(f[0])) for k, f in zip(batch["scene"], batch["frames"], strict=True)
    ]
    return flow.stored_flow(scenes, pairs) if scenes else None


@torch.inference_mode()
def evaluate(
    method: Method | torch.nn.Module,
    dataset,
    device: torch.device,
    batch_size: int,
    nominal_displacement: float | None = None,
    collect: bool = True,
    predictions_dir: Path | None = None,
    median_scaling: bool = False,
    plot_pixels: int = 400_000,
    grid_samples: int = 6,
) -> EvalResult:
    """Score a method (or a depth network with its ``nominal_displacement``) on an eval-mode
    PairDataset; returns aggregated and per-pair metrics (plus ``epe`` for flow methods).
    ``median_scaling``: every depth map is multiplied by median(ground truth) / median(map)
    over its valid pixels first (metrics.median_scale; the depth error's 1/4 map too)."""
    if isinstance(method, torch.nn.Module):
        method = Method(DEPTH, method, nominal_displacement)
    model = method.model
    was_training = model is not None and model.training
    if model is not None:
        model.eval()
    loader = torch.utils.data.DataLoader(dataset, batch_size=batch_size, shuffle=False)
    per_image: dict[str, list] = {}
    rows: list[dict] = []
    pix: dict[str, list] = {"gt": [], "pred": [], "abs_err": [], "foe_distance": []}
    samples: list[dict] = []
    per_pair = max(1, plot_pixels // max(1, len(dataset)))
    if predictions_dir is not None:
        runfolder.make_folder(predictions_dir)
    store = getattr(dataset, "store", None)
    scenes = {s.index: s for s in getattr(store, "scenes", [])}
    truths: set[str] = set()
    for batch in loader:
        gt = batch["target"].to(device)
        h, w = gt.shape[-2:]
        out = predict(method, batch, device, getattr(dataset, "store", None))
        if median_scaling:
            scale = metrics.median_scale(out["depth"], gt).to(out["depth"].dtype)
            out["depth"] = out["depth"] * scale.view(-1, 1, 1)
            out["depth_q"] = out["depth_q"] * scale.view(-1, 1, 1, 1).to(out["depth_q"].dtype)
        pred = out["depth"]
        m = metrics.image_metrics(pred, gt)
        m["depth_error"] = metrics.original_depth_error(out["depth_q"], gt)
        if "depth_gt" in out:  # the same depth with the ground truth's median scale
            with_gt = metrics.image_metrics(out["depth_gt"], gt)
            m.update({f"gt_{k}": v for k, v in with_gt.items() if k != "valid_pixels"})
        if "flow" in out:
            truth = _flow_truth(scenes, batch)
            truths.add("computed" if truth is None else "stored")
            truth = out["gt_flow"] if truth is None else truth.to(device)
            m.update(flow.flow_errors(out["flow"], truth))
        for k, v in m.items():
            per_image.setdefault(k, []).append(v.cpu())
        pred, gt = pred.cpu(), gt.cpu()
        for b in range(gt.shape[0]):
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
                runfolder.save_prediction(predictions_dir, scene, i2, pred[b].numpy())
                if "flow" in out:
                    f = out["flow"][b].cpu().numpy()
                    runfolder.save_flow_prediction(predictions_dir, scene, i2, i1, f)
            if not collect:
                continue
            K, t = batch["K"][b].numpy().astype(np.float64), batch["translation"][b].numpy()
            p = pred[b].clamp(metrics.MIN_DEPTH, MAX_DEPTH).numpy()
            g = np.clip(gt[b].numpy(), 0, MAX_DEPTH)
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
    if model is not None:
        model.train(was_training)
    stacked = {k: torch.cat(v).numpy() for k, v in per_image.items()}
    summary = metrics.aggregate(stacked)  # valid_pixels decides which images count
    return EvalResult(
        summary=summary,
        per_sample=rows,
        pixels={k: np.concatenate(v) for k, v in pix.items() if v},
        samples=samples,
        flow_truth=", ".join(sorted(truths, reverse=True)) or None,
    )
