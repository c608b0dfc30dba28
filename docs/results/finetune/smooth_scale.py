"""Usage: python docs/results/finetune/smooth_scale.py DATA [SCENES]

How large is eq. 5.5's smooth term on the true depth, and does it prefer the truth pushed far?
For SCENES scenes (default 16) of a stillbox-gen dataset, frame 4's true depth (clipped to
100 m) is area-downsampled to DepthNet's five output scales (1/4 to 1/64 of the frame), and the
smooth term Σ_s w_s·L_gdiff(ξ_s, I_s, κ) (depthnet-unsup's w_s = 1/2^s and κ = 0.3, I_s the
frame downsampled alike) is printed for two inverse depths:

- ``raw``: ξ = 1/θ as it is (the loss before 2026-12-03);
- ``normalised``: ξ divided by its mean over the map (per sample), so that scaling every depth by
  one factor leaves the term unchanged (the convention of Godard et al.'s Monodepth2).

for the truth, the truth × 2, and the truth with every pixel beyond 20 m moved to 100 m. The
ratio raw / normalised on the truth is what keeps λ·L_s at the same share of the photometric loss
when the normalised term replaces the raw one (SMOOTH_SCALE in benchmark.unsupervised.training).
One thread; a few seconds.
"""

import sys

import numpy as np
import torch
import torch.nn.functional as F

from benchmark.core.registry import UNSUPERVISED_RECIPE
from benchmark.unsupervised.reprojection import gradient_diffusion_loss
from benchmark.unsupervised.training import mean_normalised, smooth_settings
from stillbox_gen.dataset import Dataset

KAPPA = smooth_settings(None, None, False)[1]  # depthnet-unsup's κ
WEIGHTS = UNSUPERVISED_RECIPE.loss_weights  # w_s, finest (1/4 of the frame) first


def term(depth: torch.Tensor, image: torch.Tensor, normalise: bool) -> torch.Tensor:
    """(B,) Σ_s w_s·L_gdiff over DepthNet's scales of ``depth`` (B, 1, H, W) metres."""
    total = torch.zeros(depth.shape[0])
    h = depth.shape[-1]
    for s, weight in enumerate(WEIGHTS):
        size = max(h // 4 // 2**s, 1)
        if size < 3:
            continue
        xi = 1 / F.adaptive_avg_pool2d(depth, size)
        xi = mean_normalised(xi) if normalise else xi
        total += weight * gradient_diffusion_loss(xi, F.adaptive_avg_pool2d(image, size), KAPPA)
    return total


def main(data: str, count: int) -> None:
    torch.set_num_threads(1)
    depths, images = [], []
    for scene in list(Dataset(data).scenes())[:count]:
        depths.append(torch.from_numpy(scene.load_depth(4).astype(np.float32))[None])
        rgb = scene.load_rgb(4).astype(np.float32) / 255
        images.append(torch.from_numpy(rgb).permute(2, 0, 1))
    truth, image = torch.stack(depths).clamp(max=100.0), torch.stack(images)
    cases = {
        "truth": truth,
        "truth x 2": (truth * 2).clamp(max=100.0),
        "beyond 20 m -> 100 m": torch.where(truth > 20, torch.full_like(truth, 100.0), truth),
    }
    print(f"{data}: {len(truth)} scenes, frame 4, {truth.shape[-1]} px")
    print(f"{'candidate':24s} {'raw':>10s} {'normalised':>11s}")
    for name, depth in cases.items():
        raw, norm = term(depth, image, False).mean(), term(depth, image, True).mean()
        print(f"{name:24s} {raw:10.5f} {norm:11.5f}")
    raw, norm = term(truth, image, False).mean(), term(truth, image, True).mean()
    print(f"truth raw / normalised: {raw / norm:.5f}")


if __name__ == "__main__":
    if len(sys.argv) not in (2, 3):
        raise SystemExit(__doc__)
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) == 3 else 16)
