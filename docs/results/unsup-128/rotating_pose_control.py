"""Usage: python docs/results/unsup-128/rotating_pose_control.py DATA [STEPS] [SCENES] [CKPT]

Does PoseNet learn the direction of motion of rotating sequences when the depth is true? The
chapter-5 positive control for PoseNet (tests/test_video_positive_controls.py, on stabilised
data) redone with `--pose orientation`: the dataset's rotations in the warps, PoseNet's
translations, the true depth of each window's target in the training's convention (depth × d0 /
‖τ_pair‖), no smooth term. Two windows (frames 0-4 and 8-12) of each of the first SCENES (6)
training scenes of a rotating DATA; PoseNet at 1/4 width, Adam at 1e-3, STEPS (100) steps on
that one batch. Prints the loss and the mean cosine of the translation used for each window's
reference to the true one (benchmark.unsupervised.training.pose_cosine) after every 25 steps and
after the last. With CKPT (a supervised depthnet checkpoint), the depth is that network's instead of
the truth, frozen (eval mode) and reading the pair stabilised with the known rotations, as
`run depthnet-unsup --pretrained CKPT --pose-warmup` trains PoseNet against it. One thread;
about a minute at 128 px. POSE_WIDTH and POSE_LR (environment) replace the width (0.25) and
Adam's learning rate (1e-3), e.g. 1 and 2e-4: the full-width PoseNet at the recipe's rate.
"""

import os
import sys

import numpy as np
import torch

from benchmark.core import registry
from benchmark.core.checkpoint import load_checkpoint, load_weights
from benchmark.core.data import FrameStore, load_scenes
from benchmark.core.posenet import PoseNet
from benchmark.unsupervised.sequences import SequenceDataset
from benchmark.unsupervised.training import PhotometricStep, pose_cosine, true_translations
from stillbox_gen.conventions import NOMINAL_SHIFT

WINDOWS, KAPPA = (0, 8), 0.3  # κ unused: λ = 0
WIDTH, LR = float(os.environ.get("POSE_WIDTH", 0.25)), float(os.environ.get("POSE_LR", 1e-3))


class TrueDepthPoseNet(torch.nn.Module):
    """A fresh PoseNet, and the given depth in place of DepthNet's output."""

    def __init__(self, depth: torch.Tensor, frames: int):
        super().__init__()
        self.pose = PoseNet(frames, 3, WIDTH)
        self.register_buffer("depth", depth)

    def forward(self, pair: torch.Tensor, sequence: torch.Tensor, stabilise=None):
        return [self.depth], self.pose(sequence)


class FrozenDepthPoseNet(torch.nn.Module):
    """A fresh PoseNet, and a trained DepthNet's finest output (frozen) for the stabilised pair."""

    def __init__(self, depth: torch.nn.Module, frames: int):
        super().__init__()
        self.pose = PoseNet(frames, 3, WIDTH)
        self.depth = depth.eval().requires_grad_(False)

    def forward(self, pair: torch.Tensor, sequence: torch.Tensor, stabilise=None):
        poses = self.pose(sequence)
        out = self.depth(pair if stabilise is None else stabilise(pair, poses))
        return [out[0] if isinstance(out, (list, tuple)) else out], poses


def main(data: str, steps: int = 100, scenes: int = 6, ckpt: str | None = None) -> None:
    torch.set_num_threads(1)
    chosen = load_scenes(data, "train", rotations=True)[:scenes]
    sequences = SequenceDataset(FrameStore(chosen, progress=False), 5, seed=0)
    picked = [i for i, (_, first) in enumerate(sequences.items) if first in WINDOWS]
    batch = sequences.batch(picked, 0)
    d0 = NOMINAL_SHIFT * chosen[0].displacement
    tau, depth = true_translations(batch), []
    for j, i in enumerate(picked):
        k, first = sequences.items[i]
        target, ref = first + int(batch["target_index"][j]), int(batch["reference_index"][j])
        scaled = chosen[k].load_depth(target) * d0 / float(tau[j, ref].norm())
        depth.append(torch.from_numpy(scaled.astype(np.float32))[None])
    torch.manual_seed(0)
    if ckpt is None:
        net, source = TrueDepthPoseNet(torch.stack(depth), 5), "true depth"
    else:
        ck = load_checkpoint(ckpt)
        depth_net = registry.build_model(ck["model_name"])
        load_weights(depth_net, ck, None, ckpt, ck["model_name"])
        net, source = FrozenDepthPoseNet(depth_net, 5), f"depth of {ckpt}"
    opt = torch.optim.Adam(net.pose.parameters(), lr=LR)
    step = PhotometricStep(
        net, opt, torch.device("cpu"), (1.0,), d0, 0.0, KAPPA, pose="orientation"
    )
    print(
        f"{data}: {len(picked)} windows of {len(chosen)} scenes, --pose orientation, {source}, "
        f"PoseNet width {WIDTH:g}, Adam {LR:g}"
    )
    for done in range(steps + 1):  # the terms after `done` updates
        terms = step.losses(batch) if done == steps else step.update(batch)
        if done % 25 == 0 or done == steps:
            loss, cosine = float(terms["loss"].detach()), pose_cosine(batch, terms["translations"])
            print(f"after {done} steps: loss {loss:.4f}, pose cosine {cosine:.3f}")


if __name__ == "__main__":
    main(sys.argv[1], *map(int, sys.argv[2:4]), *sys.argv[4:5])
