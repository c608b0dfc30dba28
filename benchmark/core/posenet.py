"""PoseNet and the pair of networks trained without depth (thesis §5.2.1, chapter 5).

:class:`PoseNet` (Zhou et al. 2017, as the thesis uses it) reads a sequence of N RGB frames
stacked on the channel axis, ``(B, 3·N, H, W)``, through seven stride-2 convolutions (kernels
7, 5, then 3; ReLU) and a 1×1 prediction averaged over the remaining pixels. It outputs the pose
of every frame relative to the *last* one, ``(B, N, dof)``: ``dof = 3`` translations for
stabilised footage, 6 (translation, then rotation as Euler angles in radians) otherwise; the last
frame's row is exactly zero. Pose convention: that of
:mod:`benchmark.unsupervised.reprojection`, ``X_i = R_i·X_last + τ_i`` (camera coordinates of
frame i from those of the last frame, OpenCV axes x right, y down, z forward); ``R_i`` is
:func:`euler_matrix` of the angles (identity with ``dof = 3``); the unit of ``τ_i`` is arbitrary
(the pose normalisation of eq. 5.2 removes it). Outputs are multiplied by :data:`POSE_SCALE`
(small initial poses, as the author's code). Compensation to the target frame and normalisation
are in :mod:`benchmark.unsupervised.training`, rotations in :mod:`benchmark.unsupervised.rotation`.

:class:`DepthPoseNet` holds a DepthNet (``depth``) and a PoseNet (``pose``) in one module, so
that a run folder's checkpoint has both; called on a ``(B, 6, H, W)`` pair it is the DepthNet
(the same outputs, so scoring, ``eval`` and ``infer`` use it as any depth network); called with
the sequence too, it gives both outputs (the training step).
"""

from __future__ import annotations

import torch
from torch import nn

from .models import DepthNet

#: PoseNet's channels per stage at width 1 (the SFMLearner PoseNet's)
POSE_CHANNELS = (16, 32, 64, 128, 256, 256, 256)
POSE_KERNELS = (7, 5, 3, 3, 3, 3, 3)
#: ε of eq. 5.2 (the thesis gives no value; the author's training code uses 1e-5), in PoseNet's
#: (arbitrary) translation unit: translations are divided by ε + their norm (normalised in
#: training, benchmark.unsupervised.training; the "P" scale, benchmark.engine.scaling)
EPSILON = 1e-5
#: PoseNet's outputs are multiplied by this (the author's code: 0.1): small poses at first
POSE_SCALE = 0.1
#: DepthPoseNet's DepthNet starts at this depth everywhere (metres at the nominal displacement;
#: the toy study's start depth, thesis Fig. 4.11): its prediction convs get zero weights and the
#: bias giving it through 1 + ELU. With DepthNet's own initialisation, a quarter (``-tiny``) to a
#: half (full width) of its first outputs are below 0.1 m (spikes of ξ = 1/θ up to 10 /m), and the
#: smooth loss of those spikes is 10⁴ times the photometric loss: the first steps only flatten
#: them, pulling the neighbouring depths towards 0.1 m (measured: docs/results/unsupervised.md,
#: "Why the first short training did not learn").
INITIAL_DEPTH = 10.0


