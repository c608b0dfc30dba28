"""End-point error of predicting zero flow: the floor a flow network must beat.

Scores zero flow on the same fixed pairs (i, i + 3) and with the same exact flow and averaging as
``stillbox-bench`` (EPE per pair over pixels in front of both cameras, then the mean over pairs)::

    .venv/bin/python docs/zero_flow_epe.py data/stillbox-64 [SPLIT ...]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from benchmark.core.data import load_scenes
from benchmark.core.flow import endpoint_error, flow_from_depth
from stillbox_gen.conventions import NOMINAL_SHIFT


def zero_flow_epe(data: Path, split: str, shift: int = NOMINAL_SHIFT) -> tuple[float, int]:
    """(mean per-pair EPE of zero flow in pixels, number of pairs) of a split."""
    errors = []
    for scene in load_scenes(data, split):
        for i in range(len(scene.depth) - shift):
            depth = torch.from_numpy(scene.load_depth(i + shift).astype(np.float64))
            back = -torch.from_numpy(scene.translation(i, i + shift))  # second frame -> first
            gt = flow_from_depth(depth[None], torch.from_numpy(scene.K)[None], back[None])
            errors.append(endpoint_error(torch.zeros_like(gt), gt).item())
    return float(np.mean(errors)), len(errors)


if __name__ == "__main__":
    root = Path(sys.argv[1])
    for name in sys.argv[2:] or ["val", "test"]:
        epe, pairs = zero_flow_epe(root, name)
        print(f"{root} {name}: zero-flow EPE {epe:.3f} px over {pairs} pairs")
