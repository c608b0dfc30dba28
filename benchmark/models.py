"""Networks of the StillBox benchmark and the registry that names them.

Registered methods (``MODELS``): DepthNet (depth directly), FlowNetS with a depth head, FlowNetS
for optical flow followed by depth from flow and the known translation (benchmark.flow), the same
geometry fed with ground-truth flow (``oracle-flow``) and a constant depth (``constant``); the last
two have no network. FlowNetS lives in benchmark.flownets.

DepthNet (Pinard et al., thesis section 3.5) is FlowNetS with every width halved, 3×3 kernels
everywhere, BatchNorm and a 1-channel depth output. It reads two stacked RGB frames,
(B, 6, H, W), and predicts depth in metres at five scales, finest (H/4) first.

Module names follow the public DepthNet code (``conv1`` … ``conv6_1``, ``deconv5`` …,
``predict_depth6`` …, ``upsampled_depth6_to_5`` …) and each block is an ``nn.Sequential`` of the
same layers, so a batch-norm DepthNet checkpoint from that code loads with ``load_state_dict``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from .flownets import FlowNetS, check_frame_pair

BN_EPS = 1e-3
DEPTH_CLAMP_M = (10.0, 60.0)  # range of the optional output clamp, metres (as the public code)


def _conv(c_in: int, c_out: int, stride: int, batch_norm: bool) -> nn.Sequential:
    """3×3 conv (padding 1) → [BatchNorm] → ReLU; the conv has no bias when BN follows it."""
    layers: list[nn.Module] = [nn.Conv2d(c_in, c_out, 3, stride, 1, bias=not batch_norm)]
    if batch_norm:
        layers.append(nn.BatchNorm2d(c_out, eps=BN_EPS))
    return nn.Sequential(*layers, nn.ReLU(inplace=True))


def _deconv(c_in: int, c_out: int, batch_norm: bool) -> nn.Sequential:
    """×2 upsampling block: 4×4 stride-2 transposed conv (with bias) → 3×3 conv → [BN] → ReLU."""
    layers: list[nn.Module] = [
        nn.ConvTranspose2d(c_in, c_out, 4, 2, 1, bias=True),
        nn.Conv2d(c_out, c_out, 3, 1, 1, bias=not batch_norm),
    ]
    if batch_norm:
        layers.append(nn.BatchNorm2d(c_out, eps=BN_EPS))
    return nn.Sequential(*layers, nn.ReLU(inplace=True))


class DepthNet(nn.Module):
    """DepthNet: depth from two stacked frames, multi-scale output.

    Args:
        width: multiplies every hidden channel count (rounded, at least 1); 1.0 is the
            published network (10,290,473 parameters with batch norm), small values give
            cheap variants for tests. The 6 input and 1 output channels never change.
        batch_norm: BatchNorm2d(eps=1e-3) after every hidden conv (the published setting).
        clamp: clamp every output to [10, 60] m after the activation, as the public code's
            ``clamp`` option (off by default; it zeroes gradients outside that range).

    ``forward(x)``: ``x`` is (B, 6, H, W), H and W multiples of 64 (the two frames stacked on
    the channel axis, normalised as the data pipeline chooses). Returns a list of 5 tensors of
    depth in metres, > 0 by the "1 + ELU" activation (computed as ``F.elu(x) + 1``, which in
    float32 rounds to exactly 0 for raw values below about -17), finest first:
    (B, 1, H/4, W/4), (B, 1, H/8, W/8), …, (B, 1, H/64, W/64) -- in both train and eval
    mode (the public code returns only the finest map in eval mode and drops the channel axis).
    """

    in_channels = 6
    min_multiple = 64  # six stride-2 stages

    def __init__(self, width: float = 1.0, batch_norm: bool = True, clamp: bool = False):
        super().__init__()
        if not width > 0:
            raise ValueError(f"width must be > 0, got {width}")
        self.width, self.batch_norm, self.clamp = width, batch_norm, clamp

        def c(n: int) -> int:
            return max(1, round(n * width))

        bn = batch_norm
        c1, c2, c3, c4, c5, c6 = (c(n) for n in (32, 64, 128, 256, 256, 512))
        self.conv1 = _conv(self.in_channels, c1, 2, bn)  # 1/2
        self.conv2 = _conv(c1, c2, 2, bn)  # 1/4
        self.conv3 = _conv(c2, c3, 2, bn)  # 1/8
        self.conv3_1 = _conv(c3, c3, 1, bn)
        self.conv4 = _conv(c3, c4, 2, bn)  # 1/16
        self.conv4_1 = _conv(c4, c4, 1, bn)
        self.conv5 = _conv(c4, c5, 2, bn)  # 1/32
        self.conv5_1 = _conv(c5, c5, 1, bn)
        self.conv6 = _conv(c5, c6, 2, bn)  # 1/64
        self.conv6_1 = _conv(c6, c6, 1, bn)

        # Decoder input at scale s = skip features + deconv output + upsampled raw prediction:
        # 256+256+1 = 513 (1/32), 256+128+1 = 385 (1/16), 128+64+1 = 193 (1/8), 64+32+1 = 97 (1/4).
        d5, d4, d3, d2 = (c(n) for n in (256, 128, 64, 32))
        cat5, cat4, cat3, cat2 = c5 + d5 + 1, c4 + d4 + 1, c3 + d3 + 1, c2 + d2 + 1
        self.deconv5 = _deconv(c6, d5, bn)
        self.deconv4 = _deconv(cat5, d4, bn)
        self.deconv3 = _deconv(cat4, d3, bn)
        self.deconv2 = _deconv(cat3, d2, bn)

        self.predict_depth6 = nn.Conv2d(c6, 1, 3, 1, 1)
        self.predict_depth5 = nn.Conv2d(cat5, 1, 3, 1, 1)
        self.predict_depth4 = nn.Conv2d(cat4, 1, 3, 1, 1)
        self.predict_depth3 = nn.Conv2d(cat3, 1, 3, 1, 1)
        self.predict_depth2 = nn.Conv2d(cat2, 1, 3, 1, 1)

        self.upsampled_depth6_to_5 = nn.ConvTranspose2d(1, 1, 4, 2, 1, bias=False)
        self.upsampled_depth5_to_4 = nn.ConvTranspose2d(1, 1, 4, 2, 1, bias=False)
        self.upsampled_depth4_to_3 = nn.ConvTranspose2d(1, 1, 4, 2, 1, bias=False)
        self.upsampled_depth3_to_2 = nn.ConvTranspose2d(1, 1, 4, 2, 1, bias=False)

        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Initialise as the public code: conv and transposed-conv weights ~ N(0, 2 / (k·k·C_out)),
        i.e. He/kaiming normal over the fan-out counted with the layer's *output* channels (for a
        transposed conv too, where torch's own ``mode="fan_out"`` would use its input channels);
        biases 0; BatchNorm weight 1, bias 0."""
        for m in self.modules():
            if isinstance(m, nn.Conv2d | nn.ConvTranspose2d):
                fan_out = m.kernel_size[0] * m.kernel_size[1] * m.out_channels
                nn.init.normal_(m.weight, 0.0, math.sqrt(2.0 / fan_out))
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def _activate(self, raw: torch.Tensor) -> torch.Tensor:
        """Raw prediction → depth (m): 1 + ELU, i.e. 1 + x for x > 0 and e^x otherwise."""
        depth = F.elu(raw) + 1.0
        return depth.clamp(*DEPTH_CLAMP_M) if self.clamp else depth

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """(B, 6, H, W) → [(B, 1, H/4, W/4), (B, 1, H/8, W/8), …, (B, 1, H/64, W/64)], metres."""
        check_frame_pair(x, "DepthNet", self.in_channels, self.min_multiple)
        out_conv2 = self.conv2(self.conv1(x))
        out_conv3 = self.conv3_1(self.conv3(out_conv2))
        out_conv4 = self.conv4_1(self.conv4(out_conv3))
        out_conv5 = self.conv5_1(self.conv5(out_conv4))
        features = self.conv6_1(self.conv6(out_conv5))

        raw = self.predict_depth6(features)
        raws = [raw]
        stages = (
            (out_conv5, self.deconv5, self.upsampled_depth6_to_5, self.predict_depth5),
            (out_conv4, self.deconv4, self.upsampled_depth5_to_4, self.predict_depth4),
            (out_conv3, self.deconv3, self.upsampled_depth4_to_3, self.predict_depth3),
            (out_conv2, self.deconv2, self.upsampled_depth3_to_2, self.predict_depth2),
        )
        for skip, deconv, upsample, predict in stages:
            # The *raw* (pre-activation) prediction is upsampled, as in the public code.
            features = torch.cat((skip, deconv(features), upsample(raw)), dim=1)
            raw = predict(features)
            raws.append(raw)
        return [self._activate(r) for r in reversed(raws)]


