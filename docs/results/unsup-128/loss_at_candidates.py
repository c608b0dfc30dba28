"""Usage: python docs/results/unsup-128/loss_at_candidates.py DATA CKPT [SCENES] [SAMPLES]

Where does `run depthnet-unsup`'s training loss (eq. 5.5: photometric + smooth, every scale,
the recipe's λ and κ) have its minimum, and how far is a checkpoint from it? On SAMPLES (64)
training windows of the first SCENES (60) training scenes of DATA, drawn as the first epoch
draws them, the loss is computed exactly as training computes it
(benchmark.unsupervised.training.PhotometricStep) for candidate depth maps (the true depth at
the nominal displacement, perturbations of it, constants) and for the checkpoint's own depth,
each with two camera motions: the true one (from the dataset's poses) and the checkpoint's
PoseNet's translations (with the known rotations on rotating data, as `--pose orientation`).
A candidate whose loss is below the truth's is preferred by training to the truth.
Prints a markdown table. One thread; a few minutes at 128 px.
"""

import sys

import torch
import torch.nn.functional as F

from benchmark.core import registry
from benchmark.core.checkpoint import load_checkpoint, load_weights
from benchmark.core.data import FrameStore, load_scenes
from benchmark.unsupervised.sequences import SequenceDataset
from benchmark.unsupervised.training import PhotometricStep, smooth_settings

BATCH = 16


class Given(torch.nn.Module):
    """A DepthPoseNet stand-in answering given depth scales (finest first) and poses."""

    def __init__(self, depths: list[torch.Tensor], poses: torch.Tensor):
        super().__init__()
        self.depths, self.poses = depths, poses

    def forward(self, *inputs):
        return self.depths, self.poses


def scales_of(depth: torch.Tensor, count: int) -> list[torch.Tensor]:
    """DepthNet's ``count`` output sizes (1/4 … of the frame) of a full-resolution map."""
    h, w = depth.shape[-2:]
    return [F.adaptive_avg_pool2d(depth, (h // 2**s, w // 2**s)) for s in range(2, 2 + count)]


def true_poses(batch: dict) -> torch.Tensor:
    """Poses that training.compensate turns into the true motion ``X_i = R·X_t + τ_i``:
    ``τ_i = −R_{t→i}·c_i``, ``c_i`` frame i's camera position in the target's axes."""
    c = batch["translation"].unsqueeze(-1)
    return -(batch["rotation"] @ c).squeeze(-1)


def candidates(truth: torch.Tensor) -> dict[str, torch.Tensor]:
    """The true depth at the nominal displacement and wrong maps, (B, 1, H, W) metres."""
    median = truth.flatten(1).median(1).values.view(-1, 1, 1, 1).expand_as(truth)
    return {
        "truth": truth,
        "truth × 1.5": truth * 1.5,
        "truth / 1.5": truth / 1.5,
        "truth, beyond 20 m set to 100 m": torch.where(truth > 20, 100.0, truth),
        "median constant": median,
        "flat 10 m (DepthNet at step 0)": torch.full_like(truth, 10.0),
        "flat 100 m": torch.full_like(truth, 100.0),
    }


def main(data: str, ckpt: str, scenes: str = "60", samples: str = "64") -> None:
    torch.set_num_threads(1)
    ck = load_checkpoint(ckpt)
    net = registry.build_model(ck["model_name"])
    load_weights(net, ck, "ckpt", ckpt, ck["model_name"])
    net.train()  # batch statistics, as in training
    d0 = float(ck["nominal_displacement"])
    store = FrameStore(load_scenes(data, "train", rotations=True)[: int(scenes)], progress=False)
    pose = "translation" if all(s.stabilised for s in store.scenes) else "orientation"
    seq = SequenceDataset(store, registry.UNSUPERVISED_RECIPE.sequence_length)
    weights = registry.UNSUPERVISED_RECIPE.loss_weights
    lam, kappa = smooth_settings(None, None, False)
    cpu = torch.device("cpu")
    order = torch.randperm(len(seq), generator=torch.Generator().manual_seed(0))
    picked = order[: int(samples)].tolist()
    sums: dict[str, list[float]] = {}

    def add(name: str, depths: list[torch.Tensor], poses: torch.Tensor, batch: dict) -> None:
        step = PhotometricStep(Given(depths, poses), None, cpu, weights, d0, lam, kappa, pose=pose)
        terms = step.losses(batch)
        row = sums.setdefault(name, [0.0, 0.0, 0])
        n = len(batch["scene"])
        row[0] += float(terms["photometric"]) * n
        row[1] += float(terms["smooth"]) * n
        row[2] += n

    with torch.no_grad():
        for start in range(0, len(picked), BATCH):
            indices = picked[start : start + BATCH]
            batch = seq.batch(indices, 0)
            truth = []
            for j, i in enumerate(indices):
                k, first, t, r = seq.draw(i, 0)
                moved = float(batch["translation"][j, r].norm())
                truth.append(torch.from_numpy(store.depth(k, first + t)).float() * d0 / moved)
            truth = torch.stack(truth).unsqueeze(1).clamp(max=1e4)
            own_depths, own_poses = PhotometricStep(
                net, None, cpu, weights, d0, lam, kappa, pose=pose
            )._forward(batch)
            count = len(own_depths)
            motions = {"true": true_poses(batch), "PoseNet's": own_poses[..., :3]}
            for motion, poses in motions.items():
                add(f"the checkpoint's depth | {motion}", list(own_depths), poses, batch)
                for name, depth in candidates(truth).items():
                    add(f"{name} | {motion}", scales_of(depth, count), poses, batch)
    print(f"{data}: {sum(r[2] for r in sums.values()) // len(sums)} windows, {ckpt} ({pose})")
    print("| depth | translations | photometric | λ·smooth | loss |")
    print("|---|---|---|---|---|")
    for name, (photo, smooth, n) in sums.items():
        print(f"| {name} | {photo / n:.4f} | {smooth / n:.4f} | {(photo + smooth) / n:.4f} |")


if __name__ == "__main__":
    main(*sys.argv[1:])
