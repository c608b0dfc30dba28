"""Usage: python docs/results/finetune/pose_overfit.py CKPT DATA [LR] [STEPS]

Can PoseNet learn the translation directions through the photometric loss at all? PoseNet alone
(fresh, seed 0) is fitted to ONE fixed batch of 8 training sequences of DATA (the first 20
training scenes, one window in 20, or closer when they have fewer than 160 windows) with the
depth network of CKPT frozen (eval mode), the loss of ``finetune`` without smooth term (eq. 5.3
at d0 = 0.3 m), Adam at LR (1e-3) for STEPS (150) steps; every 25 steps it prints the
photometric loss and the mean cosine between PoseNet's reference translation and the true one. A
cosine that climbs towards 1 shows the gradient path from the warps to PoseNet works;
``finetune``'s warm-up then needs the steps to generalise across scenes. One torch thread.
"""

import sys

import torch

from benchmark.core.checkpoint import load_checkpoint, load_weights
from benchmark.core.data import FrameStore, load_scenes
from benchmark.core.posenet import DepthPoseNet
from benchmark.core.registry import build_model
from benchmark.unsupervised.finetune import pose_cosine
from benchmark.unsupervised.sequences import SequenceDataset
from benchmark.unsupervised.training import PhotometricStep

WEIGHTS = (1, 0.5, 0.25, 0.125, 0.0625)


def main(ckpt: str, data: str, lr: str = "1e-3", steps: str = "150") -> None:
    torch.set_num_threads(1)
    torch.manual_seed(0)
    ck = load_checkpoint(ckpt)
    depth = build_model(ck["model_name"])
    load_weights(depth, ck, None, ckpt, ck["model_name"])
    net = DepthPoseNet(5, 1.0, depth=depth)
    net.depth.requires_grad_(False)
    store = FrameStore(load_scenes(data, "train")[:20], progress=False)
    seqs = SequenceDataset(store, 5, 0)
    every = max(1, min(20, len(seqs) // 8))  # 20 on the study's data; a small DATA keeps 8
    batch = seqs.batch(list(range(0, len(seqs), every))[:8], 0)
    opt = torch.optim.Adam(net.pose.parameters(), lr=float(lr))
    step = PhotometricStep(net, opt, torch.device("cpu"), WEIGHTS, 0.3, 0.0, 0.3)
    for i in range(int(steps) + 1):
        net.train()
        net.depth.eval()
        terms = step.update(batch)
        if i % 25 == 0:
            cos = pose_cosine(batch, terms["translations"])
            print(f"step {i:4d}  photometric {float(terms['photometric']):.4f}  cosine {cos:.3f}")


if __name__ == "__main__":
    main(*sys.argv[1:])
