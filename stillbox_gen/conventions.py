"""Conventions shared by the generator, the reader and the benchmark: depth range, the nominal
pair and the default dataset folder. Imports nothing of the project."""

from __future__ import annotations

from pathlib import Path

#: Frames between the two images of a nominal StillBox pair (i, i + 3): the benchmark's fixed
#: evaluation pairs, the displacement its depth targets are expressed for (3 frames of 0.1 m, as
#: in the thesis), and the shift of ``stillbox-gen stats``.
NOMINAL_SHIFT = 3

#: Metres. Depth is clipped to [0, MAX_DEPTH] for training and scoring (files hold it unclipped).
MAX_DEPTH = 100.0


def default_root(width: int, height: int) -> Path:
    """The generator's default ``--out`` for frames of width x height pixels:
    ``data/stillbox-<W>`` when square, ``data/stillbox-<W>x<H>`` otherwise (relative path)."""
    res = f"{width}" if width == height else f"{width}x{height}"
    return Path("data") / f"stillbox-{res}"
