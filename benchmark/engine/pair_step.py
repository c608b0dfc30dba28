"""Learning from pairs with ground truth (thesis 3.6): the multi-scale losses and the training
step of depth and flow networks, registered for Target.DEPTH and Target.FLOW (engine.steps).

Depth networks learn the rescaled depth of the second frame (metres at the nominal
displacement) with the multi-scale L1 loss; flow networks learn the exact flow of the pair
(pixels of the input resolution; core.data.PairDataset ``target="flow"``) with the multi-scale
end-point error, times ``loss_scale`` (1/20: the public FlowNetS code's loss on flow / 20).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..core import registry
from ..core.data import PairDataset
from ..core.registry import Target
from .steps import training_step


def multiscale_l1(outputs: list[torch.Tensor], target: torch.Tensor, weights) -> torch.Tensor:
    """Σ_s γ_s · mean|out_s − area_downsample(target)| (outputs finest first, (B,1,h,w))."""
    loss = target.new_zeros(())
    t = target.unsqueeze(1)
    for out, w in zip(outputs, weights, strict=True):
        loss = loss + w * (out - F.adaptive_avg_pool2d(t, out.shape[-2:])).abs().mean()
    return loss


def multiscale_epe(outputs: list[torch.Tensor], target: torch.Tensor, weights) -> torch.Tensor:
    """Σ_s γ_s · mean‖out_s − area_downsample(target)‖₂ for (B, 2, H, W) flow targets.

    NaN target pixels are left out: each scale's target is the mean of the valid pixels under
    each output pixel, and output pixels covering no valid pixel are ignored. Flow values are
    not rescaled with the resolution (all scales in input-resolution pixels).
    """
    valid = torch.isfinite(target).all(1, keepdim=True).to(target.dtype)
    filled = torch.nan_to_num(target) * valid
    loss = target.new_zeros(())
    for out, w in zip(outputs, weights, strict=True):
        size = out.shape[-2:]
        share = F.adaptive_avg_pool2d(valid, size)
        t = F.adaptive_avg_pool2d(filled, size) / share.clamp_min(1e-12)
        keep = (share > 0)[:, 0]
        epe = (out - t).norm(dim=1)
        loss = loss + w * epe[keep].sum() / keep.sum().clamp_min(1)
    return loss


def multiscale_loss(outputs: list[torch.Tensor], target: torch.Tensor, weights) -> torch.Tensor:
    """multiscale_l1 for (B, H, W) depth targets, multiscale_epe for (B, 2, H, W) flow."""
    if target.ndim == 4:
        return multiscale_epe(outputs, target, weights)
    return multiscale_l1(outputs, target, weights)


class TrainStep:
    """One optimiser step on a batch: forward, multi-scale loss (× ``loss_scale``), backward,
    optimiser step; returns the loss (a 0-d tensor). ``channels_last``: inputs are handed to
    the network in channels-last memory format (the network should be converted too)."""

    def __init__(
        self,
        net: torch.nn.Module,
        opt: torch.optim.Optimizer,
        device: torch.device,
        loss_weights,
        loss_scale: float = 1.0,
        channels_last: bool = False,
        autocast: torch.dtype | None = None,
    ):
        self.net, self.opt, self.device = net, opt, device
        self.loss_weights, self.loss_scale = loss_weights, loss_scale
        self.memory_format = torch.channels_last if channels_last else torch.contiguous_format
        self.autocast = autocast

    def __call__(self, batch: dict) -> torch.Tensor:
        x = batch["input"].to(self.device, non_blocking=True, memory_format=self.memory_format)
        y = batch["target"].to(self.device, non_blocking=True)
        if self.autocast is None:
            outputs = self.net(x)
        else:
            with torch.autocast(self.device.type, self.autocast):
                outputs = self.net(x)
        loss = multiscale_loss([o.float() for o in outputs], y, self.loss_weights)
        loss = loss * self.loss_scale
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        return loss


@training_step(Target.DEPTH, Target.FLOW)
def pair_training(cfg, net, opt, device, store, d0, autocast=None, progress=None):
    """The training set and step of a depth or flow method (Trainer.setup): pairs ``cfg.shift``
    frames apart over ``store`` with the method's target (depth clipped to ``cfg.depth_range``,
    metres) and a TrainStep. ``d0`` is not used (depth targets are rescaled by the pairs)."""
    target = registry.MODELS[cfg.model].kind.target
    dataset = PairDataset(store, "train", cfg.shift, cfg.seed, target.value, cfg.depth_range)
    step = TrainStep(
        net, opt, device, cfg.loss_weights, cfg.loss_scale, cfg.channels_last, autocast
    )
    return dataset, step
