"""Depth sources of the closed loop (simulate.DepthSource): a depth network through the ``infer``
pipeline, a flow network through ``compare``'s flow-to-depth geometry, and the error of any
source against the rendered depth on the frames it saw.

Every source gets the frames so far (RGB uint8, oldest first, the current one last), the current
frame's true depth (used by ``oracle`` only, and by :class:`Scored` to score) and the frames'
OpenCV camera-to-world poses; it returns planar depth (H, W) in metres. The displacement between
two frames is measured from their poses (as ``infer --poses``), never from the true depth. A
frame a network cannot answer (the first one, or no motion since the earlier frames: hovering)
gets :data:`UNSEEN` everywhere: no obstacle point, and it is not scored.

A stateful source (the network's shift planner) has ``reset()``, called before each episode.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..core import metrics, registry
from ..core.checkpoint import load_checkpoint, load_weights, source_error
from ..core.data import normalise
from ..core.multishift import EMA_LAMBDA, ShiftPlanner, closest_shift, displacements
from ..engine.evaluate import Method
from ..engine.evaluate import predict as predict_depth
from ..engine.frame_depth import frame_depth, network_outputs
from ..engine.network import depth_network
from .obstacles import SensingConfig
from .simulate import DepthSource
from .summary import ERROR_KEYS

UNSEEN = np.inf  # metres: a pixel without depth (no obstacle point, obstacles.camera_points)


def positions_of(poses: Sequence[np.ndarray]) -> np.ndarray:
    """Camera centres (frames, 3), metres, of OpenCV camera-to-world poses."""
    return np.array([np.asarray(p)[:3, 3] for p in poses], dtype=float)


def unseen(shape: tuple[int, ...]) -> np.ndarray:
    """A depth map without any depth (H, W)."""
    return np.full(shape, UNSEEN, np.float32)


class NetworkDepth:
    """A depth network's checkpoint (``kind`` depth in the registry) as ``infer`` runs it: per
    frame the :class:`~benchmark.core.multishift.ShiftPlanner`'s ``shifts`` pairs
    (frame t - shift, frame t), the displacements |p_t - p_{t-shift}| (m) from the poses, the
    network's outputs scaled and fused (benchmark.engine.frame_depth). Shifts reach back at most
    as far as the frames the loop keeps (simulate.HISTORY - 1)."""

    def __init__(
        self,
        ckpt: str | Path,
        device: torch.device,
        shifts: int = 1,
        ema: float = EMA_LAMBDA,
        **planner,
    ) -> None:
        self.model, self.scale, self.info = depth_network(ckpt, "depth")
        self.model.to(device)
        self.device, self.shifts, self.ema, self.planner_options = device, shifts, ema, planner
        self.reset()

    def reset(self) -> None:
        """A new episode: the shift planner starts again from the nominal displacement."""
        self.planner = ShiftPlanner(self.shifts, self.scale, self.ema, **self.planner_options)

    def __call__(self, rgbs, true_depth, poses) -> np.ndarray:
        if len(rgbs) < 2:
            return unseen(true_depth.shape)
        available = displacements(positions_of(poses), len(poses) - 1, len(poses) - 1)
        net = (self.model, self.info["clamp"], self.device)
        est = frame_depth(self.planner, available, lambda s: network_outputs(*net, rgbs, s))
        return unseen(true_depth.shape) if est is None else est.depth.numpy()


class FlowDepth:
    """A flow network's checkpoint (``kind`` flow: FlowNetS) turned into depth exactly as
    ``compare`` scores ``flownets-flow`` (engine.evaluate.predict: the flow upsampled to the
    frame, then core.flow.depth_from_flow with the pair's known translation, clamped to
    [MIN_DEPTH, MAX_DEPTH]). The pair is (frame t - shift, frame t), the shift whose displacement
    is closest to the checkpoint's nominal displacement; the translation is measured from the
    poses, in frame t's camera axes (the camera is stabilised: same orientation)."""

    def __init__(self, ckpt: str | Path, device: torch.device, K: np.ndarray) -> None:
        ck = load_checkpoint(ckpt, "depth")
        name = ck["model_name"]
        kind = registry.MODELS[name].kind
        if kind.scored_as is not registry.Scoring.FLOW:
            raise source_error("depth", ckpt, f"'{name}' predicts {kind.name}, not flow")
        model = registry.build_model(name)
        load_weights(model, ck, "depth", ckpt, name)
        self.method = Method(kind, model.to(device).eval())
        self.d0 = float(ck["nominal_displacement"])
        self.device, self.K = device, torch.as_tensor(np.asarray(K, float))[None]
        self.info = {"model_name": name, "nominal_displacement_m": self.d0}

    @torch.no_grad()
    def __call__(self, rgbs, true_depth, poses) -> np.ndarray:
        if len(rgbs) < 2:
            return unseen(true_depth.shape)
        positions = positions_of(poses)
        available = displacements(positions, len(poses) - 1, len(poses) - 1)
        if not (available > 0).any():
            return unseen(true_depth.shape)
        shift = closest_shift(self.d0, available)
        forward = np.asarray(poses[-1])[:3, :3].T @ (positions[-1] - positions[-1 - shift])
        x = np.concatenate([normalise(rgbs[-1 - shift]), normalise(rgbs[-1])])
        batch = {
            "input": torch.from_numpy(x)[None],
            "target": torch.from_numpy(np.asarray(true_depth, np.float32))[None],
            "K": self.K,
            "translation": torch.from_numpy(forward)[None],
        }
        return predict_depth(self.method, batch, self.device)["depth"][0].float().cpu().numpy()


