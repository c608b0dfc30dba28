"""What the measurements of ``stillbox-gen stats`` share: the two pixel parts, the dataset
opened once, frames in the channel order the sums use, and means of empty sets."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..dataset import Dataset

PARTS = ("walls", "objects")


def open_dataset(root: Path | Dataset) -> Dataset:
    """The dataset at ``root`` (a Dataset is used as it is, so its files are read once)."""
    return root if isinstance(root, Dataset) else Dataset(root)


def bgr(rgb: np.ndarray) -> np.ndarray:
    """A frame in BGR order: the figures sum channels in that order (another order could move
    the last digits of float sums)."""
    return rgb[..., ::-1]


def mean_or_none(total: float, count: int) -> float | None:
    """``total / count``, None for an empty set."""
    return float(total / count) if count else None


def parts(wall: np.ndarray) -> tuple[tuple[str, np.ndarray], ...]:
    """(part, mask) of PARTS for a wall mask: walls, and objects (every other pixel)."""
    return (("walls", wall), ("objects", ~wall))
