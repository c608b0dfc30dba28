"""Usage:
    python docs/results/unsup-128/pose_generalisation.py DATA [STEPS] [LR] [EVERY] [stabilised]

Does PoseNet learn the direction of motion over a whole training split, and does the direction
hold on unseen scenes? rotating_pose_control.py trains on one fixed batch of 12 windows; here a
fresh full-width PoseNet (--pose orientation: the dataset's rotations in the warps, PoseNet's
translations) trains on random batches of 16 windows of the training split of a rotating DATA,
STEPS (600) steps of Adam at LR (2e-4, the recipe's), against the true depth of each window's
target in the training's convention (depth × d0 / ‖τ_pair‖), without the smooth term. Every
EVERY (100) steps it prints the mean cosine to the true direction over the last EVERY training
batches, and over 64 fixed windows of the test split (no update). With ``stabilised``, PoseNet
reads every frame turned to the last frame's orientation by the known rotation (eq. 5.1), and
its translations are turned back to each frame's axes, the warps' convention. One thread; about
9 minutes for 600 steps at 128 px.
"""

import sys
import time

import numpy as np
import torch

from benchmark.core.data import NORM_MEAN, NORM_STD, FrameStore, load_scenes
from benchmark.core.posenet import PoseNet
from benchmark.unsupervised.reprojection import rotate_frame
from benchmark.unsupervised.sequences import SequenceDataset
from benchmark.unsupervised.training import PhotometricStep, pose_cosine, true_translations
from stillbox_gen.conventions import NOMINAL_SHIFT

BATCH, TEST_WINDOWS, LENGTH, KAPPA = 16, 64, 5, 0.3  # κ unused: λ = 0


class TrueDepthPoseNet(torch.nn.Module):
    """A fresh PoseNet, and each batch's true depth (``depth``) in place of DepthNet's output.
    ``turns`` (B, N, 3, 3): R_{last→i} when PoseNet reads stabilised frames, else None."""

    def __init__(self):
        super().__init__()
        self.pose = PoseNet(LENGTH, 3, 1.0)
        self.depth: torch.Tensor | None = None
        self.turns: torch.Tensor | None = None

    def forward(self, pair: torch.Tensor, sequence: torch.Tensor, stabilise=None):
        poses = self.pose(sequence)
        if self.turns is not None:  # read in the last frame's axes, τ_i = R_{last→i}·s_i
            poses = (self.turns @ poses.unsqueeze(-1)).squeeze(-1)
        return [self.depth], poses


def stabilised(batch: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """PoseNet's input with every frame turned to the last frame's orientation, and R_{last→i}."""
    frames, rotation, K = batch["frames"], batch["rotation"], batch["K"]
    b, n, _, h, w = frames.shape
    turns = rotation @ rotation[:, -1:].transpose(-1, -2)  # R_{t→i}·R_{t→last}ᵀ
    image, valid = rotate_frame(
        frames.reshape(b * n, 3, h, w), turns.reshape(-1, 3, 3), K.repeat_interleave(n, 0)
    )
    normalised = torch.where(valid, (image - NORM_MEAN) / NORM_STD, torch.zeros_like(image))
    return normalised.reshape(b, n * 3, h, w), turns


class Windows:
    """Batches of one split's windows with their true depth (the training convention)."""

    def __init__(self, data: str, split: str, stabilise: bool):
        self.scenes = load_scenes(data, split, rotations=True)
        self.data = SequenceDataset(FrameStore(self.scenes, progress=False), LENGTH, seed=0)
        self.d0 = NOMINAL_SHIFT * self.scenes[0].displacement
        self.stabilise = stabilise

    def __len__(self) -> int:
        return len(self.data)

    def load(self, net: TrueDepthPoseNet, indices: list[int], epoch: int) -> dict:
        batch = self.data.batch(indices, epoch)
        tau, depth = true_translations(batch), []
        for j, i in enumerate(indices):
            k, first = self.data.items[i]
            target = first + int(batch["target_index"][j])
            ref = int(batch["reference_index"][j])
            scaled = self.scenes[k].load_depth(target) * self.d0 / float(tau[j, ref].norm())
            depth.append(torch.from_numpy(scaled.astype(np.float32))[None])
        net.depth, net.turns = torch.stack(depth), None
        if self.stabilise:
            batch["sequence"], net.turns = stabilised(batch)
        return batch


def main(data: str, steps: int = 600, lr: float = 2e-4, every: int = 100, *how: str) -> None:
    torch.set_num_threads(1)
    stabilise = "stabilised" in how
    train, test = Windows(data, "train", stabilise), Windows(data, "test", stabilise)
    rng = np.random.default_rng(0)
    held_out = rng.choice(len(test), min(TEST_WINDOWS, len(test)), replace=False).tolist()
    torch.manual_seed(0)
    net = TrueDepthPoseNet()
    opt = torch.optim.Adam(net.pose.parameters(), lr=lr)
    step = PhotometricStep(net, opt, torch.device("cpu"), (1.0,), train.d0, 0.0, KAPPA,
                           pose="orientation")  # fmt: skip

    def test_cosine() -> float:
        cosines = []
        with torch.no_grad():
            for c in range(0, len(held_out), BATCH):
                batch = test.load(net, held_out[c : c + BATCH], 0)
                cosines.append(pose_cosine(batch, step.losses(batch)["translations"]))
        return float(np.mean(cosines))

    reads = "frames stabilised to the last one" if stabilise else "the rotating frames"
    print(
        f"{data}: {len(train)} training windows of {len(train.scenes)} scenes, "
        f"{len(held_out)} test windows of {len(test.scenes)} scenes; PoseNet width 1 reading "
        f"{reads}, Adam {lr:g}, true depth"
    )
    print(f"after 0 steps: test cosine {test_cosine():.3f}")
    start, seen = time.perf_counter(), []
    for done in range(1, steps + 1):
        drawn = rng.choice(len(train), min(BATCH, len(train)), replace=False).tolist()
        batch = train.load(net, drawn, done)
        seen.append(pose_cosine(batch, step.update(batch)["translations"]))
        if done % every == 0 or done == steps:
            print(
                f"after {done} steps: training cosine {np.mean(seen[-every:]):.3f}, test cosine "
                f"{test_cosine():.3f} ({time.perf_counter() - start:.0f} s)",
                flush=True,
            )


if __name__ == "__main__":
    args = sys.argv[1:]
    numbers = [t(a) for t, a in zip((int, float, int), args[1:4], strict=False)]
    main(args[0], *numbers, *args[4:])