@dataclass
class Scored:
    """A depth source whose answers are scored against the rendered depth (core.metrics: MAE in
    metres, MRE; predictions clamped to [MIN_DEPTH, MAX_DEPTH], truth clipped to MAX_DEPTH) on
    the frames where it gave depth (not :data:`UNSEEN`), per episode, over every pixel and
    within ``near_range`` (m: the sensing range, obstacles.SensingConfig.max_range; see
    :data:`ERROR_KEYS`). The frames are kept and scored by :meth:`errors`, so that the time of a
    call is the source's alone."""

    source: DepthSource
    near_range: float = SensingConfig.max_range
    frames: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)

    def reset(self) -> None:
        """A new episode."""
        self.frames = []
        if hasattr(self.source, "reset"):
            self.source.reset()

    def __call__(self, rgbs, true_depth, poses) -> np.ndarray:
        depth = self.source(rgbs, true_depth, poses)
        if np.isfinite(depth).any():
            self.frames.append((np.asarray(depth, np.float32), np.asarray(true_depth, np.float32)))
        return depth

    def errors(self) -> dict:
        """This episode's ``depth_frames`` scored (frames with a valid pixel) and the mean of
        each :data:`ERROR_KEYS` over them (None without any; a frame with no pixel of a kind
        does not count in that kind's mean)."""
        if not self.frames:
            return {"depth_frames": 0} | dict.fromkeys(ERROR_KEYS)
        pred, gt = (torch.from_numpy(np.stack(a)) for a in zip(*self.frames, strict=True))
        m = metrics.image_metrics(pred, gt, sensing_range=self.near_range)
        kept = m["valid_pixels"] > 0
        near_gt = torch.where(gt <= self.near_range, gt, torch.nan)  # far pixels invalid
        per_frame = {
            "depth_mae_m": m["mae"],
            "depth_mre": m["mre"],
            "near_mae_m": metrics.image_metrics(pred, near_gt)["mae"],
            "missed_near": m["missed_near"],
            "phantom_near": m["phantom_near"],
        }
        out = {"depth_frames": int(kept.sum())}
        for key, values in per_frame.items():
            values = values[kept]
            values = values[~torch.isnan(values)]
            out[key] = float(values.mean()) if len(values) else None
        return out
