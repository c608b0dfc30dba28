"""Training samples without depth: frame sequences of a dataset's scenes (thesis §5.2, Fig. 5.1).

A sample is N consecutive frames of one scene (N = ``length``, 5 by default as §5.4.3), a
target index t and a reference index r ≠ t, both drawn uniformly from ``numpy.random
.default_rng([seed, epoch, index])`` (the same batches whatever the machine; a resumed run
continues the sequence). There is one sample per (scene, first frame) window. No depth is read:
the known translations are returned for logging and tests only, never for the loss; the known
rotations (rotating scenes) are the loss's with ``--pose orientation``. No flips
(the author's code has them off too).
"""

from __future__ import annotations

import numpy as np
import torch

from ..core.data import NORM_MEAN, NORM_STD, FrameStore


class SequenceDataset:
    """Windows of ``length`` frames of a FrameStore's scenes, read a batch at a time
    (:meth:`batch`; the trainer's PairBatches and EpochBatches use it as a PairDataset).
    ``store`` may be any object with FrameStore's ``scenes`` (each with ``rgb`` (one entry a
    frame), ``K``, ``translation(i, j)`` and ``index``), ``rgb(k, f)``, ``height`` and
    ``width``: ``finetune`` passes the moving stretches of a user's footage
    (benchmark.unsupervised.finetune.FootageStore)."""

    def __init__(self, store: FrameStore, length: int, seed: int = 0):
        self.store, self.length, self.seed = store, length, seed
        self.epoch = 0
        self.items = [
            (k, f) for k, s in enumerate(store.scenes) for f in range(len(s.rgb) - length + 1)
        ]

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.items)

    def draw(self, i: int, epoch: int) -> tuple[int, int, int, int]:
        """Sample ``i`` of ``epoch``: (scene position k, first frame, target t, reference r)."""
        k, first = self.items[i]
        rng = np.random.default_rng([self.seed, epoch, i])
        t = int(rng.integers(0, self.length))
        r = int(rng.integers(0, self.length - 1))
        return k, first, t, r + (r >= t)

    def batch(self, indices: list[int], epoch: int | None = None) -> dict:
        """Samples ``indices`` of ``epoch`` (default: the current one) as one batch:

        ``frames`` (B, N, 3, H, W) float32 in [0, 1] (the photometric loss's images);
        ``sequence`` (B, 3·N, H, W) normalised as DepthNet's inputs ((x − 0.5)/0.2), PoseNet's
        input; ``input`` (B, 6, H, W): the (reference, target) pair, DepthNet's input;
        ``target_index``, ``reference_index`` (B,) int64; ``K`` (B, 3, 3) pixels;
        ``translation`` (B, N, 3) metres: the true camera displacement from the target to each
        frame (target axes; logging and tests only); ``rotation`` (B, N, 3, 3): the true
        rotation ``R_{t→i}`` from the target's camera axes to each frame's (identity on
        stabilised scenes; the loss's rotation with ``--pose orientation``, as the dataset's
        orientations stand for a UAV's inertial sensors, §5.2.2); ``scene`` (B,).
        """
        epoch = self.epoch if epoch is None else epoch
        draws = [self.draw(i, epoch) for i in indices]
        n, length = len(draws), self.length
        h, w = self.store.height, self.store.width
        raw = np.empty((n, length, 3, h, w), np.uint8)
        translation, K = np.empty((n, length, 3)), np.empty((n, 3, 3))
        rotation = np.tile(np.eye(3), (n, length, 1, 1))
        for j, (k, first, t, _) in enumerate(draws):
            scene = self.store.scenes[k]
            for f in range(length):
                raw[j, f] = self.store.rgb(k, first + f).transpose(2, 0, 1)
                translation[j, f] = scene.translation(first + t, first + f)
                if not scene.stabilised:  # X_f = R·X_t + τ: camera f sits at −Rᵀτ
                    pose = scene.relative_pose(first + t, first + f)
                    rotation[j, f] = pose[:3, :3]
                    translation[j, f] = -pose[:3, :3].T @ pose[:3, 3]
            K[j] = scene.K
        frames = torch.from_numpy(raw).float() / 255.0
        sequence = (frames - NORM_MEAN) / NORM_STD
        tgt = torch.tensor([d[2] for d in draws])
        ref = torch.tensor([d[3] for d in draws])
        rows = torch.arange(n)
        pair = torch.cat([sequence[rows, ref], sequence[rows, tgt]], 1)
        return {
            "frames": frames,
            "sequence": sequence.reshape(n, length * 3, h, w),
            "input": pair,
            "target_index": tgt,
            "reference_index": ref,
            "K": torch.from_numpy(K.astype(np.float32)),
            "translation": torch.from_numpy(translation.astype(np.float32)),
            "rotation": torch.from_numpy(rotation.astype(np.float32)),
            "scene": torch.tensor([self.store.scenes[d[0]].index for d in draws]),
        }
