"""DepthNet and FlowNetS: one FlowNetS-style encoder-decoder with two sets of layers and heads.

Both read two stacked RGB frames, ``(B, 6, H, W)`` with H and W multiples of 64, and predict at
five scales, finest first: ``(B, C, H/4, W/4)``, …, ``(B, C, H/64, W/64)`` in train and eval
mode. The encoder is ``conv1`` … ``conv6_1`` (six stride-2 stages), the decoder runs from 1/64 up
to 1/4: at each scale a 3×3 ``predict_<head>`` conv gives a *raw* prediction, a bias-free 4×4
stride-2 transposed conv (``upsampled_<head>6_to_5`` …) upsamples it, and the next scale's
features are (skip features, ``deconv`` output, upsampled raw prediction) concatenated.

- :class:`DepthNet` (thesis 3.5, Figs. 3.8-3.9): FlowNetS at half width, 3×3 kernels, ReLU,
  BatchNorm (eps 1e-3), deconvs followed by a 3×3 conv, ``predict_depth`` convs with bias, one
  channel of depth in metres through "1 + ELU". 10,290,473 parameters.
- :class:`FlowNetS` (Dosovitskiy et al. 2015): kernels 7, 5, 5 then 3×3,
  LeakyReLU(0.1), optional BatchNorm on the encoder, single transposed-conv deconvs, bias-free
  ``predict_flow`` convs; a flow head (2 channels, pixels) or a depth head (1 channel, metres).

Module names, order and shapes are those of the public DepthNet and FlowNetS code (and of this
project's earlier checkpoints; tests/fixtures/models.json), so their state_dicts load with
``load_state_dict(strict=True)``. The registry of methods is :mod:`benchmark.core.registry`.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

BN_EPS = 1e-3
FLOW_DIV = 20.0  # FlowNetS works in flow / 20 (the public code's div_flow)
LEAKY_SLOPE = 0.1  # FlowNetS's LeakyReLU

ENCODER = ("conv1", "conv2", "conv3", "conv3_1", "conv4", "conv4_1", "conv5", "conv5_1")
ENCODER += ("conv6", "conv6_1")
DECODER_SCALES = (6, 5, 4, 3, 2)  # 1/64 … 1/4: predict_<head>6 … predict_<head>2


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


def conv_bn(c_in: int, c_out: int, k: int, stride: int, bn: bool, act: nn.Module) -> list:
    """k×k conv (padding (k−1)/2, no bias when BatchNorm(eps 1e-3) follows) → [BN] → ``act``."""
    layers: list[nn.Module] = [nn.Conv2d(c_in, c_out, k, stride, (k - 1) // 2, bias=not bn)]
    if bn:
        layers.append(nn.BatchNorm2d(c_out, eps=BN_EPS))
    return [*layers, act]


def upconv(c_in: int, c_out: int, bias: bool = False) -> nn.ConvTranspose2d:
    """×2 upsampling: 4×4 stride-2 transposed conv, padding 1."""
    return nn.ConvTranspose2d(c_in, c_out, 4, 2, 1, bias=bias)


def depth_activation(raw: torch.Tensor) -> torch.Tensor:
    """Raw prediction → depth (m) > 0: 1 + ELU, i.e. 1 + x for x > 0 and e^x otherwise."""
    return F.elu(raw) + 1.0


class EncoderDecoder(nn.Module):
    """The shared network; subclasses give the blocks, the head name, init and activation.

    Subclasses set ``head`` ("depth" or "flow": the names of the prediction layers),
    ``predict_bias``, and implement :meth:`conv_block`, :meth:`deconv_block`,
    :meth:`reset_parameters` and :meth:`activate`; their ``__init__`` calls :meth:`build`.
    """

    in_channels = 6
    min_multiple = 64  # six stride-2 stages
    head = "depth"
    predict_bias = True

    def __init__(self, width: float, batch_norm: bool):
        super().__init__()
        if not width > 0:
            raise ValueError(f"width must be > 0, got {width}")
        self.width, self.batch_norm = width, batch_norm

    def scaled(self, *channels: int) -> tuple[int, ...]:
        """Hidden channel counts times ``width``, rounded, at least 1."""
        return tuple(max(1, round(n * self.width)) for n in channels)

    def conv_block(self, c_in: int, c_out: int, k: int, stride: int) -> nn.Sequential:
        raise NotImplementedError

    def deconv_block(self, c_in: int, c_out: int) -> nn.Sequential:
        raise NotImplementedError

    def activate(self, raw: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def init_weight(self, name: str, conv: nn.Conv2d | nn.ConvTranspose2d) -> None:
        raise NotImplementedError

    def reset_parameters(self) -> None:
        """Conv and transposed-conv weights by :meth:`init_weight`, biases 0; BatchNorm weight 1,
        bias 0 (module order, so the seeded initialisation is the public code's)."""
        for name, m in self.named_modules():
            if isinstance(m, nn.Conv2d | nn.ConvTranspose2d):
                self.init_weight(name, m)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def build(self, encoder: tuple, kernels: tuple, decoder: tuple, out_channels: int) -> None:
        """Register the layers, in the public code's order.

        ``encoder``: channels of conv1, conv2, conv3, conv4, conv5, conv6 (each ``convN_1``
        keeps its width); ``kernels``: of conv1, conv2, conv3 (3×3 from conv3_1 on);
        ``decoder``: channels of deconv5 … deconv2; ``out_channels``: per prediction.
        """
        c1, c2, c3, c4, c5, c6 = encoder
        n = self.out_channels = out_channels
        k1, k2, k3 = kernels
        plan = [(self.in_channels, c1, k1, 2), (c1, c2, k2, 2), (c2, c3, k3, 2), (c3, c3, 3, 1)]
        plan += [(c3, c4, 3, 2), (c4, c4, 3, 1), (c4, c5, 3, 2), (c5, c5, 3, 1)]
        plan += [(c5, c6, 3, 2), (c6, c6, 3, 1)]
        for name, args in zip(ENCODER, plan, strict=True):
            setattr(self, name, self.conv_block(*args))
        # decoder input at each scale: skip features + deconv output + upsampled prediction
        cats = [c + d + n for c, d in zip((c5, c4, c3, c2), decoder, strict=True)]
        for k, c_in, c_out in zip((5, 4, 3, 2), [c6, *cats[:3]], decoder, strict=True):
            setattr(self, f"deconv{k}", self.deconv_block(c_in, c_out))
        for k, c_in in zip(DECODER_SCALES, [c6, *cats], strict=True):
            predict = nn.Conv2d(c_in, n, 3, 1, 1, bias=self.predict_bias)
            setattr(self, f"predict_{self.head}{k}", predict)
        for k in DECODER_SCALES[:-1]:
            setattr(self, f"upsampled_{self.head}{k}_to_{k - 1}", upconv(n, n))

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """(B, 6, H, W) → [(B, C, H/4, W/4), …, (B, C, H/64, W/64)], finest first."""
        check_frame_pair(x, type(self).__name__, self.in_channels, self.min_multiple)
        out_conv2 = self.conv2(self.conv1(x))
        out_conv3 = self.conv3_1(self.conv3(out_conv2))
        out_conv4 = self.conv4_1(self.conv4(out_conv3))
        out_conv5 = self.conv5_1(self.conv5(out_conv4))
        features = self.conv6_1(self.conv6(out_conv5))
        raw = getattr(self, f"predict_{self.head}6")(features)
        raws = [raw]
        for k, skip in zip((5, 4, 3, 2), (out_conv5, out_conv4, out_conv3, out_conv2), strict=True):
            upsample = getattr(self, f"upsampled_{self.head}{k + 1}_to_{k}")
            # the *raw* (pre-activation) prediction is upsampled, as in the public code
            features = torch.cat((skip, getattr(self, f"deconv{k}")(features), upsample(raw)), 1)
            raw = getattr(self, f"predict_{self.head}{k}")(features)
            raws.append(raw)
        return [self.activate(r) for r in reversed(raws)]


class DepthNet(EncoderDecoder):
    """DepthNet: depth from two stacked frames, multi-scale output (module doc).

    Args:
        width: multiplies every hidden channel count (rounded, at least 1); 1.0 is the
            published network (10,290,473 parameters with batch norm), small values give
            cheap variants for tests. The 6 input and 1 output channels never change.
        batch_norm: BatchNorm2d(eps=1e-3) after every hidden conv (the published setting).

    Outputs are depth in metres, > 0 by "1 + ELU" (computed as ``F.elu(x) + 1``, which in float32
    rounds to exactly 0 for raw values below about -17), in train and eval mode (the public code
    returns only the finest map in eval mode and drops the channel axis). The clamped DepthNet of
    thesis 6.4 is this network with a training recipe (benchmark.core.registry.CLAMPED_RECIPE): its
    targets are clipped during training and its outputs clamped where it is used, not inside the
    network, where a clamp would zero the gradients of every pixel outside the range.
    """

    head = "depth"
    predict_bias = True

    def __init__(self, width: float = 1.0, batch_norm: bool = True):
        super().__init__(width, batch_norm)
        encoder = self.scaled(32, 64, 128, 256, 256, 512)
        self.build(encoder, (3, 3, 3), self.scaled(256, 128, 64, 32), 1)
        self.reset_parameters()

    def conv_block(self, c_in: int, c_out: int, k: int, stride: int) -> nn.Sequential:
        """conv → [BN] → ReLU."""
        return nn.Sequential(*conv_bn(c_in, c_out, k, stride, self.batch_norm, nn.ReLU(True)))

    def deconv_block(self, c_in: int, c_out: int) -> nn.Sequential:
        """4×4 stride-2 transposed conv (with bias) → 3×3 conv → [BN] → ReLU."""
        tail = conv_bn(c_out, c_out, 3, 1, self.batch_norm, nn.ReLU(inplace=True))
        return nn.Sequential(upconv(c_in, c_out, bias=True), *tail)

    def init_weight(self, name: str, conv: nn.Conv2d | nn.ConvTranspose2d) -> None:
        """As the public code: N(0, 2 / (k·k·C_out)), i.e. He/kaiming normal over the fan-out
        counted with the layer's *output* channels (for a transposed conv too, where torch's own
        ``mode="fan_out"`` would use its input channels)."""
        fan_out = conv.kernel_size[0] * conv.kernel_size[1] * conv.out_channels
        nn.init.normal_(conv.weight, 0.0, math.sqrt(2.0 / fan_out))

    def activate(self, raw: torch.Tensor) -> torch.Tensor:
        """Raw prediction → depth (m): 1 + ELU (:func:`depth_activation`)."""
        return depth_activation(raw)


class FlowNetS(EncoderDecoder):
    """FlowNetS with a flow or a depth head (module doc).

    Args:
        output: ``"flow"``: 2 channels, optical flow in pixels of the *input* resolution at every
            scale (targets are area-downsampled without rescaling their values, as the public
            code); the network works in flow / 20 and multiplies its outputs by 20, so train with
            the loss divided by 20 to reproduce the original loss scale. ``"depth"`` (thesis
            Table 3.5): 1 channel, metres, through DepthNet's "1 + ELU".
        width: multiplies every hidden channel count (rounded, at least 1); 1.0 is the
            published network, small values give cheap variants for tests.
        batch_norm: BatchNorm (eps 1e-3) after every encoder conv, whose bias is then dropped
            (the public ``flownets_bn``).
    """

    head = "flow"  # module names follow the public code for both heads
    predict_bias = False

    def __init__(self, output: str = "flow", width: float = 1.0, batch_norm: bool = False):
        if output not in ("flow", "depth"):
            raise ValueError(f"output must be 'flow' or 'depth', got {output!r}")
        super().__init__(width, batch_norm)
        self.output = output
        encoder = self.scaled(64, 128, 256, 512, 512, 1024)
        n = 2 if output == "flow" else 1
        self.build(encoder, (7, 5, 5), self.scaled(512, 256, 128, 64), n)
        self.reset_parameters()

    def conv_block(self, c_in: int, c_out: int, k: int, stride: int) -> nn.Sequential:
        """conv → [BN] → LeakyReLU(0.1)."""
        act = nn.LeakyReLU(LEAKY_SLOPE, inplace=True)
        return nn.Sequential(*conv_bn(c_in, c_out, k, stride, self.batch_norm, act))

    def deconv_block(self, c_in: int, c_out: int) -> nn.Sequential:
        """4×4 stride-2 transposed conv (no bias) → LeakyReLU(0.1)."""
        return nn.Sequential(upconv(c_in, c_out), nn.LeakyReLU(LEAKY_SLOPE, inplace=True))

    def init_weight(self, name: str, conv: nn.Conv2d | nn.ConvTranspose2d) -> None:
        """As the public FlowNetS code: kaiming normal (fan-in, LeakyReLU slope 0.1). Except: the
        flow head's ``predict_flow*`` convs start at zero, so an untrained network predicts zero
        flow (with kaiming weights it predicts ~10-20 px of random flow, and the short CPU
        trainings here ended worse than zero flow: EPE 9-11 px against 3.0 px)."""
        if self.output == "flow" and name.startswith("predict_flow"):
            nn.init.zeros_(conv.weight)
        else:
            nn.init.kaiming_normal_(conv.weight, LEAKY_SLOPE)

    def activate(self, raw: torch.Tensor) -> torch.Tensor:
        """Raw prediction → flow (pixels, × 20) or depth (metres, 1 + ELU)."""
        return raw * FLOW_DIV if self.output == "flow" else depth_activation(raw)


def count_parameters(model: nn.Module) -> int:
    """Number of scalar parameters (all parameters; BN running statistics not included)."""
    return sum(p.numel() for p in model.parameters())


def macs(model: nn.Module, height: int, width: int) -> int:
    """Multiply-accumulates of one forward pass at batch 1 on a (1, C, height, width) input.

    Counts Conv2d (output elements × in_channels/groups × kh × kw) and ConvTranspose2d (input
    elements × out_channels/groups × kh × kw) layers only; biases, BN, activations and
    concatenations are ignored. C is ``model.in_channels`` (6 for DepthNet).
    """
    total = 0

    def hook(module: nn.Module, inputs: tuple[torch.Tensor, ...], output: torch.Tensor) -> None:
        nonlocal total
        kh, kw = module.kernel_size
        if isinstance(module, nn.ConvTranspose2d):
            total += inputs[0].numel() * (module.out_channels // module.groups) * kh * kw
        else:
            total += output.numel() * (module.in_channels // module.groups) * kh * kw

    layers = [m for m in model.modules() if isinstance(m, nn.Conv2d | nn.ConvTranspose2d)]
    handles = [m.register_forward_hook(hook) for m in layers]
    param = next(model.parameters(), None)
    shape = (1, getattr(model, "in_channels", 6), height, width)
    x = torch.zeros(shape) if param is None else param.new_zeros(shape)
    was_training = model.training
    try:
        model.eval()
        with torch.no_grad():
            model(x)
    finally:
        model.train(was_training)
        for h in handles:
            h.remove()
    return total