# --------------------------------------------------------------------------- registry


def _depthnet_defaults() -> dict:
    """Training hyper-parameters of the thesis recipe at 64/128 px (REFERENCE §5)."""
    return {
        "lr": 1e-2,
        "batch_size": 256,
        "epochs": 55,
        "momentum": 0.9,
        "dampening": 0.9,
        "weight_decay": 4e-4,
        # lr × gamma at these fractions of the epoch count (epochs 19, 30, 44, 53 of 55)
        "milestones": [19 / 55, 30 / 55, 44 / 55, 53 / 55],
        "gamma": 0.3,
        # loss weight per output, finest (1/4) to coarsest (1/64)
        "loss_weights": (0.32, 0.08, 0.02, 0.01, 0.005),
    }


def _flow_defaults() -> dict:
    """The public FlowNetS flow recipe: Adam (lr 1e-4, betas 0.9/0.999, weight decay 4e-4), loss
    in flow / 20; batch, epochs and lr steps as DepthNet. DepthNet's SGD at lr 0.01 did not learn
    flow here (64 px, 2 epochs: predictions uncorrelated with the truth, EPE 10.7 px against
    3.0 px for zero flow)."""
    return {
        **_depthnet_defaults(),
        "optimizer": "adam",
        "lr": 1e-4,
        "momentum": 0.9,
        "beta2": 0.999,
        "loss_scale": 1.0 / 20.0,
    }


