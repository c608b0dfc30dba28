"""Usage: python docs/results/finetune/loss_floor.py DATA [CKPT ...]

The training loss a fine-tuning can reach, and where checkpoints stand on it. On 64 training
sequences of DATA (a stabilised stillbox-gen dataset; 5 frames, the targets and references
``finetune`` draws in its first epoch), eq. 5.5's terms as ``finetune --known-motion`` computes
them (PhotometricStep, the known motion, d0 = 0.3 m, λ = 0.003 for the smooth column) for:

- the true depth through DepthNet's five output scales (area-downsampled from 1/4 of the frame:
  the floor of the photometric term, since the finest output is upsampled from 1/4), × 2, × 0.5;
- each CKPT's depth network (eval mode, BatchNorm on its running statistics), with the median
  over samples of the median ratio of its finest depth (upsampled) to the truth.

One thread; about a minute.
"""

import sys

import torch
import torch.nn.functional as F

from benchmark.core import registry
from benchmark.core.checkpoint import load_checkpoint
from benchmark.core.data import FrameStore, load_scenes
from benchmark.unsupervised.sequences import SequenceDataset
from benchmark.unsupervised.training import PhotometricStep, smooth_settings

D0 = 0.3  # metres: DepthNet's nominal displacement on StillBox (3 frames of 0.1 m)
LAMBDA, KAPPA = smooth_settings(None, None, False)  # depthnet-unsup's
SAMPLES = 64


class _Known(torch.nn.Module):
    """Answers a fixed depth map through DepthNet's scales (1/4 to 1/64) and no poses."""

    def __init__(self, depth: torch.Tensor):
        super().__init__()
        self.depth = depth

    def forward(self, pair, sequence):
        h, w = self.depth.shape[-2:]
        scales = [F.adaptive_avg_pool2d(self.depth, (h >> s, w >> s)) for s in range(2, 7)]
        return scales, torch.zeros(len(pair), sequence.shape[1] // 3, 3)


class _Depth(torch.nn.Module):
    """A depth network in PhotometricStep's (depths, poses) form (poses unused: known motion)."""

    def __init__(self, net: torch.nn.Module):
        super().__init__()
        self.net = net

    def forward(self, pair, sequence):
        return self.net(pair), torch.zeros(len(pair), sequence.shape[1] // 3, 3)


def terms(net: torch.nn.Module, batch: dict) -> tuple[float, float]:
    """(photometric, smooth) of eq. 5.5 for ``net`` on ``batch``."""
    weights = registry.UNSUPERVISED_RECIPE.loss_weights
    step = PhotometricStep(
        net, None, torch.device("cpu"), weights, D0, LAMBDA, KAPPA, known_translation=True
    )
    with torch.no_grad():
        out = step.losses(batch)
    return float(out["photometric"]), float(out["smooth"])


def main(data: str, ckpts: list[str]) -> None:
    torch.set_num_threads(1)
    seqs = SequenceDataset(FrameStore(load_scenes(data, "train"), progress=False), 5)
    indices = list(range(0, len(seqs), max(1, len(seqs) // SAMPLES)))[:SAMPLES]
    batch = seqs.batch(indices, 0)
    depths = []
    for j, i in enumerate(indices):
        k, first, t, r = seqs.draw(i, 0)
        scale = D0 / float(batch["translation"][j][r].norm())  # the reference at d0
        depths.append(torch.from_numpy(seqs.store.depth(k, first + t)) * scale)
    truth = torch.stack(depths).unsqueeze(1).clamp(max=1e4)
    print(f"{data}: {len(indices)} training sequences; photometric, smooth (λ = {LAMBDA})")
    for name, depth in (("truth", truth), ("truth x 2", truth * 2), ("truth x 0.5", truth / 2)):
        photo, smooth = terms(_Known(depth), batch)
        print(f"{name:40s} {photo:.4f} {smooth:.4f}")
    for path in ckpts:
        ck = load_checkpoint(path)
        net = registry.build_model(ck["model_name"])
        net.load_state_dict(ck["model"])
        net.eval()
        photo, smooth = terms(_Depth(net), batch)
        with torch.no_grad():
            finest = net(batch["input"])[0]
        up = F.interpolate(finest, size=truth.shape[-2:], mode="bilinear", align_corners=False)
        ratio = float((up / truth).flatten(1).median(1).values.median())
        print(f"{path:40s} {photo:.4f} {smooth:.4f}  median depth / truth {ratio:.2f}")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        raise SystemExit(__doc__)
    main(sys.argv[1], sys.argv[2:])
