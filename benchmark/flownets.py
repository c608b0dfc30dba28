"""FlowNetS (Dosovitskiy et al. 2015) as in REFERENCE §4, with a flow or a depth head.

Encoder widths 64/128/256/256/512/512/512/512/1024/1024, kernels 7, 5, 5 for conv1–conv3 then
3×3, LeakyReLU(0.1); decoder deconvs are a single 4×4 stride-2 transposed conv + LeakyReLU (no
extra 3×3 conv, unlike DepthNet); at each scale a bias-free 3×3 ``predict_flow`` conv and a
bias-free 4×4 transposed conv upsampling that raw prediction. Concatenations: 1026, 770, 386,
194 channels at 1/32 … 1/4 (two flow channels). Module names follow the public FlowNetS code
(``conv1`` … ``conv6_1``, ``deconv5`` …, ``predict_flow6`` …, ``upsampled_flow6_to_5`` …).

Two heads:

- ``output="flow"``: 2 channels, optical flow in pixels of the *input* resolution at every scale
  (targets are area-downsampled without rescaling their values, as the public code). The network
  works internally in flow / 20 (``FLOW_DIV``, the public code's ``div_flow``) and multiplies its
  outputs by 20; train with the loss divided by 20 to reproduce the original loss scale.
- ``output="depth"``: 1 channel (thesis Table 3.5 "FlowNetS"), depth in metres through the same
  "1 + ELU" activation as DepthNet (the raw prediction is upsampled, as in DepthNet).

``batch_norm=True`` (the public ``flownets_bn``) puts BatchNorm (eps 1e-3, as DepthNet) after every
encoder conv, whose bias is then dropped.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def check_frame_pair(x: torch.Tensor, name: str, in_channels: int, min_multiple: int) -> None:
    """ValueError unless ``x`` is (B, in_channels, H, W) with H and W multiples of min_multiple."""
    if x.dim() != 4 or x.shape[1] != in_channels:
        raise ValueError(
            f"{name} expects a (B, {in_channels}, H, W) tensor (two RGB frames stacked "
            f"on the channel axis), got shape {tuple(x.shape)}"
        )
    h, w = x.shape[-2:]
    if h % min_multiple or w % min_multiple:
        raise ValueError(
            f"{name} needs height and width that are multiples of {min_multiple} "
            f"(six stride-2 stages), got {h}x{w}"
        )


FLOW_DIV = 20.0
BN_EPS = 1e-3


def _conv(c_in: int, c_out: int, k: int, stride: int, bn: bool) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Conv2d(c_in, c_out, k, stride, (k - 1) // 2, bias=not bn)]
    if bn:
        layers.append(nn.BatchNorm2d(c_out, eps=BN_EPS))
    return nn.Sequential(*layers, nn.LeakyReLU(0.1, inplace=True))


def _deconv(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.ConvTranspose2d(c_in, c_out, 4, 2, 1, bias=False), nn.LeakyReLU(0.1, inplace=True)
    )


class FlowNetS(nn.Module):
    """FlowNetS on two stacked RGB frames, multi-scale output, finest (1/4) first.

    Args:
        output: ``"flow"`` (2 channels, pixels) or ``"depth"`` (1 channel, metres, > 0).
        width: multiplies every hidden channel count (rounded, at least 1); 1.0 is the
            published network, small values give cheap variants for tests.
        batch_norm: BatchNorm after every encoder conv (see module doc).

    ``forward(x)``: ``x`` is (B, 6, H, W), H and W multiples of 64. Returns 5 tensors
    (B, C, H/4, W/4), …, (B, C, H/64, W/64) in train and eval mode.
    """

    in_channels = 6
    min_multiple = 64

    def __init__(self, output: str = "flow", width: float = 1.0, batch_norm: bool = False):
        super().__init__()
        if output not in ("flow", "depth"):
            raise ValueError(f"output must be 'flow' or 'depth', got {output!r}")
        if not width > 0:
            raise ValueError(f"width must be > 0, got {width}")
        self.output, self.width, self.batch_norm = output, width, batch_norm
        self.out_channels = n = 2 if output == "flow" else 1

        def c(k: int) -> int:
            return max(1, round(k * width))

        bn = batch_norm
        c1, c2, c3, c4, c5, c6 = (c(k) for k in (64, 128, 256, 512, 512, 1024))
        self.conv1 = _conv(self.in_channels, c1, 7, 2, bn)  # 1/2
        self.conv2 = _conv(c1, c2, 5, 2, bn)  # 1/4
        self.conv3 = _conv(c2, c3, 5, 2, bn)  # 1/8
        self.conv3_1 = _conv(c3, c3, 3, 1, bn)
        self.conv4 = _conv(c3, c4, 3, 2, bn)  # 1/16
        self.conv4_1 = _conv(c4, c4, 3, 1, bn)
        self.conv5 = _conv(c4, c5, 3, 2, bn)  # 1/32
        self.conv5_1 = _conv(c5, c5, 3, 1, bn)
        self.conv6 = _conv(c5, c6, 3, 2, bn)  # 1/64
        self.conv6_1 = _conv(c6, c6, 3, 1, bn)

        d5, d4, d3, d2 = (c(k) for k in (512, 256, 128, 64))
        cat5, cat4, cat3, cat2 = c5 + d5 + n, c4 + d4 + n, c3 + d3 + n, c2 + d2 + n
        self.deconv5 = _deconv(c6, d5)
        self.deconv4 = _deconv(cat5, d4)
        self.deconv3 = _deconv(cat4, d3)
        self.deconv2 = _deconv(cat3, d2)

        self.predict_flow6 = nn.Conv2d(c6, n, 3, 1, 1, bias=False)
        self.predict_flow5 = nn.Conv2d(cat5, n, 3, 1, 1, bias=False)
        self.predict_flow4 = nn.Conv2d(cat4, n, 3, 1, 1, bias=False)
        self.predict_flow3 = nn.Conv2d(cat3, n, 3, 1, 1, bias=False)
        self.predict_flow2 = nn.Conv2d(cat2, n, 3, 1, 1, bias=False)

        self.upsampled_flow6_to_5 = nn.ConvTranspose2d(n, n, 4, 2, 1, bias=False)
        self.upsampled_flow5_to_4 = nn.ConvTranspose2d(n, n, 4, 2, 1, bias=False)
        self.upsampled_flow4_to_3 = nn.ConvTranspose2d(n, n, 4, 2, 1, bias=False)
        self.upsampled_flow3_to_2 = nn.ConvTranspose2d(n, n, 4, 2, 1, bias=False)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """As the public FlowNetS code: kaiming-normal (fan-in, LeakyReLU slope 0.1) conv and
        transposed-conv weights, zero biases, BatchNorm weight 1 / bias 0. Except: the flow
        head's ``predict_flow*`` convs start at zero, so an untrained network predicts zero flow
        (with kaiming weights it predicts ~10-20 px of random flow, and the short CPU trainings
        here ended worse than zero flow: EPE 9-11 px against 3.0 px)."""
        for name, m in self.named_modules():
            if isinstance(m, nn.Conv2d | nn.ConvTranspose2d):
                if self.output == "flow" and name.startswith("predict_flow"):
                    nn.init.zeros_(m.weight)
                else:
                    nn.init.kaiming_normal_(m.weight, 0.1)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def _activate(self, raw: torch.Tensor) -> torch.Tensor:
        return raw * FLOW_DIV if self.output == "flow" else F.elu(raw) + 1.0

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """(B, 6, H, W) → [(B, C, H/4, W/4), …, (B, C, H/64, W/64)], finest first."""
        check_frame_pair(x, "FlowNetS", self.in_channels, self.min_multiple)
        out_conv2 = self.conv2(self.conv1(x))
        out_conv3 = self.conv3_1(self.conv3(out_conv2))
        out_conv4 = self.conv4_1(self.conv4(out_conv3))
        out_conv5 = self.conv5_1(self.conv5(out_conv4))
        features = self.conv6_1(self.conv6(out_conv5))
        raw = self.predict_flow6(features)
        raws = [raw]
        stages = (
            (out_conv5, self.deconv5, self.upsampled_flow6_to_5, self.predict_flow5),
            (out_conv4, self.deconv4, self.upsampled_flow5_to_4, self.predict_flow4),
            (out_conv3, self.deconv3, self.upsampled_flow4_to_3, self.predict_flow3),
            (out_conv2, self.deconv2, self.upsampled_flow3_to_2, self.predict_flow2),
        )
        for skip, deconv, upsample, predict in stages:
            features = torch.cat((skip, deconv(features), upsample(raw)), dim=1)
            raw = predict(features)
            raws.append(raw)
        return [self._activate(r) for r in reversed(raws)]
