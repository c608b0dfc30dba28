"""Usage: python docs/results/finetune/photometric_landscape.py DATA [MAX_GAP] [TARGET]

Where is the minimum of the photometric loss that fine-tuning descends? For every scene of a
stabilised stillbox-gen dataset, frame TARGET (default 4) is the target and every frame up to
MAX_GAP (default 4) frames away on either side a reference. Each reference is warped to the
target with a candidate depth map and the true camera motion (so the pose is not in question),
and the loss is eq. 5.3's per-pixel L1 + DSSIM (α = 0.15) averaged over the pixels the warp
keeps, as ``finetune --known-motion`` computes it (benchmark.unsupervised.training). The
candidates are the true depth and perturbations of it (a scale, the depths beyond 20 m moved,
noise, blur, a constant, the truth at DepthNet's 1/4 resolution); the table prints each one's
MAE against the truth and its loss per gap, with the difference to the truth's loss. A negative
difference means the loss prefers the wrong depth to the truth: descending it moves depth away
from the truth there.

Depth is clipped to 100 m (the metrics' range). One thread; a few seconds for 12 scenes.
"""

import sys

import numpy as np
import torch
import torch.nn.functional as F

from benchmark.unsupervised.reprojection import (
    SSIM_WEIGHT,
    inverse_warp,
    masked_mean,
    photometric_map,
)
from stillbox_gen.dataset import Dataset

#: metres: the depths the "far" candidates move
KNEE = 20.0


def frame(scene, f: int) -> torch.Tensor:
    """(3, H, W) float32 in [0, 1]."""
    return torch.from_numpy(scene.load_rgb(f).astype(np.float32) / 255).permute(2, 0, 1)


def pairs(data: str, max_gap: int, target: int) -> dict[str, torch.Tensor]:
    """Every (target, reference) pair of the dataset's stabilised scenes, stacked."""
    rows: dict[str, list] = {k: [] for k in ("target", "depth", "reference", "move", "K", "gap")}
    for scene in Dataset(data).scenes():
        if not scene.stabilised:
            raise SystemExit(f"{data}: scene {scene.index} rotates; this needs stabilised scenes")
        depth = torch.from_numpy(scene.load_depth(target).astype(np.float32))[None]
        for gap in range(1, max_gap + 1):
            for ref in (target - gap, target + gap):
                if 0 <= ref < scene.frames:
                    rows["target"].append(frame(scene, target))
                    rows["depth"].append(depth.clamp(max=100.0))
                    rows["reference"].append(frame(scene, ref))
                    # X_ref = X_target − T, T the camera's displacement (target axes)
                    move = scene.translation(target, ref).astype(np.float32)
                    rows["move"].append(-torch.from_numpy(move))
                    rows["K"].append(torch.from_numpy(np.asarray(scene.K, np.float32)))
                    rows["gap"].append(torch.tensor(gap))
    if not rows["gap"]:
        raise SystemExit(f"{data}: no scene has frame {target} and a reference")
    return {k: torch.stack(v) for k, v in rows.items()}


def losses(p: dict[str, torch.Tensor], depth: torch.Tensor) -> torch.Tensor:
    """(pairs,) eq. 5.3 loss of each pair with ``depth`` (pairs, 1, H, W) metres."""
    warped, valid = inverse_warp(p["reference"], depth, None, p["move"], p["K"])
    return masked_mean(photometric_map(p["target"], warped, SSIM_WEIGHT), valid)


def candidates(truth: torch.Tensor) -> dict[str, torch.Tensor]:
    """The true depth and perturbations of it, (pairs, 1, H, W) metres each."""
    noise = torch.randn(truth.shape, generator=torch.Generator().manual_seed(0))
    far = truth > KNEE

    def blur(k: int) -> torch.Tensor:
        return F.avg_pool2d(truth, k, 1, k // 2, count_include_pad=False)

    def far_scaled(s: float) -> torch.Tensor:
        return torch.where(far, KNEE + (truth - KNEE) * s, truth).clamp(max=100.0)

    median = truth.flatten(1).median(1).values.view(-1, 1, 1, 1)
    # DepthNet's finest output is 1/4 of the frame, upsampled bilinearly for the warp (§4.7.1)
    quarter = F.interpolate(
        F.avg_pool2d(truth, 4), size=truth.shape[-2:], mode="bilinear", align_corners=False
    )
    return {
        "truth": truth,
        "truth x0.8": truth * 0.8,
        "truth x1.1": truth * 1.1,
        "truth x1.25": truth * 1.25,
        "beyond 20 m: x0.5": far_scaled(0.5),
        "beyond 20 m: x1.5": far_scaled(1.5),
        "beyond 20 m: x3": far_scaled(3.0),
        "beyond 20 m: 100 m": torch.where(far, torch.full_like(truth, 100.0), truth),
        "beyond 20 m: 20 m": truth.clamp(max=KNEE),
        "below 10 m: x1.3": torch.where(truth < 10, truth * 1.3, truth),
        "log-normal noise 0.1": truth * torch.exp(0.1 * noise),
        "log-normal noise 0.3": truth * torch.exp(0.3 * noise),
        "blur 3x3": blur(3),
        "blur 5x5": blur(5),
        "median constant": median.expand_as(truth),
        "truth at 1/4 resolution": quarter,
        "truth at 1/4 resolution x1.5": quarter * 1.5,
        "truth at 1/4 resolution x3": quarter * 3,
    }


def main(data: str, max_gap: str = "4", target: str = "4") -> None:
    torch.set_num_threads(1)
    p = pairs(data, int(max_gap), int(target))
    gaps = sorted(set(p["gap"].tolist()))
    size = "x".join(str(n) for n in p["target"].shape[-2:][::-1])
    print(f"{data}: {len(p['gap'])} (target, reference) pairs, {size} px, target frame {target}")
    print("| depth | MAE m | " + " | ".join(f"gap {g}: loss (vs truth)" for g in gaps) + " |")
    print("|---" * (2 + len(gaps)) + "|")
    base: dict[int, float] = {}
    for name, depth in candidates(p["depth"]).items():
        per = losses(p, depth)
        cells = []
        for g in gaps:
            value = per[p["gap"] == g].mean().item()
            base.setdefault(g, value)  # the first candidate is the truth
            cells.append(f"{value:.4f} ({value - base[g]:+.4f})")
        mae = (depth - p["depth"]).abs().mean().item()
        print(f"| {name} | {mae:.2f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(*sys.argv[1:])
