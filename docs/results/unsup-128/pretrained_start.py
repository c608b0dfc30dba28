"""Usage: python docs/results/unsup-128/pretrained_start.py DATA CKPT [SCENES] [WINDOWS]

What does `run depthnet-unsup --pretrained CKPT --known-motion` start from? A supervised
DepthNet checkpoint's depth maps at every scale (median, share below the 0.1 m floor) on WINDOWS
(16) training windows of the first SCENES (40) scenes of a stabilised DATA, and eq. 5.5's terms
at step 0 with the true motion: photometric and λ·smooth over every scale (as training computes
them), and the photometric term of the finest map alone. In training mode (batch statistics,
as the first step sees them) and in eval mode (running statistics). One thread; about a minute
at 128 px.
"""

import sys

import torch

from benchmark.core import registry
from benchmark.core.checkpoint import load_checkpoint, load_weights
from benchmark.core.data import FrameStore, load_scenes
from benchmark.unsupervised.sequences import SequenceDataset
from benchmark.unsupervised.training import PhotometricStep, smooth_settings

FLOOR = 0.1  # metres: training.floored's floor


class Given(torch.nn.Module):
    """A DepthPoseNet stand-in answering given depth scales (its poses unused: known motion)."""

    def __init__(self, depths: list[torch.Tensor], frames: int):
        super().__init__()
        self.depths, self.frames = depths, frames

    def forward(self, pair, *inputs):
        return self.depths, torch.zeros(pair.shape[0], self.frames, 3)


def main(data: str, ckpt: str, scenes: str = "40", windows: str = "16") -> None:
    torch.set_num_threads(1)
    ck = load_checkpoint(ckpt)
    net = registry.build_model(ck["model_name"])
    load_weights(net, ck, "ckpt", ckpt, ck["model_name"])
    recipe = registry.UNSUPERVISED_RECIPE
    store = FrameStore(load_scenes(data, "train")[: int(scenes)], progress=False)
    seq = SequenceDataset(store, recipe.sequence_length)
    count = min(int(windows), len(seq))
    step = max(1, len(seq) // count)
    batch = seq.batch(list(range(0, step * count, step))[:count], 0)
    lam, kappa = smooth_settings(None, None, False)
    d0, cpu = float(ck["nominal_displacement"]), torch.device("cpu")
    print(f"{data}: {count} windows, {ckpt} ({ck['model_name']})")
    for mode in ("train", "eval"):
        getattr(net, mode)()
        with torch.no_grad():
            depths = list(net(batch["input"]))
            stats = [
                f"1/{batch['frames'].shape[-1] // d.shape[-1]}: median {d.median():.1f} m, "
                f"{(d < FLOOR).float().mean():.1%} below {FLOOR} m"
                for d in depths
            ]
            terms = {}
            for name, maps, weights in (
                ("every scale", depths, recipe.loss_weights),
                ("finest", depths[:1], (1.0,)),
            ):
                given = Given(maps, recipe.sequence_length)
                loss = PhotometricStep(
                    given, None, cpu, weights, d0, lam, kappa, known_translation=True
                )
                terms[name] = loss.losses(batch)
        print(f"{mode} mode: " + "; ".join(stats))
        every = terms["every scale"]
        print(
            f"{mode} mode: photometric {float(every['photometric']):.4f}, λ·smooth "
            f"{float(every['smooth']):.4f} (every scale); photometric "
            f"{float(terms['finest']['photometric']):.4f} (finest map alone)"
        )


if __name__ == "__main__":
    main(*sys.argv[1:])
