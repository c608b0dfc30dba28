"""Checkpoints read back: only what ``stillbox-bench`` writes, never code (docs/RUNS.md).

Checkpoints are written by ``runfolder.save_checkpoint`` (``Trainer.checkpoint`` decides what
goes in). Reading unpickles with ``torch.load(weights_only=True)``: tensors and plain data only.
A file that is not such a checkpoint, whose weights do not fit the network, or whose numbers
(displacement, shift, depth range, camera: :func:`check_metadata`) are unusable is a ValueError of
one line naming the file and the field it was given as (FieldError: ``ckpt``, ``resume``,
``pretrained``; the command line names the flag).
"""

from __future__ import annotations

import math
import pickle
import re
import warnings
from pathlib import Path

import torch

from . import registry
from .errors import FieldError


def first_line(e: Exception) -> str:
    """The first line of an exception's message (its type's name when it has none)."""
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


CHECKPOINT_KEYS = ("model", "model_name", "nominal_displacement")


def source_error(field: str | None, path: str | Path, *parts) -> ValueError:
    """A one-line error about the file ``path`` given as ``field`` (e.g. "ckpt"): a FieldError,
    or, without a field, a ValueError naming the file alone."""
    if field:
        return FieldError(field, *parts, where=f" {path}")
    return ValueError(f"{path}: " + "".join(map(str, parts)))


def load_checkpoint(path: str | Path, field: str | None = None) -> dict:
    """A checkpoint written by Trainer.checkpoint, unpickled with ``weights_only=True`` (tensors
    and plain data only: a file that would run code is refused, never executed).

    Anything else raises a ValueError of one line naming the file and ``field`` (e.g. "ckpt":
    :func:`source_error`).
    """
    try:
        with warnings.catch_warnings():  # e.g. "Detected pickle protocol 4" for foreign pickles
            warnings.simplefilter("ignore")
            ck = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise source_error(field, path, "no such checkpoint") from None
    except pickle.UnpicklingError as e:
        found = re.search(r"GLOBAL (\S+)", str(e))
        if found:
            raise source_error(
                field,
                path,
                "refused, it would run code or build objects other than tensors "
                f"({found.group(1)}); only checkpoints written by stillbox-bench are loaded",
            ) from None
        raise source_error(
            field, path, "not a readable checkpoint (corrupt or not a torch file)"
        ) from None
    except Exception as e:  # noqa: BLE001 - any reader failure is the file's fault
        raise source_error(field, path, f"not a readable checkpoint ({first_line(e)})") from None
    if isinstance(ck, dict) and ck and all(isinstance(v, torch.Tensor) for v in ck.values()):
        raise source_error(
            field,
            path,
            "a bare state_dict, not a stillbox-bench checkpoint (a dict with "
            f"{', '.join(map(repr, CHECKPOINT_KEYS))}, as 'run' writes)",
        )
    if not isinstance(ck, dict) or not all(k in ck for k in CHECKPOINT_KEYS):
        raise source_error(
            field,
            path,
            "not a stillbox-bench checkpoint (expected a dict with "
            f"{', '.join(map(repr, CHECKPOINT_KEYS))}, as 'run' writes)",
        )
    name = ck["model_name"]
    spec = registry.MODELS.get(name) if isinstance(name, str) else None
    if spec is None or not spec.trainable:
        raise source_error(field, path, f"unknown model name {name!r} in the checkpoint")
    if not isinstance(ck["model"], dict):
        raise source_error(field, path, "its 'model' entry is not a state_dict")
    check_metadata(ck, field, path)
    return ck


def _real(value) -> bool:
    """A finite int or float (not a bool)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _count(value) -> bool:
    """An int >= 1 (not a bool)."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 1


def check_metadata(ck: dict, field: str | None, path: str | Path) -> None:
    """The numbers a checkpoint's users rely on, checked once for every reader (eval, infer,
    eval-multishift, run --pretrained/--resume): ``nominal_displacement`` a finite number of
    metres > 0; optional ``shift`` an integer >= 1 (frames); ``depth_range`` [lo, hi] metres with
    0 <= lo < hi <= MAX_DEPTH; ``camera`` width and height integers >= 1 (pixels) and ``fov_deg``
    in (0, 180) degrees. Otherwise a ValueError of one line naming the file ``path``, the
    ``field`` it was given as (:func:`source_error`) and the checkpoint's entry."""
    from stillbox_gen.conventions import MAX_DEPTH

    def bad(entry: str, value, rule: str) -> ValueError:
        return source_error(field, path, f"its '{entry}' is {value!r}; it must be {rule}")

    d0 = ck["nominal_displacement"]
    if not (_real(d0) and d0 > 0):
        raise bad("nominal_displacement", d0, "a positive number of metres")
    if "shift" in ck and not _count(ck["shift"]):
        raise bad("shift", ck["shift"], "a frame shift of at least 1")
    if "depth_range" in ck:
        r = ck["depth_range"]
        ok = isinstance(r, (list, tuple)) and len(r) == 2 and all(map(_real, r))
        if not (ok and 0 <= r[0] < r[1] <= MAX_DEPTH):
            raise bad("depth_range", r, f"[lo, hi] metres with 0 <= lo < hi <= {MAX_DEPTH:g}")
    cam = ck.get("camera")
    if cam is not None:
        if not isinstance(cam, dict):
            raise bad("camera", cam, "a dict of width, height and fov_deg")
        for key in ("width", "height"):
            if not _count(cam.get(key)):
                raise bad(f"camera.{key}", cam.get(key), "a number of pixels of at least 1")
        fov = cam.get("fov_deg")
        if not (_real(fov) and 0 < fov < 180):
            raise bad("camera.fov_deg", fov, "a field of view in (0, 180) degrees")


def load_weights(
    model: torch.nn.Module, ck: dict, field: str | None, path: str | Path, name: str
) -> None:
    """``model.load_state_dict(ck["model"])`` for the network ``name``; weights that do not fit
    raise a one-line ValueError naming the file ``path`` given as ``field``
    (:func:`source_error`) and the first misfit tensor."""
    own, theirs = model.state_dict(), ck["model"]
    shape = [
        k
        for k in own
        if k in theirs
        and not (isinstance(theirs[k], torch.Tensor) and theirs[k].shape == own[k].shape)
    ]
    missing = [k for k in own if k not in theirs]
    unexpected = [k for k in theirs if k not in own]
    if shape or missing or unexpected:
        found = [(shape, "of another shape"), (missing, "missing"), (unexpected, "unexpected")]
        parts = [f"{len(keys)} {what}" for keys, what in found if keys]
        counts = ", ".join([parts[0].replace(" ", " tensors ", 1), *parts[1:]])
        if shape:
            k = shape[0]
            got = tuple(theirs[k].shape) if isinstance(theirs[k], torch.Tensor) else "no tensor"
            example = f"{k} is {got} instead of {tuple(own[k].shape)}"
        else:
            example = f"{(missing or unexpected)[0]} is {'missing' if missing else 'unexpected'}"
        source = ck.get("model_name")
        whose = "its weights" if source == name else f"weights of '{source}'"
        raise source_error(field, path, f"{whose} do not fit '{name}': {counts}; e.g. {example}")
    try:
        model.load_state_dict(theirs)
    except (RuntimeError, TypeError, ValueError) as e:
        raise source_error(
            field, path, f"weights do not load into '{name}' ({first_line(e)})"
        ) from None