def euler_matrix(angles: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` of Euler angles ``(..., 3)`` = (α, β, γ), radians:
    ``R = R_x(α)·R_y(β)·R_z(γ)``, each factor the right-handed rotation about that camera axis,
    e.g. ``R_y(β) = [[cos β, 0, sin β], [0, 1, 0], [−sin β, 0, cos β]]`` (PoseNet's 6-DoF
    rotation, module doc; differentiable)."""
    cos, sin = angles.cos(), angles.sin()
    one, zero = torch.ones_like(angles[..., 0]), torch.zeros_like(angles[..., 0])

    def rot(k: int, i: int, j: int) -> torch.Tensor:  # about axis k: the (i, j) plane turns
        m = [[zero] * 3 for _ in range(3)]
        m[k][k] = one
        m[i][i], m[i][j], m[j][i], m[j][j] = cos[..., k], -sin[..., k], sin[..., k], cos[..., k]
        return torch.stack([torch.stack(row, -1) for row in m], -2)

    return rot(0, 1, 2) @ rot(1, 2, 0) @ rot(2, 0, 1)


class PoseNet(nn.Module):
    """Poses of ``frames`` frames relative to the last one (module doc); ``width`` multiplies the
    channel counts (``-tiny`` variants), ``dof`` is 3 (translation) or 6 (and rotation)."""

    def __init__(self, frames: int, dof: int = 3, width: float = 1.0):
        super().__init__()
        if frames < 2 or dof not in (3, 6) or not width > 0:
            raise ValueError(
                f"PoseNet: frames >= 2, dof 3 or 6, width > 0; got {(frames, dof, width)}"
            )
        self.frames, self.dof = frames, dof
        layers: list[nn.Module] = []
        c_in = 3 * frames
        for c, k in zip(POSE_CHANNELS, POSE_KERNELS, strict=True):
            c_out = max(1, round(c * width))
            layers += [nn.Conv2d(c_in, c_out, k, 2, (k - 1) // 2), nn.ReLU(inplace=True)]
            c_in = c_out
        self.encoder = nn.Sequential(*layers)
        self.predict = nn.Conv2d(c_in, dof * (frames - 1), 1)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, sequence: torch.Tensor) -> torch.Tensor:
        """``(B, 3·N, H, W)`` normalised frames (oldest first) -> ``(B, N, dof)`` poses relative
        to the last frame (its row zero)."""
        if sequence.dim() != 4 or sequence.shape[1] != 3 * self.frames:
            raise ValueError(
                f"PoseNet expects (B, {3 * self.frames}, H, W) ({self.frames} RGB frames), "
                f"got {tuple(sequence.shape)}"
            )
        out = self.predict(self.encoder(sequence)).mean((2, 3))
        out = out.view(-1, self.frames - 1, self.dof) * POSE_SCALE
        return torch.cat([out, torch.zeros_like(out[:, :1])], 1)


def start_flat(net: DepthNet, depth: float) -> None:
    """Give ``net``'s prediction convs (every scale) zero weights and the bias whose 1 + ELU is
    ``depth`` (metres, ≥ 1): it then outputs ``depth`` at every pixel and scale, and learns
    from there (the weights get gradients from the first step; the layers before them from the
    second)."""
    if depth < 1:
        raise ValueError(f"start_flat: depth >= 1 m (1 + ELU is linear there), got {depth}")
    for name, m in net.named_modules():
        if name.startswith(f"predict_{net.head}"):
            nn.init.zeros_(m.weight)
            nn.init.constant_(m.bias, depth - 1)


class DepthPoseNet(nn.Module):
    """DepthNet + PoseNet trained together from video (thesis Fig. 5.1); ``forward`` is the
    DepthNet's (a pair ``(B, 6, H, W)`` -> its multi-scale depth list, metres at the nominal
    displacement). The DepthNet starts flat at :data:`INITIAL_DEPTH` (:func:`start_flat`), or
    is ``depth``, a trained depth network kept as it is (``finetune``: a supervised DepthNet with
    a fresh PoseNet of its ``width``)."""

    def __init__(
        self, frames: int, width: float = 1.0, dof: int = 3, depth: nn.Module | None = None
    ):
        super().__init__()
        self.depth = DepthNet(width=width) if depth is None else depth
        self.pose = PoseNet(frames, dof, width)
        if depth is None:
            start_flat(self.depth, INITIAL_DEPTH)
        self.min_multiple = self.depth.min_multiple
        self.frames = frames

    def forward(self, pair: torch.Tensor, sequence: torch.Tensor | None = None, stabilise=None):
        """DepthNet's outputs for ``pair``; with ``sequence`` ``(B, 3·N, H, W)``, the pair
        ``(depths, poses)`` (one forward for training, so that DDP sees both networks). With
        ``stabilise`` (rotating data, thesis §5.2.2), PoseNet runs first and DepthNet reads
        ``stabilise(pair, poses)``: the pair with its reference warped to the target's
        orientation (benchmark.unsupervised.rotation)."""
        if sequence is None:
            return self.depth(pair)
        if stabilise is not None:
            poses = self.pose(sequence)
            return self.depth(stabilise(pair, poses)), poses
        return self.depth(pair), self.pose(sequence)
