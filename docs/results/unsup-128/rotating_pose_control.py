"""Usage: python docs/results/unsup-128/rotating_pose_control.py DATA [STEPS] [SCENES]

Does PoseNet learn the direction of motion of rotating sequences when the depth is true? The
chapter-5 positive control for PoseNet (tests/test_video_positive_controls.py, on stabilised
data) redone with `--pose orientation`: the dataset's rotations in the warps, PoseNet's
translations, the true depth of each window's target in the training's convention (depth × d0 /
‖τ_pair‖), no smooth term. Two windows (frames 0-4 and 8-12) of each of the first SCENES (6)
training scenes of a rotating DATA; PoseNet at 1/4 width, Adam at 1e-3, STEPS (100) steps on
that one batch. Prints the loss and the mean cosine of the translation used for each window's
reference to the true one (benchmark.unsupervised.training.pose_cosine) after every 25 steps and
after the last. One thread; about a minute at 128 px.
"""

import sys

import numpy as np
import torch

from benchmark.core.data import FrameStore, load_scenes
from benchmark.core.posenet import PoseNet
from benchmark.unsupervised.sequences import SequenceDataset
from benchmark.unsupervised.training import PhotometricStep, pose_cosine, true_translations
from stillbox_gen.conventions import NOMINAL_SHIFT

WINDOWS, WIDTH, LR, KAPPA = (0, 8), 0.25, 1e-3, 0.3  # κ unused: λ = 0


class TrueDepthPoseNet(torch.nn.Module):
    """A fresh PoseNet, and the given depth in place of DepthNet's output."""

    def __init__(self, depth: torch.Tensor, frames: int):
        super().__init__()
        self.pose = PoseNet(frames, 3, WIDTH)
        self.register_buffer("depth", depth)

    def forward(self, pair: torch.Tensor, sequence: torch.Tensor, stabilise=None):
        return [self.depth], self.pose(sequence)


def main(data: str, steps: int = 100, scenes: int = 6) -> None:
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
    net = TrueDepthPoseNet(torch.stack(depth), 5)
    opt = torch.optim.Adam(net.pose.parameters(), lr=LR)
    step = PhotometricStep(
        net, opt, torch.device("cpu"), (1.0,), d0, 0.0, KAPPA, pose="orientation"
    )
    print(f"{data}: {len(picked)} windows of {len(chosen)} scenes, --pose orientation, true depth")
    for done in range(steps + 1):  # the terms after `done` updates
        terms = step.losses(batch) if done == steps else step.update(batch)
        if done % 25 == 0 or done == steps:
            loss, cosine = float(terms["loss"].detach()), pose_cosine(batch, terms["translations"])
            print(f"after {done} steps: loss {loss:.4f}, pose cosine {cosine:.3f}")


if __name__ == "__main__":
    main(sys.argv[1], *map(int, sys.argv[2:]))
