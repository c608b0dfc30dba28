"""Rotating data in unsupervised training: the ``--pose`` modes (thesis §5.2.1-5.2.2).

``TrainConfig.pose`` (core.config.POSE_MODES) says where the rotations of a sequence come from:

- ``translation``: none, PoseNet gives 3 translations (stabilised data; the default);
- ``orientation``: the dataset's known orientations (the "O" of Tables 5.1-5.2, a UAV's inertial
  sensors): ``R_{t→i}`` of SequenceDataset's batch, PoseNet's 3 outputs are the translations;
- ``6dof``: PoseNet's 6 outputs (``depthnet-unsup-6dof*``), rotations by
  core.posenet.euler_matrix, ``R_{t→i} = R_i·R_tᵀ`` (both relative to the last frame).

In both rotating modes the reference is stabilised before DepthNet reads the pair (eq. 5.1,
:func:`benchmark.unsupervised.reprojection.rotate_frame` with ``R_{t→r}``), every frame is warped
to the target with its rotation and translation, and the translations are compensated with the
rotations (training.compensate). Choices (the thesis does not say): PoseNet's rotation that
stabilises the reference is detached (PoseNet learns its rotations from the photometric warps
only, not through DepthNet's input), and the stabilised reference's pixels the reference does not
see are 0 in DepthNet's normalised input (mid-grey), not the border's colour.

A dataset says whether it rotates: a scene is stabilised when its record has no orientations
(stillbox_gen.dataset.Scene.stabilised). The ``translation`` mode refuses a training split with a
rotating scene, the other two one without any (:func:`check_pose`).
"""

from __future__ import annotations

import torch

from ..core.errors import FieldError
from ..core.posenet import euler_matrix
from .reprojection import rotate_frame

#: ``--pose`` values that need rotating data (the others, stabilised data)
ROTATING_MODES = ("orientation", "6dof")


def check_pose(pose: str, model_pose: str, scenes, data: str) -> None:
    """FieldError on ``pose`` (one line) when the mode does not fit the network (``model_pose``:
    its recipe's, "6dof" for a 6-output PoseNet) or the data (``scenes``: the training split,
    stillbox_gen.dataset.Scene, in folder ``data``)."""
    if (pose == "6dof") != (model_pose == "6dof"):
        need = "depthnet-unsup-6dof(-tiny)" if pose == "6dof" else "depthnet-unsup(-tiny)"
        raise FieldError("pose", f"'{pose}' needs {need}")
    rotating = [s.index for s in scenes if not s.stabilised]
    if pose in ROTATING_MODES and not rotating:
        raise FieldError(
            "pose", f"'{pose}' is for rotating data; {data} is stabilised (use translation)"
        )
    if pose not in ROTATING_MODES and rotating:
        raise FieldError(
            "pose",
            f"'{pose}' is for stabilised data; {data} has camera rotations (scene "
            f"{rotating[0]}): use orientation or depthnet-unsup-6dof",
        )


def target_rotations(
    pose: str, poses: torch.Tensor, known: torch.Tensor, target_index: torch.Tensor
) -> torch.Tensor | None:
    """``R_{t→i}`` ``(B, N, 3, 3)`` of every frame of a batch for mode ``pose`` (module doc),
    None for ``translation``. ``poses``: PoseNet's ``(B, N, dof)``; ``known``: the batch's
    ``rotation``; ``target_index`` ``(B,)``."""
    if pose == "orientation":
        return known.to(poses)
    if pose != "6dof":
        return None
    last = euler_matrix(poses[..., 3:])  # R_i: X_i = R_i·X_last + τ_i
    rows = torch.arange(poses.shape[0], device=poses.device)
    return last @ last[rows, target_index].transpose(-1, -2).unsqueeze(1)


class Stabiliser:
    """The ``stabilise`` of core.posenet.DepthPoseNet.forward for one batch: ``(pair, poses)``
    -> the pair ``(B, 6, H, W)`` (reference, target; normalised) with its reference warped to
    the target's orientation by ``R_{t→r}`` (eq. 5.1): the known one, or PoseNet's (detached)."""

    def __init__(self, pose: str, known, target_index, reference_index, K):
        self.pose, self.known, self.K = pose, known, K
        self.tgt, self.ref = target_index, reference_index

    def __call__(self, pair: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        rows = torch.arange(pair.shape[0], device=pair.device)
        dtype = torch.promote_types(pair.dtype, torch.float32)  # bfloat16 under autocast
        turns = target_rotations(self.pose, poses.detach().to(dtype), self.known, self.tgt)
        reference, valid = rotate_frame(pair[:, :3].to(dtype), turns[rows, self.ref], self.K)
        reference = torch.where(valid, reference, torch.zeros_like(reference)).to(pair)
        return torch.cat([reference, pair[:, 3:]], 1)
