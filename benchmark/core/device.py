"""The torch device of a command: `--device` resolved once (training, scoring, inference)."""

from __future__ import annotations

import re

import torch

from .errors import FieldError


def resolve_device(name: str) -> torch.device:
    """``auto`` (CUDA when available), ``cpu``, ``cuda`` or ``cuda:N``; FieldError on ``device``
    otherwise."""
    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", name):
        raise FieldError("device", f"unknown device '{name}' (auto, cpu, cuda or cuda:N)")
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise FieldError("device", "no CUDA device is available", where=f" {name}")
    return torch.device(name)
