"""The SFMLearner baseline's networks (Zhou et al. 2017; thesis §5.4, Tables 5.1-5.3).

:class:`DispNet`: a single-frame encoder-decoder (the DispNetS of SFMLearner's public PyTorch
reimplementation): seven stride-2 stages of two 3×3 convs (7×7 and 5×5 for the first two), each
followed by ReLU, then seven transposed-conv stages with skip connections; disparity predicted at
1/8, 1/4, 1/2 and full resolution, each the coarser one upsampled and fed to the next stage.
Disparity is ``α·sigmoid(x) + β`` (:data:`ALPHA`, :data:`BETA`), so depth ``1/disparity`` lies in
``[1/(α + β), 1/β]``, in no metric unit: the photometric loss fixes depth only up to a scale
shared with PoseNet's translations, and the scale is found when it is scored (GT median or
PoseNet's displacement: benchmark.engine.scaling). No batch normalisation. Sizes that are
not multiples of 128 work: the decoder crops each upsampled map to its skip's size.

:class:`SfmLearnerNet`: DispNet + core.posenet.PoseNet with DepthPoseNet's call contract: called on
a ``(B, 6, H, W)`` pair (reference, target) it returns the target's depth list (DispNet reads only
the target frame, the pair's last three channels), finest first; called with the sequence too,
``(depths, poses)`` (the training step, benchmark.unsupervised.training.PhotometricStep).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .posenet import PoseNet

#: disparity = ALPHA · sigmoid + BETA (Zhou et al.'s values): depth in [1/10.01, 100]
ALPHA = 10.0
BETA = 0.01
#: encoder channels per stage (width 1), the first two stages' kernels (3 for the others)
ENCODER_CHANNELS = (32, 64, 128, 256, 512, 512, 512)
DECODER_CHANNELS = (512, 512, 256, 128, 64, 32, 16)
ENCODER_KERNELS = (7, 5, 3, 3, 3, 3, 3)
#: disparity outputs: the last four decoder stages (1/8, 1/4, 1/2, 1 of the input size)
SCALES = 4


def _relu_conv(c_in: int, c_out: int, kernel: int = 3, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(c_in, c_out, kernel, stride, (kernel - 1) // 2), nn.ReLU(inplace=True)]


def _crop(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``x`` cropped to ``like``'s height and width (top-left kept)."""
    return x[..., : like.shape[-2], : like.shape[-1]]


class DispNet(nn.Module):
    """Single-frame disparity network (module doc); ``width`` multiplies every channel count
    (``-tiny`` variants: 1/8). Input ``(B, 3, H, W)`` normalised as DepthNet's frames."""

    def __init__(self, width: float = 1.0, alpha: float = ALPHA, beta: float = BETA):
        super().__init__()
        if not width > 0:
            raise ValueError(f"DispNet: width > 0, got {width}")
        self.alpha, self.beta = alpha, beta
        enc = [max(1, round(c * width)) for c in ENCODER_CHANNELS]
        dec = [max(1, round(c * width)) for c in DECODER_CHANNELS]
        self.encoder = nn.ModuleList()
        c_in = 3
        for c, k in zip(enc, ENCODER_KERNELS, strict=True):
            self.encoder.append(nn.Sequential(*_relu_conv(c_in, c, k, 2), *_relu_conv(c, c, k)))
            c_in = c
        self.upconvs, self.iconvs = nn.ModuleList(), nn.ModuleList()
        skips = [*enc[-2::-1], 0]  # encoder outputs 6..1, then none at full resolution
        for i, (c, skip) in enumerate(zip(dec, skips, strict=True)):
            up = nn.ConvTranspose2d(c_in, c, 3, 2, 1, output_padding=1)
            self.upconvs.append(nn.Sequential(up, nn.ReLU(inplace=True)))
            fed = 1 if i > len(dec) - SCALES else 0  # the coarser disparity, upsampled
            self.iconvs.append(nn.Sequential(*_relu_conv(c + skip + fed, c)))
            c_in = c
        self.predict = nn.ModuleList(nn.Conv2d(c, 1, 3, 1, 1) for c in dec[-SCALES:])
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, frame: torch.Tensor) -> list[torch.Tensor]:
        """``(B, 3, H, W)`` -> disparities ``(B, 1, H/2^s, W/2^s)`` for s = 0..3, finest first."""
        if frame.dim() != 4 or frame.shape[1] != 3:
            raise ValueError(f"DispNet expects (B, 3, H, W), got {tuple(frame.shape)}")
        skips, x = [], frame
        for stage in self.encoder:
            x = stage(x)
            skips.append(x)
        skips = [*skips[-2::-1], frame]  # what each decoder stage is cropped to and fed
        disps: list[torch.Tensor] = []
        first_scale = len(self.upconvs) - SCALES
        for i, (up, iconv, skip) in enumerate(zip(self.upconvs, self.iconvs, skips, strict=True)):
            parts = [_crop(up(x), skip)]
            if i < len(skips) - 1:
                parts.append(skip)
            if disps:
                coarse = F.interpolate(
                    disps[-1], scale_factor=2, mode="bilinear", align_corners=False
                )
                parts.append(_crop(coarse, skip))
            x = iconv(torch.cat(parts, 1))
            if i >= first_scale:
                logit = self.predict[i - first_scale](x)
                disps.append(self.alpha * torch.sigmoid(logit) + self.beta)
        return disps[::-1]


class SfmLearnerNet(nn.Module):
    """DispNet + PoseNet (3 translations) trained together from video (module doc)."""

    #: frame sizes need no particular multiple (the decoder crops)
    min_multiple = 1

    def __init__(self, frames: int, width: float = 1.0, dof: int = 3):
        super().__init__()
        self.depth = DispNet(width)
        self.pose = PoseNet(frames, dof, width)
        self.frames = frames

    def forward(self, pair: torch.Tensor, sequence: torch.Tensor | None = None, stabilise=None):
        """Depth ``1/disparity`` of the pair's target (its last 3 channels), finest first; with
        ``sequence`` ``(B, 3·N, H, W)``, ``(depths, poses)`` (one forward for DDP).
        ``stabilise`` (rotating data, DepthPoseNet's argument) is ignored: DispNet reads the
        target alone, so warping the reference to its orientation changes nothing."""
        depths = [1 / d for d in self.depth(pair[:, 3:])]
        if sequence is None:
            return depths
        return depths, self.pose(sequence)
