"""The depth of one frame from n pairs (thesis chapter 6, Fig. 6.4): the network's outputs for
the pairs (I_{t−δ_i}, I_t), each scaled by its pair's displacement d(t, δ_i) (eq. 6.1) and fused
(eq. 6.3, core.multishift.fuse), the shifts δ_i (frames) chosen by core.multishift.ShiftPlanner.
Depth in metres belongs to frame t, the later frame of each pair. Used by ``infer``'s frame loop
(benchmark.video.infer), ``eval-multishift`` and the closed-loop flight's depth sources.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..core.data import normalise
from ..core.metrics import upsample_to
from ..core.multishift import ShiftPlanner, fuse


@torch.no_grad()
def network_outputs(
    model: torch.nn.Module,
    clamp: tuple[float, float] | None,
    device: torch.device,
    frames: Sequence[np.ndarray],
    shifts: list[int],
) -> torch.Tensor:
    """Network outputs (n, H, W) at the frames' resolution (m, for the nominal displacement) of
    the pairs (frame t − δ, frame t), δ in ``shifts``; ``frames[-1]`` is frame t, ``frames[-1 - δ]``
    frame t − δ ((H, W, 3) uint8 RGB). One batch; clamped to ``clamp`` (a clamped network's range,
    m) when given."""
    current = normalise(frames[-1])
    x = np.stack([np.concatenate([normalise(frames[-1 - s]), current]) for s in shifts])
    out = model(torch.from_numpy(x).to(device))[0]
    if clamp is not None:
        out = out.clamp(*clamp)
    h, w = frames[-1].shape[:2]
    return upsample_to(out, h, w).float().cpu()  # .cpu() waits for a GPU


@dataclass
class FrameDepth:
    """One frame's fused depth: the shifts used (frames), their displacements d* (m), the
    targets d_opt they were chosen for (m), the depth (H, W) m and its saturated pixels."""

    shifts: list[int]
    displacements: list[float]
    targets: list[float]
    depth: torch.Tensor
    saturated: torch.Tensor
    network_s: float  # seconds spent in the network


def frame_depth(
    planner: ShiftPlanner, available: np.ndarray, outputs: Callable[[list[int]], torch.Tensor]
) -> FrameDepth | None:
    """One step of the frame loop (thesis Fig. 6.4): the planner's shifts among ``available``
    (``available[k]`` = d(t, k + 1), m), the network ``outputs(shifts)`` (n, H, W), their fusion,
    and the planner's update. None when no shift has any motion (hovering: depth undefined)."""
    target = [planner.scale.d0] if planner.d_opt is None else [float(v) for v in planner.d_opt]
    if not (available > 0).any():
        return None
    shifts = [s for s in planner.plan(available) if available[s - 1] > 0]
    if not shifts:
        return None
    tick = time.perf_counter()
    out = outputs(shifts)
    network_s = time.perf_counter() - tick
    d = [float(available[s - 1]) for s in shifts]
    depth, saturated = fuse(out, d, planner.scale, planner.beta_mean)
    planner.update(depth, saturated)
    return FrameDepth(shifts, d, target, depth, saturated, network_s)
