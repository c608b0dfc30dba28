"""Command-line values as text -> Python values, for both command lines (no click here): each
parser raises ConfigError naming its flag, in one line. The benchmark may import this module
(it is part of the data contract of tests/test_imports.py)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .errors import ConfigError
from .layout import enclosing_dataset


def parse_resolution(value: str, flag: str = "--res") -> tuple[int, int]:
    """``N`` (square) or ``WxH`` -> (width, height) in pixels, both positive."""
    text = value.lower().strip()
    try:
        w, h = (int(v) for v in text.split("x")) if "x" in text else (int(text), int(text))
    except ValueError:
        raise ConfigError(f"{flag}: expected N or WxH in pixels, got '{value}'") from None
    if w <= 0 or h <= 0:
        raise ConfigError(f"{flag}: width and height must be positive, got '{value}'")
    return w, h


def parse_point(value: str, flag: str = "--principal-point") -> tuple[float, float]:
    """``CX,CY`` -> (cx, cy) in pixels."""
    try:
        cx, cy = (float(v) for v in value.split(","))
    except ValueError:
        raise ConfigError(f"{flag}: expected CX,CY in pixels, got '{value}'") from None
    return cx, cy


def parse_shares(value: str, flag: str = "--split") -> tuple[float, ...]:
    """``TRAIN,VAL,TEST`` -> the shares as floats (their sum and signs: config.validate)."""
    try:
        return tuple(float(v) for v in value.split(","))
    except ValueError:
        raise ConfigError(f"{flag}: expected TRAIN,VAL,TEST shares, got '{value}'") from None


def check_out_folder(
    out: Path,
    flag: str = "--out",
    error: type[Exception] = ConfigError,
    inside_dataset: bool = False,
) -> None:
    """A folder to write into (created later when missing) must not be a file, nor lie inside
    a dataset (whose `validate` would then report stray files) unless ``inside_dataset``:
    ``error`` (the command line's own one-line error) naming ``flag`` otherwise."""
    if out.exists() and not out.is_dir():
        raise error(f"{flag}: '{out}' is a file, not a folder")
    dataset = None if inside_dataset else enclosing_dataset(out)
    if dataset is not None:
        raise error(f"{flag}: '{out}' is inside the dataset '{dataset}'; write elsewhere")
    if problem := unwritable(out):
        raise error(f"{flag}: {problem}")


def unwritable(out: Path) -> str | None:
    """Why the folder ``out`` cannot be written into (created first when missing), found by
    making and removing a folder where it would be made (permissions alone do not tell: root
    may not write under /proc); None when it can."""
    existing = next((p for p in (out, *out.absolute().parents) if p.exists()), None)
    if existing is None or not existing.is_dir():
        return f"cannot create '{out}' ('{existing}' is not a folder)"
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".stillbox-probe-", dir=existing))
    except OSError as e:
        return f"cannot create '{out}' (cannot write into '{existing}': {e.strerror or e})"
    return None