#: what a method outputs: a depth network, a flow network (depth by geometry), or no network
OUTPUTS = ("depth", "flow", "oracle-flow", "constant")


@dataclass(frozen=True)
class ModelSpec:
    """A registered method.

    ``build()`` returns a freshly initialised network, or is None for methods without one
    (``oracle-flow``, ``constant``: nothing to train). ``output`` says what the network predicts
    and how depth is obtained: "depth" (metres, multi-scale list as DepthNet), "flow" (pixels,
    multi-scale list; depth from flow and the known translation), "oracle-flow" (ground-truth
    flow through the same geometry), "constant" (the training set's median depth everywhere).
    ``defaults`` are its training hyper-parameters (copy before modifying).
    """

    name: str
    description: str
    build: Callable[[], nn.Module] | None
    output: str = "depth"
    defaults: dict = field(default_factory=_depthnet_defaults)

    @property
    def trainable(self) -> bool:
        return self.build is not None


MODELS: dict[str, ModelSpec] = {
    spec.name: spec
    for spec in (
        ModelSpec(
            "depthnet",
            "DepthNet (FlowNetS at half width, BN, 1+ELU depth output), ~10.3 M parameters",
            lambda: DepthNet(width=1.0),
        ),
        ModelSpec(
            "depthnet-tiny",
            "DepthNet at 1/8 width, for tests and smoke runs",
            lambda: DepthNet(width=0.125),
        ),
        ModelSpec(
            "flownets-depth",
            "FlowNetS (BN) with a 1-channel 1+ELU depth output, trained like DepthNet",
            lambda: FlowNetS("depth", batch_norm=True),
        ),
        ModelSpec(
            "flownets-depth-tiny",
            "flownets-depth at 1/8 width, for tests and smoke runs",
            lambda: FlowNetS("depth", width=0.125, batch_norm=True),
        ),
        ModelSpec(
            "flownets-flow",
            "FlowNetS (BN) for optical flow; depth from flow and the known translation",
            lambda: FlowNetS("flow", batch_norm=True),
            output="flow",
            defaults=_flow_defaults(),
        ),
        ModelSpec(
            "flownets-flow-tiny",
            "flownets-flow at 1/8 width, for tests and smoke runs",
            lambda: FlowNetS("flow", width=0.125, batch_norm=True),
            output="flow",
            defaults=_flow_defaults(),
        ),
        ModelSpec(
            "oracle-flow",
            "ground-truth flow -> depth by the FOE geometry (checks geometry vs metadata)",
            None,
            output="oracle-flow",
            defaults={},
        ),
        ModelSpec(
            "constant",
            "the training set's median depth at every pixel (the floor to beat)",
            None,
            output="constant",
            defaults={},
        ),
    )
}


def list_models() -> list[str]:
    """Registered model names, sorted."""
    return sorted(MODELS)


def build_model(name: str) -> nn.Module:
    """A freshly initialised network by registry name; ValueError for an unknown name or a
    method without a network (oracle-flow, constant)."""
    try:
        spec = MODELS[name]
    except KeyError:
        raise ValueError(
            f"unknown model {name!r}; registered models: {', '.join(list_models())}"
        ) from None
    if spec.build is None:
        raise ValueError(f"{name!r} has no network (nothing to build or train)")
    return spec.build()


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
